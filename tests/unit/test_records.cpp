// Calibration records (core/records): a run's identity, keyframes and result round-trip
// exactly; each call is its own transaction, so a run cut short stays readable ("running"); two
// writers on one store do not lose or corrupt a record; bad stores are refused naming the store
// and the cause. The same tests run against both stores: a SQLite file and a PostgreSQL server
// the test starts itself (tests/pg_server.hpp).
#include <fcntl.h>
#include <gtest/gtest.h>
#include <sqlite3.h>
#include <sys/wait.h>
#include <unistd.h>

#include <atomic>
#include <filesystem>
#include <fstream>
#include <set>
#include <sstream>
#include <thread>

#include "common/error.hpp"
#include "pg_server.hpp"
#include "records/fleet.hpp"
#include "records/record_store.hpp"
#include "records/record_writer.hpp"
#include "records/sql.hpp"
#include "session/journal.hpp"

using namespace posecal;
namespace fs = std::filesystem;

namespace {

fs::path fresh(const std::string& name) {
  const fs::path dir = fs::path(testing::TempDir()) / ("posecal_records_" + name);
  fs::remove_all(dir);
  fs::create_directories(dir);
  return dir;
}

KeyframeRecord sample(int k) {
  KeyframeRecord r;
  r.state_before = k == 0 ? EngineState::kInitialPose1 : EngineState::kRefining;
  r.state_after = EngineState::kRefining;
  r.target_param = k == 0 ? -1 : 2;
  for (int i = 0; i < 9; ++i) r.estimate_after.push_back(1.0 / 3.0 * (i + 1) * (k + 1) + 1e-17 * i);
  r.converged_after.assign(9, false);
  for (int i = 0; i < 5; ++i) {
    r.observation.ids.push_back(i);
    r.observation.image_points.emplace_back(100.0 / 7 * i, 200.0 / 3 + i * 0.1);
    r.observation.board_points.emplace_back(0.028 * i, 0.028, 0.0);
  }
  return r;
}

RunIdentity identity(const std::string& run_id) {
  RunIdentity id;
  id.run_id = run_id;
  id.station_id = "line-3/station-2";
  id.operator_id = "op 17";
  id.lens_id = "M12-6mm";
  id.camera_uri = "sim://?seed=3";
  id.camera_id = "sim-3";
  id.camera_vendor = "posecal";
  id.camera_model = "simulated";
  id.camera_serial = "SIM0003";
  id.posecal_version = "0.1.0";
  id.abi_version = "1";
  id.config = R"({"target":"charuco:9x6:0.028:0.0182:DICT_4X4_50"})";
  id.started = "2026-12-03T10:00:00Z";
  return id;
}

// The store under test: "sqlite" (a file in a fresh directory) or "postgresql" (a fresh
// database on the server this test process started).
class Store : public testing::TestWithParam<std::string> {
 protected:
  static void TearDownTestSuite() { server().reset(); }
  void SetUp() override {
    if (GetParam() == "postgresql") {
      if (!server()) server() = std::make_unique<testing_pg::PgServer>();
      ASSERT_TRUE(server()->error().empty()) << server()->error();
    }
  }
  static std::unique_ptr<testing_pg::PgServer>& server() {
    static std::unique_ptr<testing_pg::PgServer> s;
    return s;
  }
  // A new, empty store.
  std::string fresh_store(const std::string& name) {
    if (GetParam() == "sqlite") return (fresh(name) / "records.sqlite").string();
    return server()->create_database(name);
  }
  bool postgresql() const { return GetParam() == "postgresql"; }
};

INSTANTIATE_TEST_SUITE_P(Records, Store, testing::Values("sqlite", "postgresql"),
                         [](const testing::TestParamInfo<std::string>& i) { return i.param; });

}  // namespace

TEST(Records, RunIdsAreRandomVersion4Uuids) {
  std::set<std::string> ids;
  for (int i = 0; i < 1000; ++i) {
    const std::string id = new_run_id();
    ASSERT_EQ(id.size(), 36u) << id;
    EXPECT_EQ(id[14], '4') << id;
    EXPECT_NE(std::string("89ab").find(id[19]), std::string::npos) << id;
    ids.insert(id);
  }
  EXPECT_EQ(ids.size(), 1000u);
}

TEST_P(Store, ARunRoundTripsExactly) {
  const std::string db = fresh_store("roundtrip");
  const std::string run = new_run_id();
  {
    auto store = RecordStore::open(db);
    store->begin_run(identity(run));
    store->set_engine(run, cv::Size(1280, 720), {{"exposure_us", "10000"}, {"gain_db", "0"}});
    cv::Mat image(48, 64, CV_8U);
    cv::randu(image, 0, 256);
    store->add_keyframe(run, stored_keyframe(1, sample(0), image));
    store->add_keyframe(run, stored_keyframe(2, sample(1), cv::Mat()));
    store->finish_run(run, "converged", R"({"fx": 1070.25})", "pass", 0.123456789012345);
  }
  auto store = RecordStore::open(db);  // a second open reads what the first wrote
  const std::vector<RunSummary> runs = store->list_runs();
  ASSERT_EQ(runs.size(), 1u);
  EXPECT_EQ(runs[0].identity.run_id, run);
  EXPECT_EQ(runs[0].keyframes, 2);
  EXPECT_EQ(runs[0].state, "converged");
  EXPECT_EQ(runs[0].verdict, "pass");
  ASSERT_TRUE(runs[0].expected_error_px);
  EXPECT_EQ(*runs[0].expected_error_px, 0.123456789012345);
  EXPECT_FALSE(runs[0].finished.empty());

  const RunRecord r = store->get_run(run.substr(0, 8));  // a unique prefix
  const RunIdentity want = identity(run);
  const RunIdentity& got = r.summary.identity;
  EXPECT_EQ(got.station_id, want.station_id);
  EXPECT_EQ(got.operator_id, want.operator_id);
  EXPECT_EQ(got.lens_id, want.lens_id);
  EXPECT_EQ(got.camera_serial, want.camera_serial);
  EXPECT_EQ(got.config, want.config);
  EXPECT_EQ(got.started, want.started);
  EXPECT_EQ(r.image_width, 1280);
  EXPECT_EQ(r.locked_settings.at("exposure_us"), "10000");
  EXPECT_EQ(r.result, R"({"fx": 1070.25})");
  ASSERT_EQ(r.keyframes.size(), 2u);
  for (int k = 0; k < 2; ++k) {
    EXPECT_EQ(r.keyframes[k].index, k + 1);
    const KeyframeRecord back = keyframe_from_json(r.keyframes[k].record);
    const KeyframeRecord want_k = sample(k);
    EXPECT_EQ(back.estimate_after, want_k.estimate_after);  // bit for bit
    EXPECT_EQ(back.observation.image_points, want_k.observation.image_points);
    EXPECT_EQ(back.observation.ids, want_k.observation.ids);
    EXPECT_EQ(back.target_param, want_k.target_param);
  }
  EXPECT_FALSE(r.keyframes[0].image_png.empty());  // lossless: decodes to the same pixels
  EXPECT_TRUE(r.keyframes[1].image_png.empty());
}

TEST_P(Store, ARunCutShortStaysReadableAsRunning) {
  const std::string db = fresh_store("cut");
  const std::string run = new_run_id();
  {
    auto store = RecordStore::open(db);
    store->begin_run(identity(run));
    store->add_keyframe(run, stored_keyframe(1, sample(0), cv::Mat()));
  }  // no finish_run: the process was killed
  const RunRecord r = RecordStore::open(db)->get_run(run);
  EXPECT_EQ(r.summary.state, "running");
  EXPECT_TRUE(r.summary.finished.empty());
  EXPECT_EQ(r.keyframes.size(), 1u);
}

// A run whose process died (kill -9) stays "running" until the next run on the host begins,
// which marks it "killed" with a note; what it committed is kept. A run of a live process is
// left alone.
TEST_P(Store, ARunOfADeadProcessIsMarkedKilledByTheNextRun) {
  const std::string db = fresh_store("killed");
  const std::string dead_run = new_run_id(), live_run = new_run_id(), next_run = new_run_id();
  RecordStore::open(db);  // the schema, before the fork
  const pid_t child = ::fork();
  ASSERT_GE(child, 0);
  if (child == 0) {
    try {
      auto store = RecordStore::open(db);
      store->begin_run(identity(dead_run));
      store->add_keyframe(dead_run, stored_keyframe(1, sample(0), cv::Mat()));
    } catch (...) {
      ::_exit(1);
    }
    ::_exit(0);  // no finish_run: as if killed
  }
  int status = 0;
  ASSERT_EQ(::waitpid(child, &status, 0), child);
  ASSERT_TRUE(WIFEXITED(status) && WEXITSTATUS(status) == 0);
  auto store = RecordStore::open(db);
  store->begin_run(identity(live_run));  // this process: alive
  EXPECT_EQ(store->get_run(dead_run).summary.state, "killed");
  EXPECT_NE(store->get_run(dead_run).summary.note.find("pid " + std::to_string(child)),
            std::string::npos);
  EXPECT_EQ(store->get_run(dead_run).keyframes.size(), 1u);
  store->begin_run(identity(next_run));
  EXPECT_EQ(store->get_run(live_run).summary.state, "running");  // its process is this one
}

// Four connections setting up one new store at once (a station's cameras): each opens, none is
// refused for the other's lock (CI saw "switch to WAL: database is locked" once; without the
// retry this failed in round 30 of 300 here). PostgreSQL: each round a new database (slower to
// make, so fewer rounds); the set-up is serialised by an advisory lock.
TEST_P(Store, FourOpensOfANewStoreAllSucceed) {
  const int rounds = postgresql() ? 15 : 300;
  for (int round = 0; round < rounds; ++round) {
    const std::string db = fresh_store("opens" + std::to_string(round % 3));
    std::vector<std::thread> threads;
    std::atomic<int> opened{0};
    std::vector<std::string> errors(4);
    for (int t = 0; t < 4; ++t) {
      threads.emplace_back([&, t] {
        try {
          auto store = RecordStore::open(db);
          store->begin_run(identity(new_run_id()));
          ++opened;
        } catch (const std::exception& e) {
          errors[t] = e.what();
        }
      });
    }
    for (auto& t : threads) t.join();
    for (const std::string& e : errors) EXPECT_TRUE(e.empty()) << "round " << round << ": " << e;
    ASSERT_EQ(opened.load(), 4) << "round " << round;
  }
}

TEST_P(Store, TwoWritersOnOneStoreLoseNothing) {
  const std::string db = fresh_store("two");
  RecordStore::open(db);  // the schema, once
  std::vector<std::string> ids(2);
  std::vector<std::thread> writers;
  for (int w = 0; w < 2; ++w) {
    ids[w] = new_run_id();
    writers.emplace_back([&, w] {
      auto store = RecordStore::open(db);  // each station its own connection
      store->begin_run(identity(ids[w]));
      for (int k = 1; k <= 20; ++k)
        store->add_keyframe(ids[w], stored_keyframe(k, sample(k), cv::Mat()));
      store->finish_run(ids[w], "converged", "{}", "", std::nullopt);
    });
  }
  for (auto& t : writers) t.join();
  auto store = RecordStore::open(db);
  for (const std::string& id : ids) {
    const RunRecord r = store->get_run(id);
    EXPECT_EQ(r.keyframes.size(), 20u);
    EXPECT_EQ(r.summary.state, "converged");
  }
}

namespace {

template <class F>
void expect_error(F&& f, ErrorCode code, const std::string& part) {
  try {
    f();
    ADD_FAILURE() << "no error, expected " << part;
  } catch (const Error& e) {
    EXPECT_EQ(e.code(), code) << e.what();
    EXPECT_NE(std::string(e.what()).find(part), std::string::npos) << e.what();
  }
}

}  // namespace

TEST(Records, BadFilesAreRefusedNamingTheCause) {
  const fs::path dir = fresh("bad");
  expect_error([&] { RecordStore::open((dir / "no/such/dir/r.sqlite").string()); }, ErrorCode::kIo,
               "no/such/dir/r.sqlite");
  {
    std::ofstream((dir / "text.sqlite").string()) << "not a database, just text\n";
  }
  expect_error([&] { RecordStore::open((dir / "text.sqlite").string()); }, ErrorCode::kIo,
               "text.sqlite");
}

// A server that is not there, or refuses: the error names the store (without its password)
// and the cause, within the connect timeout.
TEST(Records, AnUnreachableServerIsRefusedNamingItWithoutThePassword) {
  const int port = testing_pg::free_port();  // nothing listens there
  const std::string url =
      "postgresql://posecal:s3cret@127.0.0.1:" + std::to_string(port) + "/records";
  try {
    RecordStore::open(url);
    ADD_FAILURE() << "opened " << url;
  } catch (const Error& e) {
    const std::string what = e.what();
    EXPECT_EQ(e.code(), ErrorCode::kIo) << what;
    EXPECT_NE(what.find("127.0.0.1:" + std::to_string(port)), std::string::npos) << what;
    EXPECT_NE(what.find("connect"), std::string::npos) << what;
    EXPECT_EQ(what.find("s3cret"), std::string::npos) << what;
  }
  EXPECT_EQ(sql::redact_url("postgresql://u:pw@h:5/d?sslmode=require&password=x&a=b"),
            "postgresql://u:***@h:5/d?sslmode=require&password=***&a=b");
  EXPECT_EQ(sql::redact_url("postgresql://u@h/d"), "postgresql://u@h/d");
}

TEST_P(Store, BadStoresAndRunIdsAreRefusedNamingTheCause) {
  // A database of something else.
  const std::string other = fresh_store("other");
  if (postgresql()) {
    ASSERT_TRUE(server()->psql("other", "CREATE TABLE inventory (item TEXT)"));
  } else {
    sqlite3* raw = nullptr;
    ASSERT_EQ(sqlite3_open(other.c_str(), &raw), SQLITE_OK);
    sqlite3_exec(raw, "CREATE TABLE inventory (item TEXT)", nullptr, nullptr, nullptr);
    sqlite3_close(raw);
  }
  expect_error([&] { RecordStore::open(other); }, ErrorCode::kIo, "no posecal_schema table");

  const std::string db = fresh_store("records");
  {
    auto store = RecordStore::open(db);
    const std::string run = new_run_id();
    store->begin_run(identity(run));
    expect_error([&] { store->begin_run(identity(run)); }, ErrorCode::kInvalidArgument,
                 "already recorded");
    expect_error([&] { store->get_run("ffffffff-0000"); }, ErrorCode::kNotFound, "no run");
    store->begin_run(identity(run.substr(0, 4) + "-second"));
    expect_error([&] { store->get_run(run.substr(0, 4)); }, ErrorCode::kInvalidArgument,
                 "ambiguous");
  }
  // A store written by a newer posecal.
  const char* later = "INSERT INTO posecal_schema VALUES (7, 'later')";
  if (postgresql()) {
    ASSERT_TRUE(server()->psql("records", later));
  } else {
    sqlite3* raw = nullptr;
    ASSERT_EQ(sqlite3_open(db.c_str(), &raw), SQLITE_OK);
    sqlite3_exec(raw, later, nullptr, nullptr, nullptr);
    sqlite3_close(raw);
  }
  expect_error([&] { RecordStore::open(db); }, ErrorCode::kInvalidArgument, "schema version 7");
}

// The tests' PostgreSQL server is a daemon: a test process that crashes or is killed must not
// leave it running (nor its directory). A child process starts one and kills itself with
// SIGKILL (no destructor runs); the server's port is closed and its directory gone soon after.
TEST(PgServerForTests, IsStoppedWhenTheTestProcessIsKilled) {
  int fds[2];
  ASSERT_EQ(::pipe2(fds, O_CLOEXEC), 0);  // the server must not hold the pipe open
  const pid_t child = ::fork();
  ASSERT_GE(child, 0);
  if (child == 0) {
    ::close(fds[0]);
    testing_pg::PgServer server;
    const std::string line = server.error().empty()
                                 ? std::to_string(server.port()) + " " + server.directory() + "\n"
                                 : "error " + server.error() + "\n";
    if (::write(fds[1], line.data(), line.size()) < 0) ::_exit(2);
    ::kill(::getpid(), SIGKILL);
  }
  ::close(fds[1]);
  std::string line;
  char buf[512];
  for (ssize_t n;
       line.find('\n') == std::string::npos && (n = ::read(fds[0], buf, sizeof buf)) > 0;)
    line.append(buf, n);
  ::close(fds[0]);
  int status = 0;
  ASSERT_EQ(::waitpid(child, &status, 0), child);
  EXPECT_TRUE(WIFSIGNALED(status) && WTERMSIG(status) == SIGKILL);
  ASSERT_NE(line.rfind("error", 0), 0u) << line;
  std::istringstream in(line);
  int port = 0;
  std::string dir;
  in >> port >> dir;
  ASSERT_GT(port, 0) << line;
  bool stopped = false;
  for (int i = 0; i < 300 && !stopped; ++i) {  // 30 s
    stopped = !testing_pg::accepting(port) && !fs::exists(dir);
    if (!stopped) std::this_thread::sleep_for(std::chrono::milliseconds(100));
  }
  EXPECT_TRUE(stopped) << "port " << port << (testing_pg::accepting(port) ? " still accepting" : "")
                       << (fs::exists(dir) ? ", " + dir + " still there" : "");
}

// A PostgreSQL server that goes away in the middle of a run (stopped at once, as a crash or a
// network cut would) and comes back before the run finishes: the writer keeps the parts the
// server could not take and writes them at the finish; the record is complete.
TEST(RecordWriter, AServerThatGoesAwayMidRunLosesNothing) {
  testing_pg::PgServer server;
  ASSERT_TRUE(server.error().empty()) << server.error();
  const std::string db = server.create_database("away");
  const std::string run = new_run_id();
  RecordWriter w(db, identity(run), "");
  w.set_engine(cv::Size(1280, 720), {{"gain_db", "0"}});
  w.add_keyframe(stored_keyframe(1, sample(0), cv::Mat()));
  EXPECT_EQ(w.pending(), 0u);
  EXPECT_EQ(w.note(), "");
  server.stop();
  w.add_keyframe(stored_keyframe(2, sample(1), cv::Mat()));
  w.add_keyframe(stored_keyframe(3, sample(2), cv::Mat()));
  EXPECT_EQ(w.pending(), 2u);
  EXPECT_NE(w.note().find("away"), std::string::npos) << w.note();
  ASSERT_TRUE(server.start());
  w.finish("converged", R"({"fx": 1})", "pass", 0.25);
  EXPECT_EQ(w.pending(), 0u) << w.note();
  EXPECT_EQ(w.note(), "");
  const RunRecord r = RecordStore::open(db)->get_run(run);
  EXPECT_EQ(r.summary.state, "converged");
  ASSERT_EQ(r.keyframes.size(), 3u);
  for (int k = 0; k < 3; ++k)
    EXPECT_EQ(keyframe_from_json(r.keyframes[k].record).estimate_after, sample(k).estimate_after);
}

// Still away at the finish: the run goes to the spool directory, and the next writer of the
// same store (or replay_spool) writes it there once the server is back. A run whose store was
// away from its very beginning is spooled and replayed whole.
TEST(RecordWriter, ARunTheServerMissedIsSpooledAndReplayed) {
  testing_pg::PgServer server;
  ASSERT_TRUE(server.error().empty()) << server.error();
  const std::string db = server.create_database("spool");
  const fs::path spool = fresh("spool");
  const std::string begun = new_run_id(), never = new_run_id();
  {
    RecordWriter w(db, identity(begun), spool.string());
    w.add_keyframe(stored_keyframe(1, sample(0), cv::Mat()));
    server.stop();
    w.add_keyframe(stored_keyframe(2, sample(1), cv::Mat()));
    w.finish("converged", "{}", "pass", 0.5);
    EXPECT_NE(w.note().find("spooled"), std::string::npos) << w.note();
    EXPECT_TRUE(fs::exists(w.spooled())) << w.spooled();
  }
  {
    RecordWriter w(db, identity(never), spool.string());  // the server is still down
    EXPECT_EQ(w.pending(), 1u);
    w.set_engine(cv::Size(640, 480), {});
    w.add_keyframe(stored_keyframe(1, sample(3), cv::Mat()));
    w.finish("failed", "", "", std::nullopt);
    EXPECT_FALSE(w.spooled().empty()) << w.note();
  }
  size_t files = 0;
  for (const auto& e : fs::directory_iterator(spool)) files += e.path().extension() == ".sqlite";
  EXPECT_EQ(files, 2u);
  ASSERT_TRUE(server.start());
  // The next run on this store replays the spool when it begins.
  const std::string next = new_run_id();
  RecordWriter w(db, identity(next), spool.string());
  EXPECT_EQ(w.note(), "");
  auto store = RecordStore::open(db);
  const RunRecord a = store->get_run(begun);
  EXPECT_EQ(a.summary.state, "converged");
  EXPECT_EQ(a.keyframes.size(), 2u);
  EXPECT_EQ(*a.summary.expected_error_px, 0.5);
  const RunRecord b = store->get_run(never);
  EXPECT_EQ(b.summary.state, "failed");
  EXPECT_EQ(b.image_width, 640);
  ASSERT_EQ(b.keyframes.size(), 1u);
  EXPECT_EQ(keyframe_from_json(b.keyframes[0].record).estimate_after, sample(3).estimate_after);
  EXPECT_TRUE(fs::is_empty(spool));
  EXPECT_EQ(store->list_runs().size(), 3u);
}

// The F quantile against values that are exact (d1 = d2 = 2: F = q / (1 - q); d1 = d2 = 1 at
// q = 0.5: 1) and tabulated ones.
TEST(Fleet, FQuantileMatchesTables) {
  EXPECT_NEAR(f_quantile(0.975, 2, 2), 39.0, 1e-8);
  EXPECT_NEAR(f_quantile(0.5, 1, 1), 1.0, 1e-9);
  EXPECT_NEAR(f_quantile(0.95, 1, 1), 161.4476, 1e-3);
  EXPECT_NEAR(f_quantile(0.95, 5, 10), 3.3258, 1e-3);
  EXPECT_NEAR(f_quantile(0.99, 10, 30), 2.9791, 1e-3);
  EXPECT_THROW(f_quantile(1.0, 2, 2), Error);
}

namespace {

// Units of a normal population around the C525's intrinsics (fx, fy, cx, cy, k1..k3, p1, p2
// order is irrelevant here): correlated fx and fy, independent others.
std::vector<double> draw_unit(cv::RNG& rng) {
  const double f = 1070 * (1 + 0.01 * rng.gaussian(1));
  return {f * (1 + 0.001 * rng.gaussian(1)),
          f,
          640 + 6 * rng.gaussian(1),
          360 + 6 * rng.gaussian(1),
          0.10 + 0.01 * rng.gaussian(1),
          -0.2 + 0.03 * rng.gaussian(1),
          0.001 * rng.gaussian(1),
          0.001 * rng.gaussian(1),
          0.1 * rng.gaussian(1)};
}

const std::vector<std::string> kNames = {"fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"};

}  // namespace

// The bound's promise: a normal unit is flagged with probability alpha, whatever the fleet's
// size. 400 fleets of 30 units, 50 new units each, at alpha 0.05: 20,000 tries.
TEST(Fleet, NormalUnitsAreFlaggedAtTheStatedRate) {
  cv::RNG rng(7);
  int flagged = 0, tries = 0;
  for (int f = 0; f < 400; ++f) {
    std::vector<FleetUnit> units;
    for (int i = 0; i < 30; ++i) units.push_back({std::to_string(i), "", draw_unit(rng)});
    const FleetStatistics fleet = fleet_statistics(kNames, units);
    for (int i = 0; i < 50; ++i, ++tries)
      flagged += fleet_position(fleet, kNames, draw_unit(rng), 0.05).outlier;
  }
  // The joint test at alpha / 2 and the nine parameter tests at alpha / 18 each: at most alpha
  // in all (the union bound), at least the joint test's alpha / 2.
  const double rate = static_cast<double>(flagged) / tries;
  std::printf("normal units flagged at alpha 0.05: %d of %d (%.4f)\n", flagged, tries, rate);
  EXPECT_LE(rate, 0.05 + 0.006) << flagged << " of " << tries;  // ~4 standard errors
  EXPECT_GE(rate, 0.025 - 0.006) << flagged << " of " << tries;
}

// A single parameter far off is caught by its own test before the joint distance crosses its
// bound: cx 6 of the fleet's standard deviations off is d 7.3 < 8.5, but |z| 6 > 4.8.
TEST(Fleet, OneParameterFarOffIsFlaggedByItsOwnTest) {
  cv::RNG rng(13);
  std::vector<FleetUnit> units;
  for (int i = 0; i < 30; ++i) units.push_back({std::to_string(i), "", draw_unit(rng)});
  const FleetStatistics fleet = fleet_statistics(kNames, units);
  const FleetPosition normal = fleet_position(fleet, kNames, fleet.mean, 0.001);
  EXPECT_FALSE(normal.outlier);
  std::vector<double> unit = fleet.mean;
  unit[2] += 6 * std::sqrt(fleet.covariance[2 * kNames.size() + 2]);
  const FleetPosition pos = fleet_position(fleet, kNames, unit, 0.001);
  std::printf("cx 6 sigma off: d %.2f (bound %.2f), z %.2f (bound %.2f)\n", pos.distance,
              pos.threshold, pos.deviations[0].second, pos.parameter_threshold);
  EXPECT_LT(pos.distance, pos.threshold);
  EXPECT_GT(pos.parameter_threshold, 4.5);
  EXPECT_LT(pos.parameter_threshold, 5.5);
  EXPECT_TRUE(pos.outlier);
  EXPECT_EQ(pos.deviations[0].first, "cx");
}

TEST(Fleet, AShiftedUnitIsFlaggedNamingTheParameter) {
  cv::RNG rng(11);
  std::vector<FleetUnit> units;
  for (int i = 0; i < 30; ++i) units.push_back({std::to_string(i), "", draw_unit(rng)});
  const FleetStatistics fleet = fleet_statistics(kNames, units);
  std::vector<double> unit = draw_unit(rng);
  // cx 10 standard deviations of the fleet's cx off (60 px here). Whether a 3% shift (19 px)
  // is flagged depends on the fleet's own spread of cx: with this fleet's 6 px it is 3.2 sigma,
  // below the nine-parameter bound at alpha 0.001 (d > ~8.1); the fleet benchmark measures it.
  unit[2] += 10 * 6.0;
  FleetPosition pos = fleet_position(fleet, kNames, unit, 0.001);
  EXPECT_TRUE(pos.outlier) << pos.distance << " vs " << pos.threshold;
  EXPECT_EQ(pos.deviations[0].first, "cx");
  unit = draw_unit(rng);
  unit[4] = -unit[4];  // k1 of the wrong sign
  pos = fleet_position(fleet, kNames, unit, 0.001);
  EXPECT_TRUE(pos.outlier);
  EXPECT_EQ(pos.deviations[0].first, "k1");
  // Too few units for nine parameters: refused, naming the counts.
  units.resize(11);
  EXPECT_THROW(fleet_statistics(kNames, units), Error);
}
