#include "records/record_store.hpp"

#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <cstring>
#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>
#include <thread>

#include "common/clock.hpp"
#include "common/error.hpp"
#include "common/run_id.hpp"
#include "records/sql.hpp"
#include "session/journal.hpp"

namespace posecal {

namespace {

using Json = nlohmann::json;

constexpr int kSchemaVersion = 1;
constexpr int kBusyTimeoutMs = 10'000;  // another station's transaction: wait, do not fail

// Version 1. A later version adds its statements to migrate() and raises kSchemaVersion.
// Version 1, in the dialect's column types. A later version adds its statements to migrate()
// and raises kSchemaVersion.
std::string schema_v1(const sql::Dialect& d) {
  const std::string i = d.integer, r = d.real, b = d.blob;
  return std::string("CREATE TABLE runs (\n") + d.run_order_column +
         R"sql(
  run_id TEXT PRIMARY KEY,
  station_id TEXT NOT NULL, operator_id TEXT NOT NULL, lens_id TEXT NOT NULL,
  camera_uri TEXT NOT NULL, camera_id TEXT NOT NULL, camera_vendor TEXT NOT NULL,
  camera_model TEXT NOT NULL, camera_serial TEXT NOT NULL, camera_device_version TEXT NOT NULL,
  posecal_version TEXT NOT NULL, abi_version TEXT NOT NULL,
  config TEXT NOT NULL,
  image_width )sql" +
         i + R"sql( NOT NULL DEFAULT 0, image_height )sql" + i + R"sql( NOT NULL DEFAULT 0,
  locked_settings TEXT NOT NULL DEFAULT '{}',
  started TEXT NOT NULL, finished TEXT NOT NULL DEFAULT '',
  state TEXT NOT NULL DEFAULT 'running',
  host TEXT NOT NULL DEFAULT '', pid )sql" +
         i + R"sql( NOT NULL DEFAULT 0,
  pid_start TEXT NOT NULL DEFAULT '',
  note TEXT NOT NULL DEFAULT '',
  verdict TEXT NOT NULL DEFAULT '',
  expected_error_px )sql" +
         r + R"sql(,
  result TEXT NOT NULL DEFAULT ''
);
CREATE TABLE keyframes (
  run_id TEXT NOT NULL REFERENCES runs(run_id),
  idx )sql" +
         i + R"sql( NOT NULL,
  time TEXT NOT NULL,
  record TEXT NOT NULL,
  image_png )sql" +
         b + R"sql(,
  PRIMARY KEY (run_id, idx)
);
CREATE INDEX runs_by_camera ON runs(camera_model, lens_id, state);
)sql";
}

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
  std::unique_ptr<sql::Connection> c;
};

namespace {

int schema_version(sql::Connection& c) {
  if (!c.has_table("posecal_schema")) {
    if (!c.empty()) {
      throw Error(ErrorCode::kIo, "record store '" + c.location() +
                                      "': a database of something else (no posecal_schema table)");
    }
    return 0;
  }
  return static_cast<int>(
      c.query("SELECT max(version) FROM posecal_schema", {}, "read the schema version")[0][0]
          .integer());
}

void migrate(sql::Connection& c) {
  sql::Transaction t(c);
  c.lock_setup();
  const int version = schema_version(c);
  if (version > kSchemaVersion) {
    throw Error(ErrorCode::kInvalidArgument,
                "record store '" + c.location() + "' has schema version " +
                    std::to_string(version) + "; this posecal reads up to " +
                    std::to_string(kSchemaVersion) + " (a newer posecal wrote it)");
  }
  if (version == 0) {
    c.script("CREATE TABLE posecal_schema (version INTEGER NOT NULL, applied TEXT NOT NULL)",
             "create the schema table");
    c.script(schema_v1(c.dialect()), "create schema version 1");
    c.query("INSERT INTO posecal_schema VALUES (1, ?)", {utc_now_iso8601()},
            "record schema version 1");
  }
  t.commit();
}

// Runs a set-up step of open() again while it fails on another connection's lock, for up to
// kBusyTimeoutMs (SQLite: the busy handler does not cover every lock of a file being created).
template <class Step>
void setup_with_retry(sql::Connection& c, Step&& step) {
  const auto deadline =
      std::chrono::steady_clock::now() + std::chrono::milliseconds(kBusyTimeoutMs);
  for (;;) {
    try {
      step();
      return;
    } catch (const Error&) {
      if (!c.last_error_was_busy() || std::chrono::steady_clock::now() > deadline) throw;
      std::this_thread::sleep_for(std::chrono::milliseconds(20));
    }
  }
}

const char* kSummaryColumns =
    "r.run_id, r.station_id, r.operator_id, r.lens_id, r.camera_uri, r.camera_id, "
    "r.camera_vendor, r.camera_model, r.camera_serial, r.camera_device_version, "
    "r.posecal_version, r.abi_version, r.config, r.started, r.state, r.finished, r.verdict, "
    "r.expected_error_px, (SELECT count(*) FROM keyframes k WHERE k.run_id = r.run_id), r.note";

RunSummary summary_of(const sql::Row& row) {
  RunSummary r;
  RunIdentity& id = r.identity;
  size_t i = 0;
  for (std::string* f : {&id.run_id, &id.station_id, &id.operator_id, &id.lens_id, &id.camera_uri,
                         &id.camera_id, &id.camera_vendor, &id.camera_model, &id.camera_serial,
                         &id.camera_device_version, &id.posecal_version, &id.abi_version,
                         &id.config, &id.started, &r.state, &r.finished, &r.verdict}) {
    *f = row[i++].text();
  }
  r.expected_error_px = row[i++].real();
  r.keyframes = static_cast<int>(row[i++].integer());
  r.note = row[i++].text();
  return r;
}

bool is_postgresql(const std::string& location) {
  return location.rfind("postgresql://", 0) == 0 || location.rfind("postgres://", 0) == 0;
}

}  // namespace

RecordStore::RecordStore(std::string location, std::unique_ptr<Db> db)
    : location_(std::move(location)), db_(std::move(db)) {}
RecordStore::~RecordStore() = default;

std::unique_ptr<RecordStore> RecordStore::open(const std::string& location) {
  if (location.empty()) throw Error(ErrorCode::kInvalidArgument, "record store: an empty location");
  auto db = std::make_unique<Db>();
  db->c = is_postgresql(location) ? sql::open_postgresql(location, kBusyTimeoutMs)
                                  : sql::open_sqlite(location, kBusyTimeoutMs);
  sql::Connection& c = *db->c;
  setup_with_retry(c, [&] { migrate(c); });
  const std::string shown = c.location();  // a URL's password is not repeated
  return std::unique_ptr<RecordStore>(new RecordStore(shown, std::move(db)));
}

void RecordStore::begin_run(const RunIdentity& r) {
  sql::Connection& c = *db_->c;
  const Writer me = this_writer();
  sql::Transaction t(c);
  // Runs of this host left "running" by a process that is gone were killed (kill -9, a power
  // cut): they are marked so, with what they kept.
  for (const sql::Row& row :
       c.query("SELECT run_id, pid, pid_start FROM runs WHERE state = 'running' AND host = ?",
               {me.host}, "read the running runs")) {
    const long long pid = row[1].integer();
    if (pid <= 0 || process_start(pid) == row[2].text()) continue;
    c.query("UPDATE runs SET state = 'killed', note = ?, finished = ? WHERE run_id = ?",
            {"its process (pid " + std::to_string(pid) +
                 ") ended without finishing the run; found when run " + r.run_id + " began",
             utc_now_iso8601(), row[0].text()},
            "mark a killed run");
  }
  if (c.query("SELECT count(*) FROM runs WHERE run_id = ?", {r.run_id}, "look up the run id")[0][0]
          .integer() != 0) {
    throw Error(ErrorCode::kInvalidArgument,
                "record store '" + location_ + "': run id " + r.run_id + " is already recorded");
  }
  std::vector<sql::Value> values;
  for (const std::string* f : {&r.run_id, &r.station_id, &r.operator_id, &r.lens_id,
                               &r.camera_uri, &r.camera_id, &r.camera_vendor, &r.camera_model,
                               &r.camera_serial, &r.camera_device_version, &r.posecal_version,
                               &r.abi_version, &r.config, &r.started}) {
    values.emplace_back(*f);
  }
  values.emplace_back(me.host);
  values.emplace_back(me.pid);
  values.emplace_back(me.start);
  c.query(
      "INSERT INTO runs (run_id, station_id, operator_id, lens_id, camera_uri, camera_id, "
      "camera_vendor, camera_model, camera_serial, camera_device_version, "
      "posecal_version, abi_version, config, started, host, pid, pid_start) "
      "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
      values, "begin the run");
  t.commit();
}

void RecordStore::set_engine(const std::string& run_id, cv::Size size,
                             const std::map<std::string, std::string>& locked) {
  sql::Connection& c = *db_->c;
  sql::Transaction t(c);
  c.query(
      "UPDATE runs SET image_width = ?, image_height = ?, locked_settings = ? "
      "WHERE run_id = ?",
      {static_cast<long long>(size.width), static_cast<long long>(size.height),
       Json(locked).dump(-1, ' ', false, Json::error_handler_t::replace), run_id},
      "record the engine");
  t.commit();
}

StoredKeyframe stored_keyframe(int index, const KeyframeRecord& record, const cv::Mat& image) {
  StoredKeyframe k;
  k.index = index;
  k.time = utc_now_iso8601();
  k.record = keyframe_json(index, record, k.time);
  if (!image.empty() && !cv::imencode(".png", image, k.image_png)) k.image_png.clear();
  return k;
}

void RecordStore::add_keyframe(const std::string& run_id, const StoredKeyframe& k) {
  sql::Connection& c = *db_->c;
  sql::Transaction t(c);
  // An upsert: a session resumed from its journal records a keyframe again under the same run
  // id only if it was lost here.
  c.query(
      "INSERT INTO keyframes (run_id, idx, time, record, image_png) VALUES (?, ?, ?, ?, ?) "
      "ON CONFLICT (run_id, idx) DO UPDATE SET time = excluded.time, "
      "record = excluded.record, image_png = excluded.image_png",
      {run_id, static_cast<long long>(k.index), k.time, k.record, k.image_png}, "add a keyframe");
  t.commit();
}

void RecordStore::finish_run(const std::string& run_id, const std::string& state,
                             const std::string& result_json, const std::string& verdict,
                             std::optional<double> expected_error_px) {
  sql::Connection& c = *db_->c;
  sql::Transaction t(c);
  c.query(
      "UPDATE runs SET state = ?, result = ?, verdict = ?, expected_error_px = ?, "
      "finished = ? WHERE run_id = ?",
      {state, result_json, verdict,
       expected_error_px ? sql::Value(*expected_error_px) : sql::Value(nullptr), utc_now_iso8601(),
       run_id},
      "finish the run");
  t.commit();
}

std::vector<RunSummary> RecordStore::list_runs() const {
  sql::Connection& c = *db_->c;
  std::vector<RunSummary> out;
  for (const sql::Row& row :
       c.query(std::string("SELECT ") + kSummaryColumns + " FROM runs r ORDER BY r.started DESC, " +
                   c.dialect().run_order + " DESC",
               {}, "list the runs")) {
    out.push_back(summary_of(row));
  }
  return out;
}

std::vector<RecordStore::FleetRun> RecordStore::fleet_runs(const std::string& camera_model,
                                                           const std::string& lens_id) const {
  sql::Connection& c = *db_->c;
  std::vector<FleetRun> out;
  for (const sql::Row& row :
       c.query(std::string("SELECT r.run_id, r.camera_serial, r.started, r.result FROM runs r "
                           "WHERE r.camera_model = ? AND r.lens_id = ? AND r.result <> '' AND "
                           "(r.verdict = 'pass' OR (r.verdict = '' AND r.state = 'converged')) "
                           "ORDER BY r.started DESC, ") +
                   c.dialect().run_order + " DESC",
               {camera_model, lens_id}, "read the fleet")) {
    out.push_back({row[0].text(), row[1].text(), row[2].text(), row[3].text()});
  }
  return out;
}

RunRecord RecordStore::get_run(const std::string& run_id) const {
  if (run_id.empty()) throw Error(ErrorCode::kInvalidArgument, "records: an empty run id");
  sql::Connection& c = *db_->c;
  const std::vector<sql::Row> rows =
      c.query(std::string("SELECT ") + kSummaryColumns +
                  ", r.image_width, r.image_height, r.locked_settings, r.result FROM runs r "
                  "WHERE substr(r.run_id, 1, length(?)) = ? LIMIT 2",
              {run_id, run_id}, "read the run");
  if (rows.empty()) {
    throw Error(ErrorCode::kNotFound, "record store '" + location_ + "' has no run " + run_id);
  }
  if (rows.size() > 1) {
    throw Error(ErrorCode::kInvalidArgument,
                "records: run id " + run_id + " is ambiguous in '" + location_ + "'");
  }
  const sql::Row& row = rows[0];
  RunRecord r;
  r.summary = summary_of(row);
  r.image_width = static_cast<int>(row[20].integer());
  r.image_height = static_cast<int>(row[21].integer());
  const Json locked = Json::parse(row[22].text(), nullptr, false);
  if (locked.is_object()) {
    for (const auto& [k, v] : locked.items())
      r.locked_settings[k] = v.is_string() ? v.get<std::string>() : v.dump();
  }
  r.result = row[23].text();
  for (const sql::Row& k : c.query("SELECT idx, time, record, image_png FROM keyframes "
                                   "WHERE run_id = ? ORDER BY idx",
                                   {r.summary.identity.run_id}, "read the keyframes")) {
    StoredKeyframe f;
    f.index = static_cast<int>(k[0].integer());
    f.time = k[1].text();
    f.record = k[2].text();
    f.image_png = k[3].blob();
    r.keyframes.push_back(std::move(f));
  }
  return r;
}

}  // namespace posecal
