// The PostgreSQL side of core/records/sql.hpp (libpq).
#include "records/sql.hpp"

#include <libpq-fe.h>

#include <cstdio>

#include "common/error.hpp"

namespace posecal::sql {

namespace {

// Type OIDs of the parameters bound (pg_type.h is a server header: the values are fixed).
constexpr Oid kInt8 = 20, kFloat8 = 701, kText = 25, kBytea = 17;

// The key of the advisory lock that serialises the set-up of a new database.
constexpr long long kSetupLockKey = 0x706f736563616cLL;  // "posecal"

const Dialect kPostgresql{"postgresql", "BIGINT", "DOUBLE PRECISION",
                          "BYTEA",      "r.seq",  "seq BIGSERIAL NOT NULL,"};

// `?` placeholders numbered as PostgreSQL wants them.
std::string numbered(const std::string& sql) {
  std::string out;
  int n = 0;
  for (char ch : sql) {
    if (ch == '?') {
      out += '$' + std::to_string(++n);
    } else {
      out += ch;
    }
  }
  return out;
}

void ignore_notice(void*, const char*) {}

class PgConnection final : public Connection {
 public:
  PgConnection(const std::string& location, PGconn* conn) : Connection(location), conn_(conn) {}
  ~PgConnection() override { PQfinish(conn_); }

  const Dialect& dialect() const override { return kPostgresql; }

  void script(const std::string& sql, const char* step) override {
    Result r(PQexec(conn_, sql.c_str()));
    check(r.get(), step);
  }

  std::vector<Row> query(const std::string& sql, const std::vector<Value>& params,
                         const char* step) override {
    std::vector<Oid> types;
    std::vector<std::string> texts(params.size());
    std::vector<const char*> values;
    std::vector<int> lengths, formats;
    for (size_t i = 0; i < params.size(); ++i) {
      const Value& v = params[i];
      Oid type = kText;
      const char* value = nullptr;
      int length = 0, format = 0;
      if (std::holds_alternative<std::nullptr_t>(v)) {
        type = 0;  // NULL: the server infers the column's type
      } else if (const auto* n = std::get_if<long long>(&v)) {
        type = kInt8;
        texts[i] = std::to_string(*n);
      } else if (const auto* d = std::get_if<double>(&v)) {
        type = kFloat8;
        char buf[40];
        std::snprintf(buf, sizeof buf, "%.17g", *d);
        texts[i] = buf;
      } else if (const auto* t = std::get_if<std::string>(&v)) {
        texts[i] = *t;
      } else if (const auto* b = std::get_if<Blob>(&v)) {
        type = kBytea;
        format = 1;  // binary: the bytes as they are
        if (!b->empty()) {
          value = reinterpret_cast<const char*>(b->data());
          length = static_cast<int>(b->size());
        }
      }
      const bool null = std::holds_alternative<std::nullptr_t>(v) ||
                        (std::holds_alternative<Blob>(v) && std::get<Blob>(v).empty());
      if (!null && format == 0) value = texts[i].c_str();
      types.push_back(type);
      values.push_back(value);
      lengths.push_back(length);
      formats.push_back(format);
    }
    Result r(PQexecParams(conn_, numbered(sql).c_str(), static_cast<int>(params.size()),
                          types.data(), values.data(), lengths.data(), formats.data(), 0));
    check(r.get(), step);
    std::vector<Row> rows;
    const int n = PQntuples(r.get()), fields = PQnfields(r.get());
    for (int i = 0; i < n; ++i) {
      Row row(static_cast<size_t>(fields));
      for (int c = 0; c < fields; ++c) {
        if (PQgetisnull(r.get(), i, c)) continue;
        Cell& cell = row[static_cast<size_t>(c)];
        cell.null = false;
        const char* text = PQgetvalue(r.get(), i, c);
        if (PQftype(r.get(), c) == kBytea) {
          size_t size = 0;
          unsigned char* raw = PQunescapeBytea(reinterpret_cast<const unsigned char*>(text), &size);
          if (!raw) fail(step, "out of memory decoding a bytea");
          cell.bytes.assign(reinterpret_cast<const char*>(raw), size);
          PQfreemem(raw);
        } else {
          cell.bytes.assign(text, static_cast<size_t>(PQgetlength(r.get(), i, c)));
        }
      }
      rows.push_back(std::move(row));
    }
    return rows;
  }

  void begin() override { script("BEGIN", "begin a transaction"); }
  void commit() override { script("COMMIT", "commit"); }
  void rollback() noexcept override {
    if (PQstatus(conn_) == CONNECTION_OK) PQclear(PQexec(conn_, "ROLLBACK"));
  }

  bool has_table(const std::string& name) override {
    return query(
               "SELECT count(*) FROM information_schema.tables "
               "WHERE table_schema = current_schema() AND table_name = ?",
               {name}, "read the schema")[0][0]
               .integer() != 0;
  }
  bool empty() override {
    return query(
               "SELECT count(*) FROM information_schema.tables "
               "WHERE table_schema = current_schema()",
               {}, "read the schema")[0][0]
               .integer() == 0;
  }
  void lock_setup() override {
    query("SELECT pg_advisory_xact_lock(?)", {kSetupLockKey}, "lock the set-up");
  }
  bool last_error_was_busy() const override { return false; }

 private:
  struct Result {
    explicit Result(PGresult* r) : r_(r) {}
    ~Result() { PQclear(r_); }
    Result(const Result&) = delete;
    Result& operator=(const Result&) = delete;
    PGresult* get() const { return r_; }
    PGresult* r_;
  };

  void check(PGresult* r, const char* step) const {
    const ExecStatusType s = r ? PQresultStatus(r) : PGRES_FATAL_ERROR;
    if (s == PGRES_COMMAND_OK || s == PGRES_TUPLES_OK) return;
    std::string why = r ? PQresultErrorMessage(r) : "";
    if (why.empty()) why = PQerrorMessage(conn_);
    while (!why.empty() && (why.back() == '\n' || why.back() == ' ')) why.pop_back();
    if (PQstatus(conn_) != CONNECTION_OK) why += " (the connection to the server is lost)";
    fail(step, why);
  }

  PGconn* conn_;
};

}  // namespace

std::string redact_url(const std::string& url) {
  std::string out = url;
  const size_t scheme = out.find("://");
  if (scheme != std::string::npos) {
    const size_t start = scheme + 3;
    const size_t end = out.find_first_of("/?", start);
    const size_t at = out.rfind('@', end == std::string::npos ? std::string::npos : end);
    if (at != std::string::npos && at >= start) {
      const size_t colon = out.find(':', start);
      if (colon != std::string::npos && colon < at) out.replace(colon + 1, at - colon - 1, "***");
    }
  }
  for (size_t p = out.find("password="); p != std::string::npos; p = out.find("password=", p + 1)) {
    const size_t v = p + 9;
    const size_t e = out.find('&', v);
    out.replace(v, (e == std::string::npos ? out.size() : e) - v, "***");
  }
  return out;
}

std::unique_ptr<Connection> open_postgresql(const std::string& url, int busy_timeout_ms) {
  const std::string location = redact_url(url);
  // Bounds first, so that the URL's own settings override them: a connect that cannot
  // complete, a server that stops answering mid-transaction (TCP keepalives and
  // tcp_user_timeout) and a statement or lock that waits too long all end in an error.
  const std::string options =
      "-c statement_timeout=60000 -c lock_timeout=" + std::to_string(busy_timeout_ms) +
      " -c idle_in_transaction_session_timeout=60000";
  const char* keys[] = {"connect_timeout",  "keepalives",
                        "keepalives_idle",  "keepalives_interval",
                        "keepalives_count", "tcp_user_timeout",
                        "options",          "application_name",
                        "dbname",           nullptr};
  const char* values[] = {"10",      "1",         "5",    "2", "3", "15000", options.c_str(),
                          "posecal", url.c_str(), nullptr};
  PGconn* conn = PQconnectdbParams(keys, values, 1);
  if (!conn) throw Error(ErrorCode::kIo, "record store '" + location + "': connect: out of memory");
  auto c = std::make_unique<PgConnection>(location, conn);
  if (PQstatus(conn) != CONNECTION_OK) {
    std::string why = PQerrorMessage(conn);
    while (!why.empty() && (why.back() == '\n' || why.back() == ' ')) why.pop_back();
    throw Error(ErrorCode::kIo, "record store '" + location + "': connect: " + why);
  }
  PQsetNoticeProcessor(conn, ignore_notice, nullptr);
  return c;
}

}  // namespace posecal::sql
