#include "records/record_store.hpp"

#include <sqlite3.h>
#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <cstring>
#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>
#include <thread>

#include "common/error.hpp"
#include "common/run_id.hpp"
#include "session/journal.hpp"

namespace posecal {

namespace {

using Json = nlohmann::json;

constexpr int kSchemaVersion = 1;
constexpr int kBusyTimeoutMs = 10'000;  // another station's transaction: wait, do not fail

// Version 1. A later version adds its statements to migrate() and raises kSchemaVersion.
constexpr const char* kSchemaV1 = R"sql(
CREATE TABLE runs (
  run_id TEXT PRIMARY KEY,
  station_id TEXT NOT NULL, operator_id TEXT NOT NULL, lens_id TEXT NOT NULL,
  camera_uri TEXT NOT NULL, camera_id TEXT NOT NULL, camera_vendor TEXT NOT NULL,
  camera_model TEXT NOT NULL, camera_serial TEXT NOT NULL, camera_device_version TEXT NOT NULL,
  posecal_version TEXT NOT NULL, abi_version TEXT NOT NULL,
  config TEXT NOT NULL,
  image_width INTEGER NOT NULL DEFAULT 0, image_height INTEGER NOT NULL DEFAULT 0,
  locked_settings TEXT NOT NULL DEFAULT '{}',
  started TEXT NOT NULL, finished TEXT NOT NULL DEFAULT '',
  state TEXT NOT NULL DEFAULT 'running',
  host TEXT NOT NULL DEFAULT '', pid INTEGER NOT NULL DEFAULT 0,
  pid_start TEXT NOT NULL DEFAULT '',
  note TEXT NOT NULL DEFAULT '',
  verdict TEXT NOT NULL DEFAULT '',
  expected_error_px REAL,
  result TEXT NOT NULL DEFAULT ''
);
CREATE TABLE keyframes (
  run_id TEXT NOT NULL REFERENCES runs(run_id),
  idx INTEGER NOT NULL,
  time TEXT NOT NULL,
  record TEXT NOT NULL,
  image_png BLOB,
  PRIMARY KEY (run_id, idx)
);
CREATE INDEX runs_by_camera ON runs(camera_model, lens_id, state);
)sql";

// This process as a record knows it: the host, the pid and the pid's start time (a pid alone
// is reused). A run left "running" by a process that no longer exists was killed.
struct Writer {
  std::string host;
  long long pid = 0;
  std::string start;
};

// The start time of process `pid` (field 22 of /proc/PID/stat, clock ticks since boot); "" if
// there is no such process.
std::string process_start(long long pid) {
  std::FILE* f = std::fopen(("/proc/" + std::to_string(pid) + "/stat").c_str(), "re");
  if (!f) return "";
  char buf[1024];
  const size_t n = std::fread(buf, 1, sizeof buf - 1, f);
  std::fclose(f);
  buf[n] = '\0';
  // The command name (field 2) is in parentheses and may hold spaces: count from its end.
  const char* p = std::strrchr(buf, ')');
  if (!p) return "";
  int field = 2;
  for (; *p && field < 22; ++p)
    if (*p == ' ') ++field;
  std::string start;
  for (; *p && *p != ' '; ++p) start += *p;
  return start;
}

Writer this_writer() {
  Writer w;
  char host[256] = {};
  if (::gethostname(host, sizeof host - 1) == 0) w.host = host;
  w.pid = static_cast<long long>(::getpid());
  w.start = process_start(w.pid);
  return w;
}

}  // namespace

struct RecordStore::Db {
  sqlite3* handle = nullptr;
  ~Db() {
    if (handle) sqlite3_close_v2(handle);
  }
};

namespace {

[[noreturn]] void fail(sqlite3* db, const std::string& location, const std::string& step) {
  throw Error(ErrorCode::kIo, "record store '" + location + "': " + step + ": " +
                                  (db ? sqlite3_errmsg(db) : "out of memory"));
}

// A prepared statement, finalised on every path.
class Statement {
 public:
  Statement(sqlite3* db, const std::string& location, const char* sql)
      : db_(db), location_(location) {
    if (sqlite3_prepare_v2(db, sql, -1, &stmt_, nullptr) != SQLITE_OK) fail(db, location, "prepare");
  }
  ~Statement() { sqlite3_finalize(stmt_); }
  Statement(const Statement&) = delete;
  Statement& operator=(const Statement&) = delete;

  Statement& text(int i, const std::string& v) {
    check(sqlite3_bind_text(stmt_, i, v.data(), static_cast<int>(v.size()), SQLITE_TRANSIENT));
    return *this;
  }
  Statement& integer(int i, long long v) {
    check(sqlite3_bind_int64(stmt_, i, v));
    return *this;
  }
  Statement& real(int i, std::optional<double> v) {
    check(v ? sqlite3_bind_double(stmt_, i, *v) : sqlite3_bind_null(stmt_, i));
    return *this;
  }
  Statement& blob(int i, const std::vector<unsigned char>& v) {
    check(v.empty() ? sqlite3_bind_null(stmt_, i)
                    : sqlite3_bind_blob(stmt_, i, v.data(), static_cast<int>(v.size()),
                                        SQLITE_TRANSIENT));
    return *this;
  }
  // true while there is a row.
  bool step() {
    const int rc = sqlite3_step(stmt_);
    if (rc == SQLITE_ROW) return true;
    if (rc == SQLITE_DONE) return false;
    fail(db_, location_, "write");
  }
  std::string column_text(int i) const {
    const unsigned char* t = sqlite3_column_text(stmt_, i);
    return t ? std::string(reinterpret_cast<const char*>(t),
                           static_cast<size_t>(sqlite3_column_bytes(stmt_, i)))
             : std::string();
  }
  long long column_int(int i) const { return sqlite3_column_int64(stmt_, i); }
  std::optional<double> column_real(int i) const {
    if (sqlite3_column_type(stmt_, i) == SQLITE_NULL) return std::nullopt;
    return sqlite3_column_double(stmt_, i);
  }
  std::vector<unsigned char> column_blob(int i) const {
    const auto* p = static_cast<const unsigned char*>(sqlite3_column_blob(stmt_, i));
    return p ? std::vector<unsigned char>(p, p + sqlite3_column_bytes(stmt_, i))
             : std::vector<unsigned char>();
  }

 private:
  void check(int rc) {
    if (rc != SQLITE_OK) fail(db_, location_, "bind");
  }
  sqlite3* db_;
  const std::string& location_;
  sqlite3_stmt* stmt_ = nullptr;
};

void exec(sqlite3* db, const std::string& location, const char* sql, const char* step) {
  char* err = nullptr;
  if (sqlite3_exec(db, sql, nullptr, nullptr, &err) != SQLITE_OK) {
    const std::string why = err ? err : sqlite3_errmsg(db);
    sqlite3_free(err);
    throw Error(ErrorCode::kIo, "record store '" + location + "': " + step + ": " + why);
  }
}

// BEGIN IMMEDIATE ... COMMIT, rolled back on any exception.
class Transaction {
 public:
  Transaction(sqlite3* db, const std::string& location) : db_(db), location_(location) {
    exec(db_, location_, "BEGIN IMMEDIATE", "begin a transaction");
  }
  void commit() {
    exec(db_, location_, "COMMIT", "commit");
    done_ = true;
  }
  ~Transaction() {
    if (!done_) sqlite3_exec(db_, "ROLLBACK", nullptr, nullptr, nullptr);
  }

 private:
  sqlite3* db_;
  const std::string& location_;
  bool done_ = false;
};

int schema_version(sqlite3* db, const std::string& location) {
  Statement has(db, location,
                "SELECT count(*) FROM sqlite_master WHERE type = 'table' AND name = 'posecal_schema'");
  has.step();
  if (has.column_int(0) == 0) {
    Statement any(db, location, "SELECT count(*) FROM sqlite_master");
    any.step();
    if (any.column_int(0) != 0) {
      throw Error(ErrorCode::kIo, "record store '" + location +
                                      "': a database of something else (no posecal_schema table)");
    }
    return 0;
  }
  Statement v(db, location, "SELECT max(version) FROM posecal_schema");
  v.step();
  return static_cast<int>(v.column_int(0));
}

void migrate(sqlite3* db, const std::string& location) {
  Transaction t(db, location);
  const int version = schema_version(db, location);
  if (version > kSchemaVersion) {
    throw Error(ErrorCode::kInvalidArgument,
                "record store '" + location + "' has schema version " + std::to_string(version) +
                    "; this posecal reads up to " + std::to_string(kSchemaVersion) +
                    " (a newer posecal wrote it)");
  }
  if (version == 0) {
    exec(db, location, "CREATE TABLE posecal_schema (version INTEGER NOT NULL, applied TEXT NOT NULL)",
         "create the schema table");
    exec(db, location, kSchemaV1, "create schema version 1");
    exec(db, location, "INSERT INTO posecal_schema VALUES (1, strftime('%Y-%m-%dT%H:%M:%SZ', 'now'))",
         "record schema version 1");
  }
  t.commit();
}

// Runs a setup step of open() again while it fails on another connection's lock, for up to
// kBusyTimeoutMs. The busy handler does not cover every lock: switching a new database to WAL
// while another connection (a station's other camera) creates it fails with SQLITE_BUSY at once
// (seen in CI: four cameras opening one new file).
template <class Step>
void setup_with_retry(sqlite3* db, Step&& step) {
  const auto deadline =
      std::chrono::steady_clock::now() + std::chrono::milliseconds(kBusyTimeoutMs);
  for (;;) {
    try {
      step();
      return;
    } catch (const Error&) {
      const int rc = sqlite3_errcode(db) & 0xff;
      if ((rc != SQLITE_BUSY && rc != SQLITE_LOCKED) ||
          std::chrono::steady_clock::now() > deadline) {
        throw;
      }
      std::this_thread::sleep_for(std::chrono::milliseconds(20));
    }
  }
}

const char* kSummaryColumns =
    "r.run_id, r.station_id, r.operator_id, r.lens_id, r.camera_uri, r.camera_id, "
    "r.camera_vendor, r.camera_model, r.camera_serial, r.camera_device_version, "
    "r.posecal_version, r.abi_version, r.config, r.started, r.state, r.finished, r.verdict, "
    "r.expected_error_px, (SELECT count(*) FROM keyframes k WHERE k.run_id = r.run_id), r.note";

RunSummary summary_of(const Statement& s) {
  RunSummary r;
  RunIdentity& id = r.identity;
  int i = 0;
  for (std::string* f : {&id.run_id, &id.station_id, &id.operator_id, &id.lens_id, &id.camera_uri,
                         &id.camera_id, &id.camera_vendor, &id.camera_model, &id.camera_serial,
                         &id.camera_device_version, &id.posecal_version, &id.abi_version,
                         &id.config, &id.started, &r.state, &r.finished, &r.verdict}) {
    *f = s.column_text(i++);
  }
  r.expected_error_px = s.column_real(i++);
  r.keyframes = static_cast<int>(s.column_int(i++));
  r.note = s.column_text(i++);
  return r;
}

}  // namespace

RecordStore::RecordStore(std::string location, std::unique_ptr<Db> db)
    : location_(std::move(location)), db_(std::move(db)) {}
RecordStore::~RecordStore() = default;

std::unique_ptr<RecordStore> RecordStore::open(const std::string& location) {
  if (location.empty()) throw Error(ErrorCode::kInvalidArgument, "record store: an empty location");
  if (location.rfind("postgresql://", 0) == 0 || location.rfind("postgres://", 0) == 0) {
    throw Error(ErrorCode::kUnsupported,
                "record store '" + location +
                    "': PostgreSQL stores are not built yet (issue 15); use a SQLite file path");
  }
  auto db = std::make_unique<Db>();
  const int rc = sqlite3_open_v2(location.c_str(), &db->handle,
                                 SQLITE_OPEN_READWRITE | SQLITE_OPEN_CREATE | SQLITE_OPEN_FULLMUTEX |
                                     SQLITE_OPEN_NOFOLLOW,
                                 nullptr);
  if (rc != SQLITE_OK) fail(db->handle, location, "open");
  sqlite3_extended_result_codes(db->handle, 1);
  sqlite3_busy_timeout(db->handle, kBusyTimeoutMs);
  // WAL: readers do not block the writer, and a crash loses at most the transaction in flight.
  // FULL synchronous: a committed keyframe survives a power cut, as the journal's fdatasync.
  sqlite3* h = db->handle;
  setup_with_retry(h, [&] { exec(h, location, "PRAGMA journal_mode = WAL", "switch to WAL"); });
  exec(h, location, "PRAGMA synchronous = FULL", "set synchronous");
  exec(h, location, "PRAGMA foreign_keys = ON", "enable foreign keys");
  setup_with_retry(h, [&] { migrate(h, location); });
  return std::unique_ptr<RecordStore>(new RecordStore(location, std::move(db)));
}

void RecordStore::begin_run(const RunIdentity& r) {
  const Writer me = this_writer();
  Transaction t(db_->handle, location_);
  {
    // Runs of this host left "running" by a process that is gone were killed (kill -9, a power
    // cut): they are marked so, with what they kept.
    Statement running(db_->handle, location_,
                      "SELECT run_id, pid, pid_start FROM runs WHERE state = 'running' AND host = ?");
    running.text(1, me.host);
    std::vector<std::pair<std::string, long long>> dead;
    while (running.step()) {
      const long long pid = running.column_int(1);
      if (pid > 0 && process_start(pid) != running.column_text(2))
        dead.emplace_back(running.column_text(0), pid);
    }
    for (const auto& [id, pid] : dead) {
      Statement mark(db_->handle, location_,
                     "UPDATE runs SET state = 'killed', note = ?, "
                     "finished = strftime('%Y-%m-%dT%H:%M:%SZ', 'now') WHERE run_id = ?");
      mark.text(1, "its process (pid " + std::to_string(pid) +
                       ") ended without finishing the run; found when run " + r.run_id + " began")
          .text(2, id)
          .step();
    }
  }
  Statement exists(db_->handle, location_, "SELECT count(*) FROM runs WHERE run_id = ?");
  exists.text(1, r.run_id).step();
  if (exists.column_int(0) != 0) {
    throw Error(ErrorCode::kInvalidArgument,
                "record store '" + location_ + "': run id " + r.run_id + " is already recorded");
  }
  Statement s(db_->handle, location_,
              "INSERT INTO runs (run_id, station_id, operator_id, lens_id, camera_uri, camera_id, "
              "camera_vendor, camera_model, camera_serial, camera_device_version, "
              "posecal_version, abi_version, config, started, host, pid, pid_start) "
              "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)");
  int i = 1;
  for (const std::string* f : {&r.run_id, &r.station_id, &r.operator_id, &r.lens_id,
                               &r.camera_uri, &r.camera_id, &r.camera_vendor, &r.camera_model,
                               &r.camera_serial, &r.camera_device_version, &r.posecal_version,
                               &r.abi_version, &r.config, &r.started}) {
    s.text(i++, *f);
  }
  s.text(i, me.host).integer(i + 1, me.pid).text(i + 2, me.start);
  s.step();
  t.commit();
}

void RecordStore::set_engine(const std::string& run_id, cv::Size size,
                             const std::map<std::string, std::string>& locked) {
  Transaction t(db_->handle, location_);
  Statement s(db_->handle, location_,
              "UPDATE runs SET image_width = ?, image_height = ?, locked_settings = ? "
              "WHERE run_id = ?");
  s.integer(1, size.width)
      .integer(2, size.height)
      .text(3, Json(locked).dump(-1, ' ', false, Json::error_handler_t::replace))
      .text(4, run_id)
      .step();
  t.commit();
}

void RecordStore::add_keyframe(const std::string& run_id, int index, const KeyframeRecord& record,
                               const cv::Mat& image) {
  const std::string text = keyframe_json(index, record);
  std::vector<unsigned char> png;
  if (!image.empty() && !cv::imencode(".png", image, png)) png.clear();
  Transaction t(db_->handle, location_);
  // INSERT OR REPLACE: a session resumed from its journal records a keyframe again under the
  // same run id only if it was lost here.
  Statement s(db_->handle, location_,
              "INSERT OR REPLACE INTO keyframes (run_id, idx, time, record, image_png) "
              "VALUES (?, ?, ?, ?, ?)");
  s.text(1, run_id)
      .integer(2, index)
      .text(3, Json::parse(text).value("time", ""))
      .text(4, text)
      .blob(5, png)
      .step();
  t.commit();
}

void RecordStore::finish_run(const std::string& run_id, const std::string& state,
                             const std::string& result_json, const std::string& verdict,
                             std::optional<double> expected_error_px) {
  Transaction t(db_->handle, location_);
  Statement s(db_->handle, location_,
              "UPDATE runs SET state = ?, result = ?, verdict = ?, expected_error_px = ?, "
              "finished = strftime('%Y-%m-%dT%H:%M:%SZ', 'now') WHERE run_id = ?");
  s.text(1, state).text(2, result_json).text(3, verdict).real(4, expected_error_px).text(5, run_id);
  s.step();
  t.commit();
}

std::vector<RunSummary> RecordStore::list_runs() const {
  Statement s(db_->handle, location_,
              (std::string("SELECT ") + kSummaryColumns +
               " FROM runs r ORDER BY r.started DESC, r.rowid DESC")
                  .c_str());
  std::vector<RunSummary> out;
  while (s.step()) out.push_back(summary_of(s));
  return out;
}

RunRecord RecordStore::get_run(const std::string& run_id) const {
  if (run_id.empty()) throw Error(ErrorCode::kInvalidArgument, "records: an empty run id");
  Statement s(db_->handle, location_,
              (std::string("SELECT ") + kSummaryColumns +
               ", r.image_width, r.image_height, r.locked_settings, r.result FROM runs r "
               "WHERE substr(r.run_id, 1, length(?1)) = ?1")
                  .c_str());
  s.text(1, run_id);
  if (!s.step()) {
    throw Error(ErrorCode::kNotFound,
                "record store '" + location_ + "' has no run " + run_id);
  }
  RunRecord r;
  r.summary = summary_of(s);
  r.image_width = static_cast<int>(s.column_int(20));
  r.image_height = static_cast<int>(s.column_int(21));
  const Json locked = Json::parse(s.column_text(22), nullptr, false);
  if (locked.is_object()) {
    for (const auto& [k, v] : locked.items()) r.locked_settings[k] = v.is_string() ? v.get<std::string>() : v.dump();
  }
  r.result = s.column_text(23);
  if (s.step()) {
    throw Error(ErrorCode::kInvalidArgument,
                "records: run id " + run_id + " is ambiguous in '" + location_ + "'");
  }
  Statement k(db_->handle, location_,
              "SELECT idx, time, record, image_png FROM keyframes WHERE run_id = ? ORDER BY idx");
  k.text(1, r.summary.identity.run_id);
  while (k.step()) {
    StoredKeyframe f;
    f.index = static_cast<int>(k.column_int(0));
    f.time = k.column_text(1);
    f.record = k.column_text(2);
    f.image_png = k.column_blob(3);
    r.keyframes.push_back(std::move(f));
  }
  return r;
}

}  // namespace posecal
