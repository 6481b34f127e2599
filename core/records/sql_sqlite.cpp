// The SQLite side of core/records/sql.hpp.
#include <sqlite3.h>

#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <thread>

#include "common/error.hpp"
#include "records/sql.hpp"

namespace posecal::sql {

long long Cell::integer() const { return null ? 0 : std::strtoll(bytes.c_str(), nullptr, 10); }

std::optional<double> Cell::real() const {
  if (null) return std::nullopt;
  return std::strtod(bytes.c_str(), nullptr);
}

void Connection::fail(const char* step, const std::string& why) const {
  throw Error(ErrorCode::kIo, "record store '" + location_ + "': " + step + ": " + why);
}

namespace {

const Dialect kSqlite{"sqlite", "INTEGER", "REAL", "BLOB", "r.rowid", ""};

class SqliteConnection final : public Connection {
 public:
  SqliteConnection(const std::string& path, sqlite3* db) : Connection(path), db_(db) {}
  ~SqliteConnection() override { sqlite3_close_v2(db_); }

  const Dialect& dialect() const override { return kSqlite; }

  void script(const std::string& sql, const char* step) override {
    char* err = nullptr;
    if (sqlite3_exec(db_, sql.c_str(), nullptr, nullptr, &err) != SQLITE_OK) {
      const std::string why = err ? err : sqlite3_errmsg(db_);
      sqlite3_free(err);
      fail(step, why);
    }
  }

  std::vector<Row> query(const std::string& sql, const std::vector<Value>& params,
                         const char* step) override {
    sqlite3_stmt* stmt = nullptr;
    if (sqlite3_prepare_v2(db_, sql.c_str(), -1, &stmt, nullptr) != SQLITE_OK)
      fail(step, sqlite3_errmsg(db_));
    struct Finalize {
      sqlite3_stmt* s;
      ~Finalize() { sqlite3_finalize(s); }
    } finalize{stmt};
    for (size_t i = 0; i < params.size(); ++i) {
      const int at = static_cast<int>(i) + 1;
      const Value& v = params[i];
      int rc = SQLITE_OK;
      if (std::holds_alternative<std::nullptr_t>(v)) {
        rc = sqlite3_bind_null(stmt, at);
      } else if (const auto* n = std::get_if<long long>(&v)) {
        rc = sqlite3_bind_int64(stmt, at, *n);
      } else if (const auto* d = std::get_if<double>(&v)) {
        rc = sqlite3_bind_double(stmt, at, *d);
      } else if (const auto* t = std::get_if<std::string>(&v)) {
        rc = sqlite3_bind_text(stmt, at, t->data(), static_cast<int>(t->size()), SQLITE_TRANSIENT);
      } else {
        const Blob& b = std::get<Blob>(v);
        rc = b.empty() ? sqlite3_bind_null(stmt, at)
                       : sqlite3_bind_blob(stmt, at, b.data(), static_cast<int>(b.size()),
                                           SQLITE_TRANSIENT);
      }
      if (rc != SQLITE_OK) fail(step, sqlite3_errmsg(db_));
    }
    std::vector<Row> rows;
    for (;;) {
      const int rc = sqlite3_step(stmt);
      if (rc == SQLITE_DONE) break;
      if (rc != SQLITE_ROW) fail(step, sqlite3_errmsg(db_));
      Row row(static_cast<size_t>(sqlite3_column_count(stmt)));
      for (int c = 0; c < static_cast<int>(row.size()); ++c) {
        Cell& cell = row[static_cast<size_t>(c)];
        switch (sqlite3_column_type(stmt, c)) {
          case SQLITE_NULL:
            break;
          case SQLITE_FLOAT: {
            char buf[40];
            std::snprintf(buf, sizeof buf, "%.17g", sqlite3_column_double(stmt, c));
            cell = {false, buf};
            break;
          }
          default: {
            const auto* p = static_cast<const char*>(sqlite3_column_blob(stmt, c));
            cell = {false, p ? std::string(p, static_cast<size_t>(sqlite3_column_bytes(stmt, c)))
                             : std::string()};
          }
        }
      }
      rows.push_back(std::move(row));
    }
    return rows;
  }

  void begin() override { script("BEGIN IMMEDIATE", "begin a transaction"); }
  void commit() override { script("COMMIT", "commit"); }
  void rollback() noexcept override { sqlite3_exec(db_, "ROLLBACK", nullptr, nullptr, nullptr); }

  bool has_table(const std::string& name) override {
    return query("SELECT count(*) FROM sqlite_master WHERE type = 'table' AND name = ?", {name},
                 "read the schema")[0][0]
               .integer() != 0;
  }
  bool empty() override {
    return query("SELECT count(*) FROM sqlite_master", {}, "read the schema")[0][0].integer() == 0;
  }
  void lock_setup() override {}
  bool last_error_was_busy() const override {
    const int rc = sqlite3_errcode(db_) & 0xff;
    return rc == SQLITE_BUSY || rc == SQLITE_LOCKED;
  }

 private:
  sqlite3* db_;
};

}  // namespace

std::unique_ptr<Connection> open_sqlite(const std::string& path, int busy_timeout_ms) {
  sqlite3* db = nullptr;
  const int rc = sqlite3_open_v2(
      path.c_str(), &db,
      SQLITE_OPEN_READWRITE | SQLITE_OPEN_CREATE | SQLITE_OPEN_FULLMUTEX | SQLITE_OPEN_NOFOLLOW,
      nullptr);
  // The connection owns the handle from here (sqlite3_open_v2 returns one even on failure).
  auto c = std::make_unique<SqliteConnection>(path, db);
  if (rc != SQLITE_OK) {
    throw Error(ErrorCode::kIo, "record store '" + path +
                                    "': open: " + (db ? sqlite3_errmsg(db) : "out of memory"));
  }
  sqlite3_extended_result_codes(db, 1);
  sqlite3_busy_timeout(db, busy_timeout_ms);
  // WAL: readers do not block the writer, and a crash loses at most the transaction in flight.
  // Switching a new file to WAL while another connection (a station's other camera) creates it
  // fails with SQLITE_BUSY at once, past the busy handler (seen in CI): retried for the timeout.
  const auto deadline =
      std::chrono::steady_clock::now() + std::chrono::milliseconds(busy_timeout_ms);
  for (;;) {
    try {
      c->script("PRAGMA journal_mode = WAL", "switch to WAL");
      break;
    } catch (const Error&) {
      if (!c->last_error_was_busy() || std::chrono::steady_clock::now() > deadline) throw;
      std::this_thread::sleep_for(std::chrono::milliseconds(20));
    }
  }
  // FULL synchronous: a committed keyframe survives a power cut, as the journal's fdatasync.
  c->script("PRAGMA synchronous = FULL", "set synchronous");
  c->script("PRAGMA foreign_keys = ON", "enable foreign keys");
  return c;
}

}  // namespace posecal::sql
