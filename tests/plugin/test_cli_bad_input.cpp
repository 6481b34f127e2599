// The command line on bad input (issue 16): model files that are FIFOs, nested without end,
// of the wrong type or size; board specs out of range; a model that fits no test frame;
// invalid UTF-8 from a robot controller; a DISPLAY that is not an X server. Each ends in a clear
// error or goes on; none blocks, crashes or reports POSECAL_E_INTERNAL.
#include <arpa/inet.h>
#include <gtest/gtest.h>
#include <netinet/in.h>
#include <sys/socket.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <unistd.h>

#include <array>
#include <atomic>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "cli_child.hpp"

namespace fs = std::filesystem;

namespace {

using posecal_test::CliRun;
using posecal_test::run_cli;

std::string temp_file(const std::string& name, const std::string& text) {
  const std::string path = (fs::path(testing::TempDir()) / ("posecal_cli_bad_" + name)).string();
  std::ofstream(path, std::ios::binary) << text;
  return path;
}

std::string model_yaml(const std::string& size, const std::string& fx,
                       const std::string& dt = "d") {
  return "%YAML:1.0\n---\n" + size +
         "camera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: " + dt + "\n   data: [ " +
         fx + ", 0., 640., 0., " + fx +
         ", 360., 0., 0., 1. ]\n"
         "distortion_coefficients: !!opencv-matrix\n   rows: 1\n   cols: 5\n   dt: d\n"
         "   data: [ 0., 0., 0., 0., 0. ]\n";
}

const std::string kSize720p = "image_width: 1280\nimage_height: 720\n";

void expect_refused(const CliRun& r, const std::vector<std::string>& needles) {
  EXPECT_EQ(r.status, 2) << r.out;
  EXPECT_EQ(r.out.find("POSECAL_E_INTERNAL"), std::string::npos) << r.out;
  for (const auto& n : needles)
    EXPECT_NE(r.out.find(n), std::string::npos) << "'" << n << "' in " << r.out;
}

}  // namespace

// A FIFO given as --result blocked for ever before (in open(), even through SIGTERM).
TEST(CliBadInput, FifoAsResultDoesNotBlock) {
  const std::string fifo = (fs::path(testing::TempDir()) / "posecal_cli_bad_fifo.yml").string();
  std::remove(fifo.c_str());
  ASSERT_EQ(mkfifo(fifo.c_str(), 0600), 0);
  const CliRun r = run_cli("evaluate --result " + fifo + " --camera 'sim://?seed=1'", false,
                           "-u DISPLAY timeout -s KILL 30");
  expect_refused(r, {"not a regular file", "POSECAL_E_INVALID_ARGUMENT"});
  std::remove(fifo.c_str());
}

// '[' x 33000 crashed OpenCV 4.6's parser (SIGSEGV), through evaluate and sim://?model=.
TEST(CliBadInput, DeeplyNestedModelFileDoesNotCrash) {
  const std::string deep =
      temp_file("deep.yml", "%YAML:1.0\n---\na: " + std::string(33000, '[') + "\n");
  expect_refused(run_cli("evaluate --result " + deep + " --camera 'sim://?seed=1'"),
                 {"nesting", "64", "POSECAL_E_INVALID_ARGUMENT"});
  expect_refused(run_cli("calibrate --camera 'sim://?model=" + deep + "' --max-keyframes 3"),
                 {"nesting"});
}

// dt u clamped K to 255: eps_gt 428 px, exit 0 before.
TEST(CliBadInput, IntegerMatrixModelIsRefused) {
  const std::string u = temp_file("dtu.yml", model_yaml(kSize720p, "1000.", "u"));
  expect_refused(run_cli("evaluate --result " + u + " --camera 'sim://?seed=1'"),
                 {"dt 'u'", "camera_matrix"});
}

// Models 32768+ px wide or 100000 x 100000: POSECAL_E_INTERNAL before.
TEST(CliBadInput, HugeModelsAreInvalidArguments) {
  for (const std::string size :
       {"image_width: 100000\nimage_height: 100000\n", "image_width: 32768\nimage_height: 720\n",
        "image_width: 20000\nimage_height: 15000\n"}) {
    const std::string m = temp_file("huge.yml", model_yaml(size, "10000."));
    expect_refused(run_cli("evaluate --result " + m + " --camera 'sim://?seed=1&model=" + m + "'"),
                   {"POSECAL_E_INVALID_ARGUMENT", "limit"});
  }
}

// charuco:9x6:1e-300:1e-301 gave POSECAL_E_INTERNAL ("a bug") before.
TEST(CliBadInput, AbsurdBoardSpecsAreInvalidArguments) {
  for (const std::string spec : {"charuco:9x6:1e-300:1e-301:DICT_4X4_50",
                                 "charuco:9x6:0.028:0.0001:DICT_4X4_50", "chessboard:9x6:1e-20"}) {
    expect_refused(run_cli("evaluate --result " + std::string(POSECAL_SOURCE_DIR) +
                           "/data/c525_reference.yml --camera 'sim://?seed=1' --target " + spec),
                   {"POSECAL_E_INVALID_ARGUMENT", spec});
  }
}

// fx = 1e-9 printed "eps_test -1.0000 px over 0 frames" with exit 0 before.
TEST(CliBadInput, ModelThatFitsNoFrameIsAnError) {
  const std::string m = temp_file("fx.yml", model_yaml(kSize720p, "1e-9"));
  const CliRun r = run_cli("evaluate --result " + m + " --camera 'sim://?seed=1'");
  expect_refused(r, {"POSECAL_E_INVALID_ARGUMENT", "cannot project the test set"});
  EXPECT_EQ(r.out.find("-1.0000"), std::string::npos) << r.out;
  const CliRun j = run_cli("evaluate --json --result " + m + " --camera 'sim://?seed=1'", true);
  EXPECT_EQ(j.status, 2) << j.out;
}

// One invalid UTF-8 byte in a controller's reply ended the calibration before (nlohmann's dump
// threw); it is answered with a protocol_error line that is valid JSON, and the run goes on.
TEST(CliBadInput, RobotReplyWithInvalidUtf8IsAProtocolError) {
  const CliRun r = run_cli(
      "calibrate --camera 'sim://?seed=13&operator=robot' --guide stdio --max-keyframes 4", true,
      "-u DISPLAY sh -c '{ printf \"\\377 where\\n\"; yes reached | head -n 2000; } | \"$0\" "
      "\"$@\"'");
  EXPECT_TRUE(r.status == 0 || r.status == 3) << r.out;
  std::istringstream lines(r.out);
  std::string line;
  int errors = 0, targets = 0;
  bool result = false;
  while (std::getline(lines, line)) {
    const auto j = nlohmann::json::parse(line, nullptr, false);
    ASSERT_FALSE(j.is_discarded()) << "not JSON: " << line;
    const std::string event = j.value("event", "");
    if (event == "protocol_error") {
      ++errors;
      EXPECT_EQ(j["line"], "\xEF\xBF\xBD where") << line;  // U+FFFD for the byte
      EXPECT_EQ(targets, 1);
    }
    targets += event == "target";
    result = result || event == "result";
  }
  EXPECT_EQ(errors, 1) << r.out;
  EXPECT_GE(targets, 2) << r.out;
  EXPECT_TRUE(result) << r.out;
}

// A DISPLAY that accepts TCP but is no X server: Qt aborted the run (SIGABRT) before.
TEST(CliBadInput, FakeXServerRunsHeadless) {
  const int listener = socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0);
  ASSERT_GE(listener, 0);
  const int one = 1;
  setsockopt(listener, SOL_SOCKET, SO_REUSEADDR, &one, sizeof one);
  int display = -1;
  for (int n = 47; n < 90 && display < 0; ++n) {
    sockaddr_in a{};
    a.sin_family = AF_INET;
    a.sin_port = htons(static_cast<uint16_t>(6000 + n));
    a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    if (bind(listener, reinterpret_cast<sockaddr*>(&a), sizeof a) == 0) display = n;
  }
  ASSERT_GE(display, 0) << "no free port 6047..6089";
  ASSERT_EQ(listen(listener, 16), 0);
  std::atomic<bool> stop{false};
  std::thread server([&] {  // accepts, writes garbage, closes
    while (!stop) {
      const int c = accept(listener, nullptr, nullptr);
      if (c < 0) break;
      const char garbage[] = "HTTP/1.0 400 Bad Request\r\n\r\nthis is not X11";
      (void)!write(c, garbage, sizeof garbage);
      close(c);
    }
  });
  const CliRun r =
      run_cli("calibrate --camera 'sim://?seed=1' --max-seconds 3 --max-keyframes 3", false,
              "-u POSECAL_WINDOW -u QT_QPA_PLATFORM DISPLAY=127.0.0.1:" + std::to_string(display));
  stop = true;
  shutdown(listener, SHUT_RDWR);
  close(listener);
  server.join();
  EXPECT_NE(r.status, -1) << "killed by a signal:\n" << r.out;
  EXPECT_TRUE(r.status == 0 || r.status == 2 || r.status == 3) << r.out;
  EXPECT_NE(r.out.find("is not a usable X server"), std::string::npos) << r.out;
  EXPECT_NE(r.out.find("headless"), std::string::npos) << r.out;
}
