// The posecal command line, end to end (it is built on the C ABI only).
#include <fcntl.h>
#include <gtest/gtest.h>
#include <poll.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <cctype>
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <opencv2/calib3d.hpp>
#include <opencv2/imgcodecs.hpp>
#include <regex>
#include <set>
#include <sstream>

#include "board/board.hpp"
#include "cli_child.hpp"
#include "common/run_id.hpp"
#include "io/model_file.hpp"
#include "lens/reference_models.hpp"
#include "pg_server.hpp"
#include "records/record_store.hpp"
#include "session/journal.hpp"

namespace fs = std::filesystem;

namespace {

using posecal_test::CliRun;
using posecal_test::run_cli;

const char* kOpenCVData = "/usr/share/doc/opencv-doc/examples/data";

}  // namespace

// OpenCV's sample chessboard photos (Debian package opencv-doc, 9x6 inner corners) calibrate
// through the CLI, and agree with cv::calibrateCamera on the same detections.
TEST(Cli, CalibratesOpenCVSampleImagesLikeOpenCV) {
  if (!fs::exists(std::string(kOpenCVData) + "/left01.jpg")) {
    GTEST_SKIP() << "opencv-doc is not installed (apt-get install opencv-doc)";
  }
  const fs::path dir = fs::path(testing::TempDir()) / "posecal_left";
  fs::remove_all(dir);
  fs::create_directories(dir);
  for (const auto& e : fs::directory_iterator(kOpenCVData)) {
    const std::string name = e.path().filename().string();
    if (name.size() == 10 && name.rfind("left", 0) == 0 && e.path().extension() == ".jpg") {
      fs::copy_file(e.path(), dir / name);
    }
  }
  {
    std::FILE* f = std::fopen((dir / "readme.txt").c_str(), "w");
    std::fputs("not an image", f);
    std::fclose(f);
  }
  const std::string out = (dir / "calib.yml").string();
  const CliRun r = run_cli("calibrate --images " + dir.string() +
                           " --target chessboard:9x6:0.025 --out " + out + " --json");
  ASSERT_EQ(r.status, 0) << r.out;
  const auto j = nlohmann::json::parse(r.out);
  EXPECT_GE(j["frames_used"].get<int>(), 10);
  EXPECT_EQ(j["frames_rejected"].get<int>(), 1);  // readme.txt
  EXPECT_EQ(j["rejected"][0]["file"], "readme.txt");
  for (const char* k : {"fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "rms"})
    ASSERT_TRUE(j[k].is_number()) << k;
  for (const char* k : {"fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"})
    ASSERT_TRUE(j["std"][k].is_number()) << k;

  // The same detections through cv::calibrateCamera.
  const posecal::Board target(posecal::BoardSpec::parse("chessboard:9x6:0.025"));
  std::vector<std::vector<cv::Point3f>> obj;
  std::vector<std::vector<cv::Point2f>> img;
  cv::Size size;
  for (const auto& name : j["used"]) {
    const cv::Mat im = cv::imread((dir / name.get<std::string>()).string(), cv::IMREAD_GRAYSCALE);
    size = im.size();
    const auto d = target.detect(im);
    obj.emplace_back(d.board_points.begin(), d.board_points.end());
    img.emplace_back(d.image_points.begin(), d.image_points.end());
  }
  cv::Mat K, D;
  std::vector<cv::Mat> rv, tv;
  const double cv_rms = cv::calibrateCamera(obj, img, size, K, D, rv, tv);
  std::printf(
      "posecal fx %.3f fy %.3f cx %.3f cy %.3f k1 %.4f rms %.4f | OpenCV fx %.3f fy %.3f cx %.3f "
      "cy %.3f k1 %.4f rms %.4f\n",
      j["fx"].get<double>(), j["fy"].get<double>(), j["cx"].get<double>(), j["cy"].get<double>(),
      j["k1"].get<double>(), j["rms"].get<double>(), K.at<double>(0, 0), K.at<double>(1, 1),
      K.at<double>(0, 2), K.at<double>(1, 2), D.at<double>(0), cv_rms);
  EXPECT_NEAR(j["fx"].get<double>(), K.at<double>(0, 0), 0.05);
  EXPECT_NEAR(j["fy"].get<double>(), K.at<double>(1, 1), 0.05);
  EXPECT_NEAR(j["cx"].get<double>(), K.at<double>(0, 2), 0.05);
  EXPECT_NEAR(j["cy"].get<double>(), K.at<double>(1, 2), 0.05);
  EXPECT_NEAR(j["k1"].get<double>(), D.at<double>(0), 1e-4);
  EXPECT_LE(j["rms"].get<double>(), cv_rms + 1e-6);
  cv::FileStorage fs_out(out, cv::FileStorage::READ);
  ASSERT_TRUE(fs_out.isOpened());
  EXPECT_EQ(static_cast<int>(fs_out["nr_of_frames"]), j["frames_used"].get<int>());
}

// A folder with both cameras of OpenCV's stereo samples (left01.jpg .., right01.jpg .., and
// left.jpg / right.jpg, a 612x459 pair) was calibrated as one camera. Now it is refused naming
// the four groups; --camera-group picks one, with a progress line per image in text mode and the
// other images listed as not used.
TEST(Cli, FolderOfTwoCamerasIsRefusedAndOneIsChosen) {
  if (!fs::exists(std::string(kOpenCVData) + "/right01.jpg")) {
    GTEST_SKIP() << "opencv-doc is not installed (apt-get install opencv-doc)";
  }
  const fs::path dir = fs::path(testing::TempDir()) / "posecal_left_right";
  fs::remove_all(dir);
  fs::create_directories(dir);
  int copied = 0;
  for (const auto& e : fs::directory_iterator(kOpenCVData)) {
    const std::string name = e.path().filename().string();
    if ((name.rfind("left", 0) == 0 || name.rfind("right", 0) == 0) &&
        e.path().extension() == ".jpg") {
      fs::copy_file(e.path(), dir / name);
      ++copied;
    }
  }
  ASSERT_GE(copied, 20);
  const std::string base = "calibrate --images " + dir.string() + " --target chessboard:9x6:0.025";
  CliRun r = run_cli(base);
  EXPECT_EQ(r.status, 2) << r.out;
  EXPECT_NE(r.out.find("'left@640x480' ("), std::string::npos) << r.out;
  EXPECT_NE(r.out.find("'right@640x480' ("), std::string::npos) << r.out;
  EXPECT_NE(r.out.find("'left@612x459' (1 image)"), std::string::npos) << r.out;
  EXPECT_NE(r.out.find("--camera-group"), std::string::npos) << r.out;
  r = run_cli(base + " --camera-group left");  // two sizes of "left": ambiguous, said so
  EXPECT_EQ(r.status, 2) << r.out;
  EXPECT_NE(r.out.find("names more than one"), std::string::npos) << r.out;

  r = run_cli(base + " --camera-group left@640x480", true);
  ASSERT_EQ(r.status, 0) << r.out;
  EXPECT_NE(r.out.find("[1/"), std::string::npos) << r.out;  // progress, one line per image
  EXPECT_NE(r.out.find("calibrated group 'left@640x480'"), std::string::npos) << r.out;
  EXPECT_NE(r.out.find("not used right01.jpg: in group 'right@640x480'"), std::string::npos)
      << r.out;

  r = run_cli(base + " --camera-group right@640x480 --json", true);
  ASSERT_EQ(r.status, 0) << r.out;
  const auto j = nlohmann::json::parse(r.out);  // --json: the result document only
  EXPECT_EQ(j["camera_group"], "right@640x480");
  EXPECT_EQ(j["groups"].size(), 4u);
  int left_listed = 0;
  for (const auto& rej : j["rejected"])
    left_listed += rej["file"].get<std::string>().rfind("left", 0) == 0;
  EXPECT_GE(left_listed, 10);
  for (const auto& used : j["used"]) EXPECT_EQ(used.get<std::string>().rfind("right", 0), 0u);

  // The quality gate offline: a residual limit these photos cannot meet, exit 4.
  const fs::path spec = dir / "spec.json";
  std::ofstream(spec) << R"({"max_eps_res_px": 0.01, "max_keyframes": 100})";
  r = run_cli(base + " --camera-group right@640x480 --json --spec " + spec.string(), true);
  EXPECT_EQ(r.status, 4) << r.out;
  const auto v = nlohmann::json::parse(r.out);
  EXPECT_EQ(v["verdict"], "fail");
  ASSERT_EQ(v["verdict_reasons"].size(), 1u) << v["verdict_reasons"].dump();
  EXPECT_EQ(v["verdict_reasons"][0].get<std::string>().rfind("eps_res ", 0), 0u);
}

TEST(Cli, BadInputGivesMessageAndNonZeroExit) {
  CliRun r = run_cli("calibrate --images /nonexistent/dir");
  EXPECT_EQ(r.status, 2);
  EXPECT_NE(r.out.find("does not exist"), std::string::npos) << r.out;
  r = run_cli("calibrate --images /tmp --target charuco:9x6");
  EXPECT_EQ(r.status, 2);
  EXPECT_NE(r.out.find("target spec"), std::string::npos) << r.out;
  r = run_cli("calibrate");
  EXPECT_EQ(r.status, 1);
  r = run_cli("calibrate --images");
  EXPECT_EQ(r.status, 1);
  r = run_cli("frobnicate");
  EXPECT_EQ(r.status, 1);
  EXPECT_NE(r.out.find("unknown command"), std::string::npos);
  // A folder of non-images: every file listed, a clear error, no crash.
  const fs::path dir = fs::path(testing::TempDir()) / "posecal_junk";
  fs::remove_all(dir);
  fs::create_directories(dir);
  for (int i = 0; i < 3; ++i) {
    std::FILE* f = std::fopen((dir / ("junk" + std::to_string(i) + ".png")).c_str(), "w");
    std::fputs("garbage", f);
    std::fclose(f);
  }
  r = run_cli("calibrate --images " + dir.string());
  EXPECT_EQ(r.status, 2);
  EXPECT_NE(r.out.find("no image"), std::string::npos) << r.out;
  // Images without enough views: a blank image set.
  for (int i = 0; i < 3; ++i)
    cv::imwrite((dir / ("blank" + std::to_string(i) + ".png")).string(),
                cv::Mat(480, 640, CV_8U, cv::Scalar(128)));
  r = run_cli("calibrate --images " + dir.string() + " --json");
  EXPECT_EQ(r.status, 2) << r.out;
}

TEST(Cli, WritesPrintableBoard) {
  const std::string png = testing::TempDir() + "/cli_board.png";
  CliRun r = run_cli("board --out " + png + " --dpi 200");
  ASSERT_EQ(r.status, 0) << r.out;
  const cv::Mat img = cv::imread(png, cv::IMREAD_GRAYSCALE);
  ASSERT_FALSE(img.empty());
  EXPECT_EQ(posecal::Board().detect(img).size(), 40u);
  r = run_cli("board --out " + testing::TempDir() + "/cli_board.pdf --target chessboard:9x6:0.025");
  EXPECT_EQ(r.status, 0) << r.out;
  r = run_cli("board --out /nonexistent/dir/board.pdf");
  EXPECT_EQ(r.status, 2) << r.out;
  // Paper sizes (tests/unit/test_printable.cpp measures the pages).
  const std::string a3 = testing::TempDir() + "/cli_board_a3.pdf";
  r = run_cli("board --out " + a3 + " --paper A3 --target charuco:14x10:0.04:0.03:DICT_5X5_100");
  EXPECT_EQ(r.status, 0) << r.out;
  std::ifstream f(a3, std::ios::binary);
  const std::string pdf((std::istreambuf_iterator<char>(f)), std::istreambuf_iterator<char>());
  EXPECT_NE(pdf.find("/Count 4"), std::string::npos) << "four A3 sheets";
  r = run_cli("board --out " + testing::TempDir() + "/cli_board_a5.pdf --paper a5");
  EXPECT_EQ(r.status, 1) << r.out;
  EXPECT_NE(r.out.find("a5"), std::string::npos) << r.out;
  r = run_cli("board --out " + png + " --paper a4");
  EXPECT_EQ(r.status, 2) << r.out;
  EXPECT_NE(r.out.find("paper size applies to a PDF"), std::string::npos) << r.out;
}

namespace {

// Non-empty lines of a text.
std::vector<std::string> lines_of(const std::string& text) {
  std::vector<std::string> out;
  std::istringstream in(text);
  for (std::string line; std::getline(in, line);) {
    if (!line.empty()) out.push_back(line);
  }
  return out;
}

std::string temp_dir(const std::string& name) {
  const fs::path dir = fs::path(testing::TempDir()) / name;
  fs::remove_all(dir);
  fs::create_directories(dir);
  return dir.string();
}

}  // namespace

TEST(Cli, SimulateExitCodes) {
  // (exit code 0 for a converged run: LiveCalibrationPrintsJsonEvents, EvaluateGrabFeatures)
  // Three keyframes cannot converge: the run ends as "failed", with a result, exit code 3.
  CliRun r = run_cli("simulate --seed 2 --max-keyframes 3 --json", true);
  ASSERT_EQ(r.status, 3) << r.out;
  const auto j = nlohmann::json::parse(r.out);
  EXPECT_FALSE(j["converged"].get<bool>());
  EXPECT_EQ(j["keyframes"], 3);
  // The intrinsics are the result's covariance_order (the lens model's parameters).
  ASSERT_EQ(j["covariance_order"].size(), 9u) << r.out;
  for (const auto& name : j["covariance_order"]) {
    EXPECT_TRUE(j[name.get<std::string>()].is_number()) << name;
    EXPECT_TRUE(j["std"][name.get<std::string>()].is_number()) << name;
  }
  // The expected error and its map are in the summary.
  EXPECT_GT(j["expected_error_px"].get<double>(), 0.0) << r.out;
  EXPECT_TRUE(j["expected_error_limited_by"].is_string()) << r.out;
  ASSERT_EQ(j["expected_error_map"]["px"].size(), 9u) << r.out;
  ASSERT_EQ(j["expected_error_map"]["px"][0].size(), 16u) << r.out;
  EXPECT_GT(j["expected_error_map"]["px"][0][0].get<double>(), 0.0);
  EXPECT_EQ(run_cli("simulate --operator cat").status, 1);
  EXPECT_EQ(run_cli("simulate --seed x").status, 1);
  EXPECT_EQ(run_cli("simulate --accuracy-px 0").status, 1);
  EXPECT_EQ(run_cli("simulate --accuracy-px -1").status, 1);
  EXPECT_EQ(run_cli("simulate --camera-model /nonexistent.yml").status, 2);
}

// --accuracy-px is the stop rule: converged means the predicted 90th percentile of the error is at
// most that (the RMS below it); one that
// cannot be reached within --max-keyframes ends the run as not converged, saying why.
TEST(Cli, SimulateToAnAccuracy) {
  CliRun r = run_cli("simulate --seed 4 --accuracy-px 0.4 --json", true);
  ASSERT_EQ(r.status, 0) << r.out;
  auto j = nlohmann::json::parse(r.out);
  EXPECT_TRUE(j["converged"].get<bool>());
  EXPECT_LE(j["expected_error_p90_px"].get<double>(), 0.4);
  EXPECT_LT(j["expected_error_px"].get<double>(), j["expected_error_p90_px"].get<double>());
  r = run_cli("simulate --seed 4 --accuracy-px 0.001 --max-keyframes 4 --json", true);
  ASSERT_EQ(r.status, 3) << r.out;
  j = nlohmann::json::parse(r.out);
  EXPECT_NE(j["failure"].get<std::string>().find("accuracy_px 0.001 px"), std::string::npos) << r.out;
}

// --fix holds parameters at their initial value (distortion: 0) through the whole session: they
// report std 0 and count as converged; a wrong name is refused before anything runs.
TEST(Cli, SimulateWithFixedParameters) {
  CliRun r = run_cli("simulate --seed 3 --fix k2,k3 --json", true);
  ASSERT_EQ(r.status, 0) << r.out;
  const auto j = nlohmann::json::parse(r.out);
  EXPECT_TRUE(j["converged"].get<bool>());
  EXPECT_EQ(j["k2"].get<double>(), 0.0);
  EXPECT_EQ(j["k3"].get<double>(), 0.0);
  EXPECT_EQ(j["std"]["k3"].get<double>(), 0.0);
  EXPECT_GT(j["std"]["k1"].get<double>(), 0.0);
  EXPECT_NE(j["k1"].get<double>(), 0.0);
  r = run_cli("simulate --fix k9");
  EXPECT_EQ(r.status, 2);
  EXPECT_NE(r.out.find("'k9'"), std::string::npos) << r.out;
  r = run_cli("simulate --fix k2,,k3");
  EXPECT_EQ(r.status, 1);
  EXPECT_NE(r.out.find("empty parameter name"), std::string::npos) << r.out;
  // A choice outside the table's list is a usage error, named by the canonical flag.
  r = run_cli("simulate --measure cat");
  EXPECT_EQ(r.status, 1);
  EXPECT_NE(r.out.find("--convergence-measure"), std::string::npos) << r.out;
  r = run_cli("simulate --score cat");
  EXPECT_EQ(r.status, 1);
  EXPECT_NE(r.out.find("--candidate-score"), std::string::npos) << r.out;
}

// --views: generic view candidates through the CLI and the session config.
TEST(Cli, SimulateWithViewCandidates) {
  CliRun r = run_cli("simulate --seed 5 --views 100 --measure std --json", true);
  ASSERT_EQ(r.status, 0) << r.out;
  const auto j = nlohmann::json::parse(r.out);
  EXPECT_TRUE(j["converged"].get<bool>());
  EXPECT_LE(j["keyframes"].get<int>(), 20);
  r = run_cli("simulate --views -1");
  EXPECT_EQ(r.status, 1);
  EXPECT_NE(r.out.find("--view-candidates"), std::string::npos) << r.out;
}

namespace {

// One key of core/session/session_keys.def, read as text: the CLI generates its session-config
// flags from that table, so the test reads the table itself rather than a list of its own.
struct TableKey {
  std::string key, alias;
};

std::vector<TableKey> session_table_keys() {
  std::ifstream in(std::string(POSECAL_SOURCE_DIR) + "/core/session/session_keys.def");
  std::stringstream ss;
  ss << in.rdbuf();
  const std::string text = ss.str();
  const std::string mark = "\nPOSECAL_KEY(";  // not the "// POSECAL_KEY(" of the comment
  const std::regex literal("\"((?:[^\"\\\\]|\\\\.)*)\"");
  std::vector<TableKey> keys;
  for (size_t at = text.find(mark); at != std::string::npos;) {
    const size_t next = text.find(mark, at + 1);
    const std::string entry = text.substr(at + mark.size(), next - at - mark.size());
    // scope, key, kind, member, lo, hi, then the literals choices, default, cli_alias, doc
    const size_t c1 = entry.find(','), c2 = entry.find(',', c1 + 1);
    std::string key = entry.substr(c1 + 1, c2 - c1 - 1);
    key.erase(std::remove(key.begin(), key.end(), ' '), key.end());
    std::vector<std::string> literals;
    for (std::sregex_iterator it(entry.begin(), entry.end(), literal), end; it != end; ++it) {
      literals.push_back((*it)[1]);
    }
    EXPECT_EQ(literals.size(), 4u) << entry;
    keys.push_back({key, literals.size() > 2 ? literals[2] : ""});
    at = next;
  }
  return keys;
}

// "--key" with '-' for '_'.
std::string flag_of(std::string key) {
  std::replace(key.begin(), key.end(), '_', '-');
  return "--" + key;
}

// True if `help` names `flag` as a whole word (--target, not the start of --target-timeout-frames).
bool names_flag(const std::string& help, const std::string& flag) {
  for (size_t at = help.find(flag); at != std::string::npos; at = help.find(flag, at + 1)) {
    const char after = at + flag.size() < help.size() ? help[at + flag.size()] : ' ';
    if (!std::isalnum(static_cast<unsigned char>(after)) && after != '-' && after != '_') {
      return true;
    }
  }
  return false;
}

}  // namespace

// Every command has its own --help, on stdout with exit code 0; so has posecal itself, while
// posecal without a command is a usage error.
TEST(Cli, EveryCommandHasItsOwnHelp) {
  const std::vector<std::string> commands = {"calibrate", "station",  "evaluate",
                                             "grab",      "features", "simulate",
                                             "board",     "list",     "version"};
  const CliRun top = run_cli("--help", true);
  ASSERT_EQ(top.status, 0) << top.out;
  for (const std::string& c : commands) {
    EXPECT_NE(top.out.find("\n  " + c + " "), std::string::npos) << c << " in\n" << top.out;
    for (const char* help : {" --help", " -h"}) {
      const CliRun r = run_cli(c + help, true);
      EXPECT_EQ(r.status, 0) << c << help << ": " << r.out;
      EXPECT_NE(r.out.find("Usage: posecal " + c + " [OPTIONS]"), std::string::npos)
          << c << help << ": " << r.out;
    }
  }
  EXPECT_NE(run_cli("grab --help", true).out.find("--count"), std::string::npos);
  EXPECT_EQ(run_cli("help", true).status, 0);
  CliRun r = run_cli("", true);
  EXPECT_EQ(r.status, 1);
  EXPECT_EQ(r.out, "");  // the usage goes to stderr
  EXPECT_NE(run_cli("").out.find("Usage: posecal"), std::string::npos);
}

TEST(Cli, VersionFlagIsTheVersionCommand) {
  const CliRun flag = run_cli("--version", true), command = run_cli("version", true);
  EXPECT_EQ(flag.status, 0);
  EXPECT_EQ(command.status, 0);
  EXPECT_EQ(flag.out, command.out);
  EXPECT_EQ(flag.out.rfind("posecal ", 0), 0u) << flag.out;
  EXPECT_NE(flag.out.find("(ABI 1)"), std::string::npos) << flag.out;
}

// The session-config flags are the table's keys: each key (and its older alias) is a flag of
// every session command.
TEST(Cli, EverySessionKeyIsAFlag) {
  const std::vector<TableKey> keys = session_table_keys();
  ASSERT_GE(keys.size(), 17u);
  for (const char* command : {"simulate", "station", "calibrate"}) {
    const CliRun help = run_cli(std::string(command) + " --help", true);
    ASSERT_EQ(help.status, 0) << help.out;
    for (const TableKey& k : keys) {
      EXPECT_TRUE(names_flag(help.out, flag_of(k.key))) << command << ": " << flag_of(k.key);
      if (k.alias.empty()) continue;
      const std::string alias = "--" + (k.alias[0] == '!' ? k.alias.substr(1) : k.alias);
      EXPECT_TRUE(names_flag(help.out, alias)) << command << ": " << alias;
    }
  }
}

// The flags check the table's ranges before anything runs (max_tilt_deg is [1, 88]); a value
// inside them reaches the library, which opens the session with it.
TEST(Cli, SessionFlagsCheckTheTablesRanges) {
  CliRun r = run_cli("simulate --max-tilt-deg 89");
  EXPECT_EQ(r.status, 1) << r.out;
  EXPECT_NE(r.out.find("max-tilt-deg"), std::string::npos) << r.out;
  EXPECT_NE(r.out.find("posecal simulate: "), std::string::npos) << r.out;
  EXPECT_NE(r.out.find("(see posecal --help)"), std::string::npos) << r.out;
  // One frame: the session opened (the library accepted the config) but cannot calibrate.
  for (const char* ok : {"--max-tilt-deg 88", "--max-tilt-deg=88", "--lock-settings=false",
                         "--fixed k3", "--operator=robot", "--target chessboard:9x6:0.025"}) {
    r = run_cli(std::string("simulate --max-frames 1 ") + ok);
    EXPECT_EQ(r.status, 2) << ok << ": " << r.out;
    EXPECT_NE(r.out.find("fewer than two keyframes [POSECAL_E_STATE]"), std::string::npos)
        << ok << ": " << r.out;
  }
  for (const char* bad : {"--max-keyframes 2", "--max-keyframes 5.5", "--threshold 1.5",
                          "--convergence-threshold 1.5", "--lock-settings=maybe",
                          "--prospective-only --measured-convergence"}) {
    r = run_cli(std::string("simulate ") + bad);
    EXPECT_EQ(r.status, 1) << bad << ": " << r.out;
  }
  // The alias is the canonical flag: its message names the canonical flag.
  EXPECT_NE(run_cli("simulate --threshold 1.5").out.find("--convergence-threshold"),
            std::string::npos);
}

// An alias and the canonical flag make the same session config: the same run, which the value
// changes (0.99: every parameter converges at the second keyframe; the default would need more
// than five). The text listing shows the result's covariance_order.
TEST(Cli, AliasAndCanonicalFlagAreOneSessionKey) {
  const std::string base = "simulate --seed 3 --max-keyframes 5 ";
  const CliRun a = run_cli(base + "--threshold 0.99 --json", true);
  ASSERT_EQ(a.status, 0) << a.out;
  const auto j = nlohmann::json::parse(a.out);
  EXPECT_EQ(j["keyframes"], 2);
  const CliRun b = run_cli(base + "--convergence-threshold=0.99", true);
  ASSERT_EQ(b.status, 0) << b.out;
  EXPECT_EQ(b.out.rfind("converged after 2 keyframes (" +
                            std::to_string(j["frames_processed"].get<int>()) + " frames",
                        0),
            0u)
      << b.out;
  ASSERT_EQ(j["covariance_order"].size(), 9u);
  for (const auto& name : j["covariance_order"]) {
    const std::string n = name.get<std::string>();
    char line[128];
    std::snprintf(line, sizeof line, "\n  %-3s = %14.6f  +- %.6f", n.c_str(), j[n].get<double>(),
                  j["std"][n].get<double>());
    EXPECT_NE(b.out.find(line), std::string::npos) << line << " in\n" << b.out;
  }
}

// --prospective-only (the table's "!" alias) sets measured_convergence false: the ratio test on
// captured keyframes, which converges fx and fy at seed 3's fifth keyframe, no longer runs.
TEST(Cli, ProspectiveOnlyTurnsMeasuredConvergenceOff) {
  const std::string base = "simulate --seed 3 --max-keyframes 5 --events --json";
  const std::string measured = "by the last keyframe";  // the measured test's event message
  CliRun r = run_cli(base);
  ASSERT_EQ(r.status, 3) << r.out;
  EXPECT_NE(r.out.find(measured), std::string::npos) << r.out;
  EXPECT_EQ(nlohmann::json::parse(lines_of(r.out).back())["keyframes"], 5);
  r = run_cli(base + " --prospective-only");
  ASSERT_EQ(r.status, 3) << r.out;
  EXPECT_EQ(r.out.find(measured), std::string::npos) << r.out;
  EXPECT_EQ(nlohmann::json::parse(lines_of(r.out).back())["keyframes"], 5);
}

// operator is a session key now (not simulate's URI option): the simulated operator follows it,
// and calibrate --camera puts it into the session config too.
TEST(Cli, OperatorIsASessionKey) {
  const CliRun r = run_cli("simulate --seed 2 --max-keyframes 3 --operator robot --json", true);
  ASSERT_EQ(r.status, 3) << r.out;
  const auto j = nlohmann::json::parse(r.out);
  EXPECT_NE(j["camera"]["uri"].get<std::string>().find("operator=robot"), std::string::npos)
      << r.out;
  CliRun c = run_cli("calibrate --camera 'sim://?seed=2&operator=person' --operator robot");
  EXPECT_EQ(c.status, 2) << c.out;
  EXPECT_NE(c.out.find("contradicts"), std::string::npos) << c.out;
  c = run_cli("calibrate --camera sim:// --guide stdio --operator person");
  EXPECT_EQ(c.status, 1) << c.out;
}

// posecal station over four simulated cameras: all converge, one result file per camera named
// by its identity, and a summary.
namespace {

// A station of four simulated cameras (one a robot), recorded in `records` (the station's
// default DIR/records.sqlite if empty): every camera converges, its model file is written, and
// its record is complete and re-solves bit for bit (records resolve / export).
void check_station_of_four(const std::string& dir, const std::string& records) {
  const std::string db = records.empty() ? dir + "/records.sqlite" : records;
  const auto t0 = std::chrono::steady_clock::now();
  const CliRun r = run_cli(
      "station --cameras 'sim://?seed=51,sim://?seed=52,sim://?seed=53,"
      "sim://?seed=54&operator=robot' --out-dir " +
          dir + (records.empty() ? "" : " --records '" + records + "'") + " --json",
      true);
  const double wall_s =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  ASSERT_EQ(r.status, 0) << r.out;
  const auto j = nlohmann::json::parse(r.out);
  EXPECT_EQ(j["total"], 4);
  EXPECT_EQ(j["converged"], 4);
  EXPECT_TRUE(j["all_converged"].get<bool>());
  std::set<std::string> files;
  double sum_camera_s = 0;
  for (const auto& c : j["cameras"]) {
    EXPECT_TRUE(c["converged"].get<bool>()) << c.dump();
    EXPECT_TRUE(c["error"].is_null()) << c.dump();
    EXPECT_GE(c["keyframes"].get<int>(), 5);
    EXPECT_LT(c["eps_test"].get<double>(), 0.3) << c.dump();
    const std::string file = c["file"].get<std::string>();
    files.insert(fs::path(file).filename().string());
    cv::FileStorage fsr(file, cv::FileStorage::READ);
    ASSERT_TRUE(fsr.isOpened()) << file;
    EXPECT_EQ(static_cast<std::string>(fsr["camera_id"]), c["camera"]["id"].get<std::string>());
    sum_camera_s += c["wall_ms"].get<double>() / 1000;
  }
  EXPECT_EQ(files, (std::set<std::string>{"sim-51.yml", "sim-52.yml", "sim-53.yml", "sim-54.yml"}));
  std::ifstream summary(dir + "/summary.json");
  ASSERT_TRUE(summary.good());
  EXPECT_EQ(nlohmann::json::parse(summary)["converged"], 4);
  EXPECT_EQ(j["fleet_outliers"], 0);
  for (const auto& c : j["cameras"]) {
    ASSERT_TRUE(c.contains("fleet")) << c.dump();
    EXPECT_TRUE(c["fleet"]["outlier"].is_null()) << c.dump();  // too few units yet
  }
  // Every camera's run is recorded (four writers on one store): complete, converged, its
  // keyframes with their detections and frames.
  auto store = posecal::RecordStore::open(db);
  EXPECT_EQ(store->list_runs().size(), 4u);
  for (const auto& c : j["cameras"]) {
    ASSERT_TRUE(c["run_id"].is_string()) << c.dump();
    EXPECT_TRUE(c["records_note"].is_null()) << c.dump();
    const posecal::RunRecord rec = store->get_run(c["run_id"].get<std::string>());
    EXPECT_EQ(rec.summary.state, "converged");
    EXPECT_EQ(rec.summary.identity.camera_id, c["camera"]["id"].get<std::string>());
    EXPECT_EQ(rec.image_width, 1280);
    ASSERT_EQ(static_cast<int>(rec.keyframes.size()), c["keyframes"].get<int>());
    for (const posecal::StoredKeyframe& k : rec.keyframes) {
      EXPECT_GT(posecal::keyframe_from_json(k.record).observation.ids.size(), 0u);
      EXPECT_FALSE(k.image_png.empty());
    }
    const auto result = nlohmann::json::parse(rec.result);
    EXPECT_EQ(result["keyframes"], c["keyframes"]);
    EXPECT_EQ(result["run_id"], c["run_id"]);
    // The fleet position: three other units of the model are too few for nine parameters.
    ASSERT_TRUE(result.contains("fleet")) << rec.result;
    EXPECT_TRUE(result["fleet"]["outlier"].is_null()) << result["fleet"].dump();
    EXPECT_NE(result["fleet"]["note"].get<std::string>().find("at least 12"), std::string::npos)
        << result["fleet"].dump();
    // records resolve: the calibration again from the stored detections, bit for bit.
    const std::string run_id = c["run_id"].get<std::string>();
    const CliRun rr = run_cli("records resolve " + run_id + " --db '" + db + "' --json", true);
    ASSERT_EQ(rr.status, 0) << rr.out;
    const auto rj = nlohmann::json::parse(rr.out);
    EXPECT_TRUE(rj["identical"].get<bool>()) << rr.out;
    EXPECT_EQ(rj["recomputed"], rj["stored"]);
    // records export: the re-solved model file equals the one the station wrote.
    const std::string exp_dir = dir + "/export-" + run_id;
    const CliRun re =
        run_cli("records export " + run_id + " --db '" + db + "' --out-dir " + exp_dir);
    ASSERT_EQ(re.status, 0) << re.out;
    const std::string id = c["camera"]["id"].get<std::string>();
    EXPECT_EQ(posecal::read_camera_model(exp_dir + "/" + id + ".yml").params(),
              posecal::read_camera_model(c["file"].get<std::string>()).params());
    std::ifstream exported_record(exp_dir + "/" + run_id + ".json");
    ASSERT_TRUE(exported_record.good());
    EXPECT_EQ(nlohmann::json::parse(exported_record)["keyframes"].size(), rec.keyframes.size());
  }
  const CliRun rl = run_cli("records list --db '" + db + "' --json", true);
  ASSERT_EQ(rl.status, 0) << rl.out;
  EXPECT_EQ(nlohmann::json::parse(rl.out).size(), 4u);
  // The cameras ran concurrently: the whole station took less than their sum.
  std::printf("station: %.1f s wall, %.1f s summed over the cameras\n", wall_s, sum_camera_s);
  EXPECT_LT(wall_s, sum_camera_s);
}

}  // namespace

TEST(Cli, StationOfFourSimulatedCamerasConverges) {
  check_station_of_four(temp_dir("posecal_station4"), "");
}

// The same station recording to a line's PostgreSQL server (started by the test).
TEST(Cli, StationOfFourSimulatedCamerasRecordsToPostgreSQL) {
  posecal::testing_pg::PgServer server;
  ASSERT_TRUE(server.error().empty()) << server.error();
  check_station_of_four(temp_dir("posecal_station4_pg"), server.create_database("station"));
}

TEST(Cli, StationReportsFailedCamerasAndIdentityClashes) {
  const std::string dir = temp_dir("posecal_station_bad");
  // Two sessions of one simulated camera (same id) and a camera that does not exist; three
  // keyframes at most, so the two simulated runs finish early without converging.
  const CliRun r = run_cli(
      "station --cameras 'sim://?seed=61,sim://?seed=61,images:///nonexistent/x'"
      " --max-keyframes 3 --out-dir " +
          dir + " --json",
      true);
  ASSERT_EQ(r.status, 2) << r.out;  // a failed camera outweighs unconverged ones
  const auto j = nlohmann::json::parse(r.out);
  EXPECT_EQ(j["converged"], 0);
  EXPECT_FALSE(j["all_converged"].get<bool>());
  for (int i : {0, 1}) {
    EXPECT_FALSE(j["cameras"][i]["converged"].get<bool>());
    EXPECT_TRUE(j["cameras"][i]["error"].is_null()) << j["cameras"][i].dump();
    EXPECT_EQ(j["cameras"][i]["keyframes"], 3);
  }
  EXPECT_EQ(j["cameras"][2]["status"], "POSECAL_E_NOT_FOUND");
  EXPECT_FALSE(j["cameras"][2]["error"].get<std::string>().empty());
  std::set<std::string> files = {fs::path(j["cameras"][0]["file"].get<std::string>()).filename(),
                                 fs::path(j["cameras"][1]["file"].get<std::string>()).filename()};
  EXPECT_EQ(files, (std::set<std::string>{"sim-61.yml", "sim-61-2.yml"}));
  EXPECT_EQ(run_cli("station --out-dir " + dir).status, 1);
  EXPECT_EQ(run_cli("station --cameras sim:// --out-dir " + dir + " --format txt").status, 1);
}

TEST(Cli, EvaluateGrabFeatures) {
  const std::string dir = temp_dir("posecal_eval");
  const std::string yml = dir + "/sim7.yml";
  CliRun r = run_cli("simulate --seed 7 --out " + yml + " --json", true);
  ASSERT_EQ(r.status, 0) << r.out;
  const auto sim = nlohmann::json::parse(r.out);

  // evaluate: the same simulated camera gives the session's eps_test and eps_gt.
  r = run_cli("evaluate --result " + yml + " --camera 'sim://?seed=7' --json", true);
  ASSERT_EQ(r.status, 0) << r.out;
  auto ev = nlohmann::json::parse(r.out);
  EXPECT_NEAR(ev["eps_test"].get<double>(), sim["eps_test"].get<double>(), 1e-6);
  EXPECT_NEAR(ev["eps_gt"].get<double>(), sim["eps_gt"].get<double>(), 1e-6);
  EXPECT_GE(ev["test_frames"].get<int>(), 40);
  // Another camera: the calibration does not fit it.
  r = run_cli("evaluate --result " + yml + " --camera 'sim://?seed=8' --json", true);
  ASSERT_EQ(r.status, 0) << r.out;
  EXPECT_GT(nlohmann::json::parse(r.out)["eps_gt"].get<double>(), 10 * sim["eps_gt"].get<double>());
  EXPECT_EQ(run_cli("evaluate --result /nonexistent.yml --camera sim://").status, 2);
  EXPECT_EQ(run_cli("evaluate --camera sim://").status, 1);

  // grab: PNG files that show the board.
  r = run_cli("grab --camera 'sim://?seed=7' --count 4 --out " + dir + "/frames --json", true);
  ASSERT_EQ(r.status, 0) << r.out;
  const auto g = nlohmann::json::parse(r.out);
  ASSERT_EQ(g["files"].size(), 4u);
  int with_board = 0;
  for (const auto& f : g["files"]) {
    const cv::Mat img = cv::imread(f["file"].get<std::string>(), cv::IMREAD_UNCHANGED);
    ASSERT_EQ(img.cols, 1280);
    ASSERT_EQ(img.rows, 720);
    if (posecal::Board().detect(img).size() >= 6) ++with_board;
  }
  EXPECT_GE(with_board, 3);
  // The grabbed frames are a camera for evaluate too (images://).
  r = run_cli("evaluate --result " + yml + " --camera images://" + dir + "/frames --json", true);
  ASSERT_EQ(r.status, 0) << r.out;
  ev = nlohmann::json::parse(r.out);
  EXPECT_EQ(ev["source"], "camera");
  EXPECT_TRUE(ev["eps_gt"].is_null());
  EXPECT_LT(ev["eps_test"].get<double>(), 0.5);
  r = run_cli("evaluate --result " + yml + " --camera images://" + dir + "/frames");
  EXPECT_EQ(r.status, 0);
  EXPECT_NE(r.out.find("eps_test"), std::string::npos) << r.out;
  EXPECT_EQ(run_cli("grab --camera sim:// --out " + dir + "/x").status, 1);  // no --count
  EXPECT_EQ(run_cli("grab --camera sim:// --count 0 --out " + dir + "/x").status, 1);
  r = run_cli("grab --camera external --count 1 --timeout-ms 50 --out " + dir + "/x");
  EXPECT_EQ(r.status, 2);
  EXPECT_NE(r.out.find("POSECAL_E_TIMEOUT"), std::string::npos) << r.out;

  // features
  r = run_cli("features --camera 'sim://?seed=7' --json", true);
  ASSERT_EQ(r.status, 0) << r.out;
  const auto feats = nlohmann::json::parse(r.out);
  ASSERT_FALSE(feats.empty());
  for (const auto& f : feats) {
    for (const char* k : {"name", "type", "value", "access", "unit", "range", "options"}) {
      EXPECT_TRUE(f.contains(k)) << k << " in " << f.dump();
    }
  }
  r = run_cli("features --camera 'sim://?seed=7'");
  EXPECT_EQ(r.status, 0);
  EXPECT_NE(r.out.find("Width"), std::string::npos) << r.out;
  EXPECT_EQ(run_cli("features --camera nosuch://x").status, 2);
}

TEST(Cli, LiveCalibrationPrintsJsonEvents) {
  const std::string dir = temp_dir("posecal_live");
  const CliRun r =
      run_cli("calibrate --camera 'sim://?seed=9' --json --out " + dir + "/live.yml", true);
  ASSERT_EQ(r.status, 0) << r.out;
  const auto lines = lines_of(r.out);
  ASSERT_GT(lines.size(), 5u);
  std::set<std::string> kinds;
  const std::regex iso8601(R"(\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}Z)");
  int64_t previous_ms = -1;
  for (const auto& line : lines) {
    const auto j = nlohmann::json::parse(line);  // every line is one JSON object
    kinds.insert(j["event"].get<std::string>());
    // Every event is stamped: UTC wall time and a monotonic clock that never goes back.
    ASSERT_TRUE(j["time"].is_string()) << line;
    EXPECT_TRUE(std::regex_match(j["time"].get<std::string>(), iso8601)) << line;
    ASSERT_TRUE(j["mono_ms"].is_number_integer()) << line;
    EXPECT_GE(j["mono_ms"].get<int64_t>(), previous_ms) << line;
    previous_ms = j["mono_ms"].get<int64_t>();
  }
  EXPECT_TRUE(kinds.count("captured"));
  EXPECT_TRUE(kinds.count("state_changed"));
  const auto last = nlohmann::json::parse(lines.back());
  EXPECT_EQ(last["event"], "result");
  EXPECT_TRUE(last["converged"].get<bool>());
  EXPECT_TRUE(fs::exists(dir + "/live.yml"));
}

// The live window's path (last frame + overlay + imshow) with Qt's offscreen platform, and a
// DISPLAY where no X server answers: headless instead of the toolkit ending the process.
TEST(Cli, LiveWindowOffscreenAndUnreachableDisplay) {
  // Four keyframes at most: the window shows every frame until the run ends (exit code 3).
  // The result screen stays --result-seconds (no key is pressed offscreen).
  const auto t0 = std::chrono::steady_clock::now();
  CliRun r =
      run_cli("calibrate --camera 'sim://?seed=15' --max-keyframes 4 --result-seconds 2 --json",
              true, "DISPLAY=:97 POSECAL_WINDOW=force QT_QPA_PLATFORM=offscreen");
  EXPECT_GE(std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count(), 2.0);
  ASSERT_EQ(r.status, 3) << r.out;
  EXPECT_EQ(nlohmann::json::parse(lines_of(r.out).back())["event"], "result");
  // No X server at :97: headless, with a message (a folder of three frames: over at once).
  const std::string dir = temp_dir("posecal_window");
  ASSERT_EQ(run_cli("grab --camera 'sim://?seed=15' --count 3 --out " + dir).status, 0);
  r = run_cli("calibrate --camera images://" + dir, false,
              "-u POSECAL_WINDOW -u QT_QPA_PLATFORM DISPLAY=:97");
  EXPECT_EQ(r.status, 2) << r.out;  // three frames: no calibration
  EXPECT_NE(r.out.find("no X server answers at DISPLAY=:97"), std::string::npos) << r.out;
}

namespace {

// The CLI as a child process with pipes on stdin and stdout: a robot controller's view.
class Controller {
 public:
  explicit Controller(const std::vector<std::string>& args) {
    int in[2], out[2];
    if (pipe(in) != 0 || pipe(out) != 0) return;
    pid_ = fork();
    if (pid_ == 0) {
      dup2(in[0], STDIN_FILENO);
      dup2(out[1], STDOUT_FILENO);
      const int devnull = open("/dev/null", O_WRONLY);
      dup2(devnull, STDERR_FILENO);
      close(in[1]);
      close(out[0]);
      unsetenv("DISPLAY");
      std::vector<char*> argv{const_cast<char*>(POSECAL_CLI)};
      for (const auto& a : args) argv.push_back(const_cast<char*>(a.c_str()));
      argv.push_back(nullptr);
      execv(POSECAL_CLI, argv.data());
      _exit(127);
    }
    close(in[0]);
    close(out[1]);
    to_child_ = in[1];
    from_child_ = out[0];
    signal(SIGPIPE, SIG_IGN);
  }
  ~Controller() {
    if (to_child_ >= 0) close(to_child_);
    if (from_child_ >= 0) close(from_child_);
    if (pid_ > 0 && !reaped_) {
      kill(pid_, SIGKILL);
      waitpid(pid_, nullptr, 0);
    }
  }
  bool started() const { return pid_ > 0; }
  // Next line from the child, or "" on EOF or after timeout_ms.
  std::string read_line(int timeout_ms) {
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::milliseconds(timeout_ms);
    while (true) {
      const size_t nl = buffer_.find('\n');
      if (nl != std::string::npos) {
        std::string line = buffer_.substr(0, nl);
        buffer_.erase(0, nl + 1);
        return line;
      }
      const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(
                            deadline - std::chrono::steady_clock::now())
                            .count();
      if (left <= 0) return "";
      pollfd p{from_child_, POLLIN, 0};
      if (poll(&p, 1, static_cast<int>(left)) <= 0) continue;
      char buf[4096];
      const ssize_t n = read(from_child_, buf, sizeof buf);
      if (n <= 0) return "";
      buffer_.append(buf, static_cast<size_t>(n));
    }
  }
  void send(const std::string& line) {
    const std::string text = line + "\n";
    ASSERT_EQ(write(to_child_, text.data(), text.size()), static_cast<ssize_t>(text.size()));
  }
  void close_stdin() {
    close(to_child_);
    to_child_ = -1;
  }
  int wait_exit() {
    int status = 0;
    waitpid(pid_, &status, 0);
    reaped_ = true;
    return WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  }

 private:
  pid_t pid_ = -1;
  int to_child_ = -1, from_child_ = -1;
  bool reaped_ = false;
  std::string buffer_;
};

}  // namespace

// The robot protocol of `calibrate --guide stdio`, end to end with the simulated robot: the CLI
// prints each target pose as a JSON line and does not go on until the controller answers.
TEST(Cli, RobotStdioProtocolEndToEnd) {
  Controller c({"calibrate", "--camera", "sim://?seed=13&operator=robot", "--guide", "stdio",
                "--reply-timeout-s", "60"});
  ASSERT_TRUE(c.started());
  int targets = 0, serial = 0;
  bool sent_garbage = false, skipped = false, expect_new_target = false;
  nlohmann::json result;
  while (true) {
    const std::string line = c.read_line(60000);
    ASSERT_FALSE(line.empty()) << "no line from the CLI (after " << targets << " targets)";
    const auto j = nlohmann::json::parse(line);
    const std::string event = j["event"].get<std::string>();
    if (event == "result") {
      result = j;
      break;
    }
    if (event == "protocol_error") {
      EXPECT_TRUE(sent_garbage && !expect_new_target) << line;
      c.send("{\"reached\": true}");
      continue;
    }
    ASSERT_EQ(event, "target") << line;
    expect_new_target = false;
    ++targets;
    EXPECT_EQ(j["serial"].get<int>(), ++serial);
    ASSERT_EQ(j["rvec"].size(), 3u);
    ASSERT_EQ(j["tvec"].size(), 3u);
    EXPECT_GT(j["tvec"][2].get<double>(), 0.05) << "the board must be in front of the camera";
    EXPECT_EQ(j["frame"], "T_cam_board");
    if (targets == 2) {
      // While the controller has not answered, the CLI waits: nothing more comes.
      EXPECT_EQ(c.read_line(700), "");
    }
    if (targets == 3 && !sent_garbage) {
      sent_garbage = true;
      c.send("where am I?");  // answered with a protocol_error line, then the CLI waits again
      continue;
    }
    if (!skipped && j["state"] == "refining") {
      // A target the robot cannot reach: skipped, and the next line is the next target.
      skipped = expect_new_target = true;
      c.send("skip");
      continue;
    }
    c.send(targets % 2 ? "reached" : "{\"reached\": true}");
  }
  EXPECT_EQ(c.wait_exit(), 0);
  EXPECT_TRUE(result["converged"].get<bool>()) << result.dump();
  EXPECT_GE(targets, 5);
  EXPECT_TRUE(sent_garbage);
  EXPECT_TRUE(skipped);
}

TEST(Cli, RobotStdioControllerGoneOrAborting) {
  {
    Controller c({"calibrate", "--camera", "sim://?seed=14&operator=robot", "--guide", "stdio"});
    ASSERT_TRUE(c.started());
    const auto j = nlohmann::json::parse(c.read_line(60000));
    EXPECT_EQ(j["event"], "target");
    c.close_stdin();
    EXPECT_EQ(c.wait_exit(), 2);
  }
  {
    Controller c({"calibrate", "--camera", "sim://?seed=14&operator=robot", "--guide", "stdio"});
    ASSERT_TRUE(c.started());
    EXPECT_EQ(nlohmann::json::parse(c.read_line(60000))["event"], "target");
    c.send("abort");
    EXPECT_EQ(c.wait_exit(), 2);
  }
  {
    Controller c({"calibrate", "--camera", "sim://?seed=14&operator=robot", "--guide", "stdio",
                  "--reply-timeout-s", "0.5"});
    ASSERT_TRUE(c.started());
    EXPECT_EQ(nlohmann::json::parse(c.read_line(60000))["event"], "target");
    EXPECT_EQ(c.wait_exit(), 2);  // no reply within 0.5 s
  }
}

// ---- Result file formats (issue 17; docs/formats.md) -----------------------------------------

namespace {

std::string read_text(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  return std::string((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
}

// One short simulated calibration (seed 3, 4 keyframes: k3 != 0) written as `out` with `args`.
CliRun simulate_to(const std::string& out, const std::string& args = "") {
  fs::remove(out);
  return run_cli("simulate --seed 3 --max-keyframes 4 --json --out " + out + " " + args, true);
}

// The intrinsics of a --json result, in the model's parameter order.
std::vector<double> result_params(const nlohmann::json& j) {
  std::vector<double> p;
  for (const auto& name : j["covariance_order"]) p.push_back(j[name.get<std::string>()].get<double>());
  return p;
}

}  // namespace

TEST(Cli, FormatMrcalByExtensionAndRosByName) {
  const std::string dir = temp_dir("posecal_formats");
  const std::string mrcal = dir + "/x.cameramodel", ros = dir + "/x.yaml", xml = dir + "/x.xml";
  const CliRun a = simulate_to(mrcal);
  ASSERT_TRUE(a.status == 0 || a.status == 3) << a.out;  // 3: not converged, still written
  const std::vector<double> params = result_params(nlohmann::json::parse(a.out));
  const posecal::ModelFile m = posecal::read_model_file(mrcal);
  EXPECT_EQ(m.format, posecal::ModelFormat::kMrcal);
  ASSERT_EQ(m.model.params().size(), params.size());
  for (size_t i = 0; i < params.size(); ++i) EXPECT_DOUBLE_EQ(m.model.params()[i], params[i]) << i;
  EXPECT_NE(read_text(mrcal).find("'lensmodel': 'LENSMODEL_OPENCV5'"), std::string::npos);

  const CliRun b = simulate_to(ros, "--format ros");
  ASSERT_TRUE(b.status == 0 || b.status == 3) << b.out;
  const posecal::ModelFile r = posecal::read_model_file(ros);
  EXPECT_EQ(r.format, posecal::ModelFormat::kRos);
  EXPECT_EQ(r.model.params(), m.model.params());  // the same calibration (seed 3)
  EXPECT_NE(read_text(ros).find("camera_name: sim_3\n"), std::string::npos) << read_text(ros);

  // OpenCV XML by extension, with the covariance and the outcome as 0/1.
  const CliRun c = simulate_to(xml);
  ASSERT_TRUE(c.status == 0 || c.status == 3) << c.out;
  const posecal::ModelFile x = posecal::read_model_file(xml);
  EXPECT_EQ(x.model.params(), m.model.params());
  EXPECT_EQ(x.extras.covariance.size(), params.size() * params.size());
  EXPECT_EQ(x.extras.converged, std::optional<bool>(c.status == 0));
  EXPECT_NE(read_text(xml).find("<converged>"), std::string::npos);
}

TEST(Cli, FormatUnknownOrNotMatchingTheFileIsAUsageError) {
  const std::string dir = temp_dir("posecal_formats_usage");
  const auto t0 = std::chrono::steady_clock::now();
  CliRun r = simulate_to(dir + "/x.yml", "--format halcon7");
  EXPECT_EQ(r.status, 1);
  r = run_cli("simulate --seed 3 --out " + dir + "/x.yml --format halcon7");
  EXPECT_NE(r.out.find("--format"), std::string::npos) << r.out;
  EXPECT_NE(r.out.find("halcon7"), std::string::npos) << r.out;
  r = run_cli("simulate --seed 3 --out " + dir + "/x.yml --format mrcal");
  EXPECT_EQ(r.status, 1) << r.out;
  EXPECT_NE(r.out.find(".cameramodel"), std::string::npos) << r.out;
  r = run_cli("calibrate --images " + dir + " --out " + dir + "/x.txt");
  EXPECT_EQ(r.status, 1) << r.out;
  // Refused before any calibration ran, and nothing written.
  EXPECT_LT(std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count(), 10);
  EXPECT_FALSE(fs::exists(dir + "/x.yml"));
  EXPECT_FALSE(fs::exists(dir + "/x.txt"));
}

// Kalibr's radtan has no k3, and HALCON's polynomial follows this strongly distorted lens far
// worse than its limit of 0.1 px: the calibration is refused naming the format and the model;
// nothing is written.
TEST(Cli, FormatKalibrAndHalconRefuseAModelTheyCannotHold) {
  const std::string dir = temp_dir("posecal_formats_refused");
  for (const std::string format : {"kalibr", "halcon"}) {
    const std::string out = dir + (format == "kalibr" ? "/camchain.yaml" : "/camera.dat");
    const CliRun r =
        run_cli("simulate --seed 3 --max-keyframes 4 --format " + format + " --out " + out);
    EXPECT_EQ(r.status, 2) << r.out;
    for (const std::string& needle :
         {format, std::string("opencv5"), std::string(format == "kalibr" ? "k3" : "0.1 px"),
          std::string("nothing written"), std::string("INVALID_ARGUMENT")}) {
      EXPECT_NE(r.out.find(needle), std::string::npos) << needle << " in " << r.out;
    }
    EXPECT_FALSE(fs::exists(out));
  }
}

// The station's --format names a format: one file per camera with the format's extension.
TEST(Cli, FormatOfTheStationFiles) {
  const std::string dir = temp_dir("posecal_formats_station");
  const CliRun r = run_cli(
      "station --cameras 'sim://?seed=3' --max-keyframes 4 --format mrcal "
      "--out-dir " +
          dir + " --json",
      true);
  ASSERT_TRUE(r.status == 0 || r.status == 3) << r.out;
  const auto j = nlohmann::json::parse(r.out);
  const std::string file = j["cameras"][0]["file"].get<std::string>();
  EXPECT_EQ(fs::path(file).filename().string(), "sim-3.cameramodel");
  EXPECT_EQ(posecal::read_model_file(file).format, posecal::ModelFormat::kMrcal);
}

namespace {

std::string write_spec(const std::string& dir, const std::string& name, const std::string& text) {
  const std::string path = dir + "/" + name;
  std::ofstream(path) << text;
  return path;
}

}  // namespace

// The quality gate (issue 15 item 3): a specification the simulated C525 family passes and one
// it fails, with the reasons and exit codes; a malformed one refused naming the key, before any
// frame.
TEST(Cli, QualitySpecGivesAVerdictWithReasonsAndExitCodes) {
  const std::string dir = temp_dir("posecal_quality_spec");
  // The family: sim:// cameras sampled around the C525 (fx 920-1100 px, cx 520-680 px).
  const std::string pass = write_spec(dir, "pass.json", R"({
    "max_expected_error_px": 0.6, "max_eps_res_px": 0.5, "max_keyframes": 15,
    "max_seconds": 300,
    "parameters": {"fx": {"nominal": 1030, "tolerance": 0.25},
                   "cx": {"nominal": 640, "tolerance": 0.25}}})");
  const std::string fail = write_spec(dir, "fail.json", R"({
    "max_expected_error_px": 0.05, "max_keyframes": 3,
    "parameters": {"fx": {"nominal": 1030, "tolerance": 0.25},
                   "k1": {"nominal": 0.5, "tolerance_abs": 0.05}}})");
  for (const int seed : {1, 2}) {
    const std::string base = "simulate --seed " + std::to_string(seed) + " --json --spec ";
    CliRun r = run_cli(base + pass, true);
    ASSERT_EQ(r.status, 0) << r.out;
    auto j = nlohmann::json::parse(r.out);
    EXPECT_EQ(j["verdict"], "pass") << j["verdict_reasons"].dump();
    EXPECT_TRUE(j["verdict_reasons"].empty());
    EXPECT_EQ(j["spec"], pass);

    r = run_cli(base + fail, true);
    EXPECT_EQ(r.status, 4) << r.out;  // converged, but the specification failed
    j = nlohmann::json::parse(r.out);
    EXPECT_EQ(j["verdict"], "fail");
    const std::string reasons = j["verdict_reasons"].dump();
    EXPECT_NE(reasons.find("expected_error_px"), std::string::npos) << reasons;
    EXPECT_NE(reasons.find("keyframes"), std::string::npos) << reasons;
    EXPECT_NE(reasons.find("k1"), std::string::npos) << reasons;
    EXPECT_EQ(reasons.find("fx"), std::string::npos) << reasons;  // within its tolerance
  }
  // Text mode says it too.
  CliRun r = run_cli("simulate --seed 1 --spec " + fail);
  EXPECT_EQ(r.status, 4);
  EXPECT_NE(r.out.find("quality spec " + fail + ": FAIL"), std::string::npos) << r.out;

  // A station: each camera's verdict in the summary, the count that passed, exit code 4.
  r = run_cli("station --cameras 'sim://?seed=1,sim://?seed=2' --out-dir " + dir +
                  "/station --json --spec " + fail,
              true);
  EXPECT_EQ(r.status, 4) << r.out;
  auto sum = nlohmann::json::parse(r.out);
  EXPECT_EQ(sum["converged"], 2);
  EXPECT_EQ(sum["passed"], 0);
  for (const auto& c : sum["cameras"]) EXPECT_EQ(c["verdict"], "fail") << c.dump();

  // Malformed specifications: exit 2, the file and the key named.
  for (const auto& [name, text, named] :
       {std::tuple<std::string, std::string, std::string>{"unknown.json", R"({"max_error": 1})",
                                                           "unknown key 'max_error'"},
        {"param.json", R"({"parameters": {"k9": {"nominal": 1, "tolerance": 0.1}}})",
         "'parameters.k9'"},
        {"negative.json", R"({"max_eps_res_px": -1})", "'max_eps_res_px' must be a positive"},
        {"notol.json", R"({"parameters": {"fx": {"nominal": 1000}}})", "needs 'tolerance'"},
        {"broken.json", R"({"max_eps_res_px": )", "not valid JSON"}}) {
    const std::string path = write_spec(dir, name, text);
    r = run_cli("simulate --seed 1 --spec " + path);
    EXPECT_EQ(r.status, 2) << name << ": " << r.out;
    EXPECT_NE(r.out.find(named), std::string::npos) << name << ": " << r.out;
    EXPECT_NE(r.out.find(path), std::string::npos) << name << ": " << r.out;
  }
  r = run_cli("simulate --seed 1 --spec " + dir + "/missing.json");
  EXPECT_EQ(r.status, 2) << r.out;
  EXPECT_NE(r.out.find("does not exist"), std::string::npos) << r.out;
}

// Records (issue 15): simulate --records keeps the run with the given ids; the same run id again
// is not recorded twice (the first record is intact); a store that cannot be opened does not
// cost the calibration, and the result says why it was not recorded.
TEST(Cli, RecordsKeepTheRunAndNeverCostTheCalibration) {
  const std::string dir = temp_dir("posecal_records");
  const std::string db = dir + "/records.sqlite";
  const std::string base = "simulate --seed 2 --json --records " + db;
  CliRun r = run_cli(base + " --station-id line1-st2 --operator-id op7 --lens-id M12-6mm", true);
  ASSERT_EQ(r.status, 0) << r.out;
  auto j = nlohmann::json::parse(r.out);
  ASSERT_TRUE(j["run_id"].is_string()) << r.out;
  const std::string run_id = j["run_id"];
  EXPECT_EQ(j["records"], db);
  EXPECT_TRUE(j["records_note"].is_null());
  {
    auto store = posecal::RecordStore::open(db);
    const posecal::RunRecord rec = store->get_run(run_id);
    EXPECT_EQ(rec.summary.state, "converged");
    EXPECT_EQ(rec.summary.identity.station_id, "line1-st2");
    EXPECT_EQ(rec.summary.identity.operator_id, "op7");
    EXPECT_EQ(rec.summary.identity.lens_id, "M12-6mm");
    EXPECT_EQ(static_cast<int>(rec.keyframes.size()), j["keyframes"].get<int>());
    ASSERT_TRUE(rec.summary.expected_error_px.has_value());
    EXPECT_EQ(*rec.summary.expected_error_px, j["expected_error_px"].get<double>());
  }
  r = run_cli(base + " --run-id " + run_id, true);
  ASSERT_EQ(r.status, 0) << r.out;
  j = nlohmann::json::parse(r.out);
  ASSERT_TRUE(j["records_note"].is_string()) << r.out;
  EXPECT_NE(j["records_note"].get<std::string>().find("already recorded"), std::string::npos);
  EXPECT_EQ(posecal::RecordStore::open(db)->get_run(run_id).summary.identity.station_id, "line1-st2");

  // The readers: an unknown run is a clear error; show names the run's ids and keyframes.
  r = run_cli("records show no-such-run --db " + db);
  EXPECT_EQ(r.status, 2) << r.out;
  EXPECT_NE(r.out.find("no run no-such-run"), std::string::npos) << r.out;
  r = run_cli("records show " + run_id.substr(0, 8) + " --db " + db + " --json", true);
  ASSERT_EQ(r.status, 0) << r.out;
  EXPECT_EQ(nlohmann::json::parse(r.out)["lens_id"], "M12-6mm");
  r = run_cli("records list --db " + dir + "/missing-dir/r.sqlite");
  EXPECT_EQ(r.status, 2) << r.out;
  EXPECT_NE(r.out.find("missing-dir/r.sqlite"), std::string::npos) << r.out;

  r = run_cli("simulate --seed 2 --json --journal " + dir + "/s2.journal --records " + dir +
                  "/no/such/dir/r.sqlite",
              true);
  ASSERT_EQ(r.status, 0) << r.out;  // converged all the same
  j = nlohmann::json::parse(r.out);
  ASSERT_TRUE(j["records_note"].is_string()) << r.out;
  EXPECT_NE(j["records_note"].get<std::string>().find("no/such/dir/r.sqlite"), std::string::npos);
  EXPECT_TRUE(j["converged"].get<bool>());
  // The journal is the spool: recorded afterwards, the run re-solves to the same calibration.
  r = run_cli("records import " + dir + "/s2.journal --db " + db + " --lens-id M12-6mm --json",
              true);
  ASSERT_EQ(r.status, 0) << r.out;
  const auto imported = nlohmann::json::parse(r.out);
  EXPECT_EQ(imported["state"], "converged");
  EXPECT_EQ(imported["keyframes"], j["keyframes"]);
  const std::string imported_id = imported["run_id"];
  r = run_cli("records resolve " + imported_id + " --db " + db + " --json", true);
  ASSERT_EQ(r.status, 0) << r.out;
  const auto solved = nlohmann::json::parse(r.out);
  EXPECT_TRUE(solved["identical"].get<bool>()) << r.out;
  for (const char* k : {"fx", "fy", "cx", "cy", "k1"})
    EXPECT_EQ(solved["recomputed"][k].get<double>(), j[k].get<double>()) << k;  // bit for bit
  r = run_cli("records import " + db + " --db " + db);                          // not a journal
  EXPECT_EQ(r.status, 2) << r.out;
}

// A station run's directory (issue 15): the summary names the run (its id, times, version); a
// finished run is not calibrated over without --force; with it, the old run's files go (no stale
// file beside the new summary) and the records keep both runs.
// A fleet of `units` passed runs of "synthetic camera 1280x720" with lens L1 in a new SQLite
// store: C525 units with 0.3% focal and 0.5 px principal-point spread, as a line's earlier
// calibrations would have left them (results only; the prior needs nothing else).
void write_fleet(const std::string& db, int units) {
  auto store = posecal::RecordStore::open(db);
  cv::RNG rng(99);
  const posecal::CameraModel ref = posecal::c525_reference_model();
  for (int i = 0; i < units; ++i) {
    posecal::RunIdentity id;
    id.run_id = posecal::new_run_id();
    id.camera_model = "synthetic camera 1280x720";
    id.camera_serial = std::to_string(7000 + i);
    id.lens_id = "L1";
    id.config = "{}";
    id.started = "2026-12-04T08:00:00Z";
    store->begin_run(id);
    nlohmann::json r = {{"model", "opencv5"},           {"image_width", 1280},
                        {"image_height", 720},          {"residual_sigma", 0.03},
                        {"expected_error_p90_px", 0.4}, {"converged", true}};
    const double f = 1 + 0.003 * rng.gaussian(1);
    const std::vector<double> sd = {0, 0, 0.5, 0.5, 0.0002, 0.005, 0.0002, 0.0002, 0.007};
    for (int k = 0; k < 9; ++k) {
      double v = ref.params()[k] + sd[k] * rng.gaussian(1);
      if (k < 2) v = ref.params()[k] * f * (k == 1 ? 1 + 0.0005 * rng.gaussian(1) : 1.0);
      r[ref.param_names()[k]] = v;
    }
    store->finish_run(id.run_id, "converged", r.dump(), "", 0.3);
  }
}

// "prior": "fleet": the session starts from the fleet of its camera model and lens in the
// records, stops at the fleet's median expected error, records the prior it used so that
// `records resolve` reproduces the run bit for bit; too small a fleet calibrates without it and
// says why; without a store the key is refused naming 'records'.
TEST(Cli, FleetPriorFromTheRecords) {
  const std::string dir = temp_dir("posecal_fleet_prior");
  const std::string db = dir + "/records.sqlite";
  write_fleet(db, 15);
  // This unit: the C525 with the principal point 1 px off.
  posecal::CameraModel unit = posecal::c525_reference_model();
  unit.params()[2] += 1;
  posecal::write_camera_model(dir + "/unit.yml", unit);
  const std::string base =
      "simulate --seed 5 --camera-model " + dir + "/unit.yml --json --lens-id L1 --records " + db;
  CliRun r = run_cli(base + " --prior fleet", true);
  ASSERT_EQ(r.status, 0) << r.out;
  auto j = nlohmann::json::parse(r.out);
  ASSERT_TRUE(j["prior"]["used"].get<bool>()) << j["prior"].dump();
  EXPECT_EQ(j["prior"]["units"], 15);
  EXPECT_NEAR(j["prior"]["accuracy_px"].get<double>(), 0.4, 1e-12);
  EXPECT_TRUE(j["converged"].get<bool>()) << r.out;
  EXPECT_LE(j["expected_error_p90_px"].get<double>(), 0.4);
  const int with_prior = j["keyframes"].get<int>();
  // The outlier test ran on the keyframes' own estimate (the prior pulls towards the fleet).
  EXPECT_EQ(j["fleet"]["tested"], "keyframes without the prior") << j["fleet"].dump();
  EXPECT_FALSE(j["fleet"]["outlier"].get<bool>()) << j["fleet"].dump();
  const std::string run_id = j["run_id"];
  // More units in the store now: the re-solve still uses the prior the run had.
  write_fleet(db, 3);
  CliRun rr = run_cli("records resolve " + run_id + " --db " + db + " --json", true);
  ASSERT_EQ(rr.status, 0) << rr.out;
  EXPECT_TRUE(nlohmann::json::parse(rr.out)["identical"].get<bool>()) << rr.out;

  // The same unit and operator without the prior: more keyframes for the same figure.
  r = run_cli(base + " --accuracy-px 0.4", true);
  ASSERT_EQ(r.status, 0) << r.out;
  j = nlohmann::json::parse(r.out);
  EXPECT_FALSE(j.contains("prior")) << r.out;
  EXPECT_LT(with_prior, j["keyframes"].get<int>());

  // Too few units: no prior, and why.
  const std::string small = dir + "/small.sqlite";
  write_fleet(small, 5);
  r = run_cli("simulate --seed 5 --json --lens-id L1 --camera-model " + dir +
                  "/unit.yml --prior fleet --records " + small,
              true);
  ASSERT_EQ(r.status, 0) << r.out;
  j = nlohmann::json::parse(r.out);
  EXPECT_FALSE(j["prior"]["used"].get<bool>());
  EXPECT_NE(j["prior"]["note"].get<std::string>().find("at least"), std::string::npos)
      << j["prior"].dump();
  EXPECT_TRUE(j["converged"].get<bool>());

  // No store: refused before anything runs.
  r = run_cli("simulate --seed 5 --prior fleet");
  EXPECT_NE(r.status, 0);
  EXPECT_NE(r.out.find("needs 'records'"), std::string::npos) << r.out;
}

TEST(Cli, AStationRunOwnsItsDirectory) {
  const std::string dir = temp_dir("posecal_station_dir");
  CliRun r =
      run_cli("station --cameras 'sim://?seed=1,sim://?seed=2' --out-dir " + dir + " --json", true);
  ASSERT_EQ(r.status, 0) << r.out;
  const auto first = nlohmann::json::parse(r.out);
  ASSERT_TRUE(first["station_run_id"].is_string()) << r.out;
  EXPECT_TRUE(first["started"].is_string());
  EXPECT_TRUE(first["finished"].is_string());
  EXPECT_TRUE(first["interrupted_cameras"].empty());
  ASSERT_TRUE(fs::exists(dir + "/sim-2.yml"));

  r = run_cli("station --cameras 'sim://?seed=1' --out-dir " + dir);
  EXPECT_EQ(r.status, 1) << r.out;
  EXPECT_NE(r.out.find("--force"), std::string::npos) << r.out;
  EXPECT_NE(r.out.find(first["station_run_id"].get<std::string>()), std::string::npos) << r.out;
  EXPECT_TRUE(fs::exists(dir + "/sim-2.yml"));  // nothing was touched

  r = run_cli("station --cameras 'sim://?seed=1' --out-dir " + dir + " --json --force", true);
  ASSERT_EQ(r.status, 0) << r.out;
  const auto second = nlohmann::json::parse(r.out);
  EXPECT_NE(second["station_run_id"], first["station_run_id"]);
  EXPECT_EQ(second["cameras"][0]["resumed_keyframes"], 0);  // afresh: the journals went
  EXPECT_TRUE(fs::exists(dir + "/sim-1.yml"));
  EXPECT_FALSE(fs::exists(dir + "/sim-2.yml")) << "the old run's file is left beside the new";
  EXPECT_EQ(posecal::RecordStore::open(dir + "/records.sqlite")->list_runs().size(), 3u);
}
