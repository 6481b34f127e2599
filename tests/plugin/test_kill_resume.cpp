// kill -9 at random points of `posecal calibrate --camera sim://...` and of a 4-camera
// `posecal station`, then the same command again (issue 16, the journal's proof): every resumed
// session restores every keyframe journalled before the kill, its recalibration equals the last
// one before the kill bit for bit, it converges, no result file is ever truncated (each parses
// or is absent), no journal is unreadable.
//
// POSECAL_KILL_ROUNDS (default 50) sets the rounds of each test; the label is slow.
#include <fcntl.h>
#include <gtest/gtest.h>
#include <poll.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <functional>
#include <map>
#include <nlohmann/json.hpp>
#include <opencv2/core/persistence.hpp>
#include <random>
#include <sstream>
#include <string>
#include <vector>

#include "cli_child.hpp"
#include "records/record_store.hpp"
#include "session/journal.hpp"

namespace fs = std::filesystem;
using Json = nlohmann::json;

using posecal_test::CliChild;

namespace {

int rounds() {
  const char* r = std::getenv("POSECAL_KILL_ROUNDS");
  return r ? std::max(1, std::atoi(r)) : 50;
}

// A small camera (VGA, 600 px focal length) so that a round takes seconds.
fs::path write_vga_model(const fs::path& dir) {
  const fs::path p = dir / "vga.yml";
  std::ofstream(p) << "%YAML:1.0\n---\nimage_width: 640\nimage_height: 480\n"
                      "camera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n"
                      "   data: [ 600., 0., 322., 0., 600., 238., 0., 0., 1. ]\n"
                      "distortion_coefficients: !!opencv-matrix\n   rows: 1\n   cols: 5\n   dt: d\n"
                      "   data: [ -0.1, 0.05, 0., 0., 0. ]\n";
  return p;
}

Json parse_line(const std::string& line) { return Json::parse(line, nullptr, false); }

// A result file is absent or complete: OpenCV reads it and it has the model and the last key
// posecal writes.
void expect_absent_or_whole(const fs::path& p, const std::string& where) {
  if (!fs::exists(p)) return;
  cv::FileStorage fs;
  bool ok = false;
  try {
    ok = fs.open(p.string(), cv::FileStorage::READ) && !fs["camera_matrix"].empty() &&
         !fs["converged"].empty();
  } catch (const cv::Exception&) {
    ok = false;
  }
  EXPECT_TRUE(ok) << where << ": " << p << " is not a whole result file";
}

// The kill point of a round: after `keyframes` calibrations (0: right after the start, -1: once
// the calibration has converged, i.e. around the result write), then `delay_ms`.
struct KillPoint {
  int keyframes;
  int delay_ms;
};

KillPoint kill_point(std::mt19937& rng) {
  std::uniform_int_distribution<int> k(-1, 7), d(0, 400), d_end(0, 60);
  KillPoint p{k(rng), 0};
  p.delay_ms = p.keyframes == -1 ? d_end(rng) : d(rng);
  return p;
}

bool reached(const std::string& line, const KillPoint& p, int* calibrated) {
  const Json j = parse_line(line);
  if (j.is_discarded() || !j.is_object()) return false;
  const std::string ev = j.value("event", "");
  if (ev == "calibrated") *calibrated = std::max(*calibrated, j.value("keyframes", 0));
  if (p.keyframes == -1) return ev == "state_changed" && j.value("to", "") == "converged";
  if (p.keyframes == 0) return ev == "state_changed";
  return ev == "calibrated" && j.value("keyframes", 0) >= p.keyframes;
}

}  // namespace

TEST(KillResume, CalibrateKilledAnywhereResumesExactlyAndConverges) {
  const fs::path dir = fs::path(testing::TempDir()) / "posecal_kill_calibrate";
  fs::remove_all(dir);
  fs::create_directories(dir);
  const fs::path model = write_vga_model(dir);
  std::mt19937 rng(16);
  int resumed_total = 0;
  for (int round = 0; round < rounds(); ++round) {
    const std::string where = "round " + std::to_string(round);
    const fs::path journal = dir / ("r" + std::to_string(round) + ".journal");
    const fs::path out = dir / ("r" + std::to_string(round) + ".yml");
    const std::vector<std::string> args = {"calibrate",
                                           "--camera",
                                           "sim://?seed=" + std::to_string(100 + round) +
                                               "&operator=hold-only&model=" + model.string(),
                                           "--json",
                                           "--no-window",
                                           "--journal",
                                           journal.string(),
                                           "--out",
                                           out.string()};
    const KillPoint kp = kill_point(rng);
    int calibrated = 0;
    {
      CliChild c(args, CliChild::Stream::kStdout, dir / "stderr.txt");
      const bool there =
          c.wait_for([&](const std::string& l) { return reached(l, kp, &calibrated); }, 120);
      if (there) ::usleep(static_cast<useconds_t>(kp.delay_ms) * 1000);
      c.kill9();
    }
    expect_absent_or_whole(out, where);
    posecal::JournalContents j;
    ASSERT_NO_THROW(j = posecal::read_journal(journal.string())) << where << ": journal unreadable";
    // The keyframe in flight may be lost, no other.
    EXPECT_GE(static_cast<int>(j.keyframes.size()), calibrated - 1) << where;
    CliChild again(args, CliChild::Stream::kStdout, dir / "stderr.txt");
    const int code = again.finish(180);
    EXPECT_EQ(code, 0) << where << " (kill after " << kp.keyframes << " keyframes + " << kp.delay_ms
                       << " ms)";
    ASSERT_FALSE(again.lines().empty()) << where;
    const Json result = parse_line(again.lines().back());
    ASSERT_TRUE(result.is_object()) << where << ": " << again.lines().back();
    EXPECT_EQ(result.value("event", ""), "result") << where;
    EXPECT_TRUE(result.value("converged", false)) << where;
    EXPECT_EQ(result.value("resumed_keyframes", -1), static_cast<int>(j.keyframes.size())) << where;
    if (!j.keyframes.empty()) {
      EXPECT_EQ(result.value("resume_identical", false), true) << where << ": " << result.dump();
    }
    expect_absent_or_whole(out, where);
    EXPECT_TRUE(fs::exists(out)) << where;
    const posecal::JournalContents after = posecal::read_journal(journal.string());
    EXPECT_EQ(after.end_state, "converged") << where;
    EXPECT_TRUE(after.damage.empty()) << where << ": " << after.damage;
    resumed_total += static_cast<int>(j.keyframes.size());
  }
  EXPECT_GT(resumed_total, rounds()) << "the kills hardly ever came after a keyframe";
}

TEST(KillResume, StationKilledAnywhereResumesEveryCamera) {
  const fs::path dir = fs::path(testing::TempDir()) / "posecal_kill_station";
  fs::remove_all(dir);
  fs::create_directories(dir);
  const fs::path model = write_vga_model(dir);
  std::mt19937 rng(17);
  int finished_runs = 0, killed_runs = 0, finished_rounds = 0;
  for (int round = 0; round < rounds(); ++round) {
    const std::string where = "round " + std::to_string(round);
    const fs::path st = dir / ("r" + std::to_string(round));
    std::string cameras;
    for (int c = 0; c < 4; ++c) {
      cameras += (c ? "," : "") + std::string("sim://?seed=") +
                 std::to_string(200 + 4 * round + c) +
                 "&operator=hold-only&model=" + model.string();
    }
    const std::vector<std::string> args = {"station",   "--cameras", cameras,
                                           "--out-dir", st.string(), "--json"};
    {
      // The station prints its events on stderr and only the summary on stdout: kill after a
      // random time instead (0.3 .. 7 s covers every phase of a VGA calibration; a station that
      // finished before the kill is checked too, see finished_run).
      CliChild c(args, CliChild::Stream::kStdout, dir / "stderr.txt");
      std::uniform_int_distribution<int> ms(300, 7000);
      c.wait_for([](const std::string&) { return false; }, ms(rng) / 1000.0);
      c.kill9();
    }
    std::map<std::string, size_t> journalled;
    if (fs::exists(st / "journal")) {
      for (const auto& e : fs::directory_iterator(st / "journal")) {
        if (e.path().extension() != ".journal") continue;
        posecal::JournalContents j;
        ASSERT_NO_THROW(j = posecal::read_journal(e.path().string())) << where << ": " << e.path();
        journalled[e.path().string()] = j.keyframes.size();
      }
      for (const auto& e : fs::directory_iterator(st)) {
        if (e.path().extension() == ".yml") expect_absent_or_whole(e.path(), where);
      }
    }
    bool finished_run = false;  // killed after the summary was written: the run had finished
    if (fs::exists(st / "summary.json")) {
      std::ifstream in(st / "summary.json");
      const Json prev = Json::parse(in, nullptr, false);
      EXPECT_FALSE(prev.is_discarded()) << where << ": summary.json is cut";
      finished_run = prev.is_object() && prev.value("interrupted", -1) == 0;
    }
    // The records the killed station left (issue 15): each reads; the finished cameras' runs are
    // complete, the others "running" until the next run marks them.
    std::map<std::string, int> finished_before;  // run id -> keyframes
    std::vector<std::string> running_before;
    const std::string db = (st / "records.sqlite").string();
    if (fs::exists(db)) {
      std::vector<posecal::RunSummary> runs;
      ASSERT_NO_THROW(runs = posecal::RecordStore::open(db)->list_runs()) << where;
      for (const auto& r : runs) {
        if (r.state == "running") {
          running_before.push_back(r.identity.run_id);
        } else {
          EXPECT_EQ(r.state, "converged") << where;
          finished_before[r.identity.run_id] = r.keyframes;
        }
      }
    }
    // A finished run's directory is not calibrated over without --force (issue 15); with it,
    // the run starts afresh (its journals go).
    std::vector<std::string> again_args = args;
    if (finished_run) {
      CliChild refused(args, CliChild::Stream::kStdout, dir / "stderr.txt");
      EXPECT_EQ(refused.finish(60), 1) << where << ": a finished run's directory was reused";
      again_args.push_back("--force");
      journalled.clear();
      ++finished_rounds;
    }
    CliChild again(again_args, CliChild::Stream::kStdout, dir / "stderr.txt");
    const int code = again.finish(300);
    EXPECT_EQ(code, 0) << where;
    ASSERT_FALSE(again.lines().empty()) << where;
    const Json sum = parse_line(again.lines().back());
    ASSERT_TRUE(sum.is_object()) << where;
    EXPECT_EQ(sum.value("converged", 0), 4) << where << ": " << sum.dump();
    for (const auto& cam : sum["cameras"]) {
      const std::string jpath = cam.value("journal", "");
      const size_t before = journalled.count(jpath) ? journalled[jpath] : 0;
      EXPECT_EQ(cam.value("resumed_keyframes", -1), static_cast<int>(before))
          << where << ": " << cam.dump();
      if (before > 0) {
        EXPECT_EQ(cam.value("resume_identical", false), true) << where << ": " << cam.dump();
      }
      expect_absent_or_whole(cam.value("file", ""), where);
    }
    // After the second run: its four runs converged; the killed station's finished runs are
    // intact and its unfinished ones marked "killed"; none is left "running".
    auto store = posecal::RecordStore::open(db);
    for (const auto& cam : sum["cameras"]) {
      ASSERT_TRUE(cam["run_id"].is_string()) << where << ": " << cam.dump();
      EXPECT_EQ(store->get_run(cam["run_id"].get<std::string>()).summary.state, "converged")
          << where;
    }
    for (const auto& [id, keyframes] : finished_before) {
      const posecal::RunRecord r = store->get_run(id);
      EXPECT_EQ(r.summary.state, "converged") << where;
      EXPECT_EQ(static_cast<int>(r.keyframes.size()), keyframes) << where;
    }
    for (const std::string& id : running_before) {
      EXPECT_EQ(store->get_run(id).summary.state, "killed") << where << ": run " << id;
    }
    for (const auto& r : store->list_runs()) EXPECT_NE(r.state, "running") << where;
    finished_runs += static_cast<int>(finished_before.size());
    killed_runs += static_cast<int>(running_before.size());
  }
  std::printf("station records: %d runs finished before a kill kept intact, %d killed runs "
              "marked, over %d rounds (%d killed after the station had finished)\n",
              finished_runs, killed_runs, rounds(), finished_rounds);
}
