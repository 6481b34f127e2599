// The two SQL databases records are kept in, behind one small interface (record_store.cpp is
// written once against it): SQLite for a file, PostgreSQL (libpq) for a `postgresql://` URL.
//
// Statements are written with `?` placeholders (never inside a string literal); the PostgreSQL
// connection numbers them ($1, $2, ...). Results are read whole: a row is a vector of cells,
// each NULL or the value's bytes (text as is, numbers in decimal with every digit, blobs raw).
// Every failure throws Error(kIo) naming the store, the step and the database's own message.
#pragma once

#include <memory>
#include <optional>
#include <string>
#include <variant>
#include <vector>

namespace posecal::sql {

using Blob = std::vector<unsigned char>;
// A bound parameter: NULL, an integer, a double, text or a blob.
using Value = std::variant<std::nullptr_t, long long, double, std::string, Blob>;

struct Cell {
  bool null = true;
  std::string bytes;

  const std::string& text() const { return bytes; }
  long long integer() const;           // 0 for NULL
  std::optional<double> real() const;  // nullopt for NULL
  Blob blob() const { return Blob(bytes.begin(), bytes.end()); }
};
using Row = std::vector<Cell>;

// How the two dialects spell what differs in the schema and in queries.
struct Dialect {
  const char* name;              // "sqlite" or "postgresql"
  const char* integer;           // a 64-bit integer column
  const char* real;              // an IEEE double column
  const char* blob;              // a byte-string column
  const char* run_order;         // a column of runs that grows with each insert (list order)
  const char* run_order_column;  // its declaration in the runs table ("" if implicit)
};

class Connection {
 public:
  virtual ~Connection() = default;
  virtual const Dialect& dialect() const = 0;
  const std::string& location() const { return location_; }

  // Runs statements without parameters or results (a script of several is allowed).
  virtual void script(const std::string& sql, const char* step) = 0;
  // One statement with `?` parameters; every row of its result.
  virtual std::vector<Row> query(const std::string& sql, const std::vector<Value>& params,
                                 const char* step) = 0;

  // A write transaction: SQLite takes the write lock at once (BEGIN IMMEDIATE), so two
  // writers queue instead of failing when they upgrade. Rolls back what is not committed.
  virtual void begin() = 0;
  virtual void commit() = 0;
  virtual void rollback() noexcept = 0;

  // Whether a table of this name exists / whether the database holds no table at all.
  virtual bool has_table(const std::string& name) = 0;
  virtual bool empty() = 0;
  // Inside a transaction: serialises the first set-up of a new database between connections
  // (PostgreSQL: a transaction-level advisory lock; SQLite: the write lock is already held).
  virtual void lock_setup() = 0;
  // After an Error from a set-up step: whether it was another connection's lock (retry).
  virtual bool last_error_was_busy() const = 0;

 protected:
  explicit Connection(std::string location) : location_(std::move(location)) {}
  [[noreturn]] void fail(const char* step, const std::string& why) const;

 private:
  std::string location_;
};

// A SQLite file, created if missing (never through a symbolic link); WAL mode, synchronous
// FULL, a busy timeout of `busy_timeout_ms`.
std::unique_ptr<Connection> open_sqlite(const std::string& path, int busy_timeout_ms);

// A PostgreSQL server by URL (postgresql://user@host:port/db?...). Bounded: connect_timeout,
// TCP keepalives and tcp_user_timeout so a server that goes away is noticed within seconds, and
// statement and lock timeouts (the URL may set its own).
std::unique_ptr<Connection> open_postgresql(const std::string& url, int busy_timeout_ms);

// A URL with its password replaced by "***", for messages and records.
std::string redact_url(const std::string& url);

// BEGIN ... COMMIT, rolled back on any exception.
class Transaction {
 public:
  explicit Transaction(Connection& c) : c_(c) { c_.begin(); }
  void commit() {
    c_.commit();
    done_ = true;
  }
  ~Transaction() {
    if (!done_) c_.rollback();
  }
  Transaction(const Transaction&) = delete;
  Transaction& operator=(const Transaction&) = delete;

 private:
  Connection& c_;
  bool done_ = false;
};

}  // namespace posecal::sql
