// Issue 16, bounded input through the command line: a station camera that never shows the board
// ends after board_timeout_s instead of holding the station for --max-seconds, and an images
// folder with a huge image or a FIFO in it is calibrated without decoding or blocking on them.
#include <gtest/gtest.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <zlib.h>

#include <array>
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>
#include <string>

#include "board/board.hpp"
#include "board/views.hpp"
#include "cli_child.hpp"
#include "io/model_file.hpp"
#include "lens/reference_models.hpp"
#include "sim/synthetic.hpp"

namespace fs = std::filesystem;

namespace {

using posecal_test::CliRun;
using posecal_test::run_cli;

fs::path fresh_dir(const std::string& name) {
  const fs::path dir = fs::path(testing::TempDir()) / name;
  fs::remove_all(dir);
  fs::create_directories(dir);
  return dir;
}

void put_be32(std::string* s, uint32_t v) {
  for (int shift : {24, 16, 8, 0}) s->push_back(static_cast<char>((v >> shift) & 0xFF));
}

void put_chunk(std::ofstream& out, const char* type, const std::string& data) {
  std::string c;
  put_be32(&c, static_cast<uint32_t>(data.size()));
  const std::string body = std::string(type, 4) + data;
  const uLong crc =
      crc32(0, reinterpret_cast<const Bytef*>(body.data()), static_cast<uInt>(body.size()));
  c += body;
  put_be32(&c, static_cast<uint32_t>(crc));
  out.write(c.data(), static_cast<std::streamsize>(c.size()));
}

// A valid black 1-bit PNG of `side` x `side` pixels, a few hundred KB for 20000.
void write_black_png(const fs::path& path, int side) {
  std::ofstream out(path, std::ios::binary);
  out.write("\x89PNG\r\n\x1a\n", 8);
  std::string ihdr;
  put_be32(&ihdr, static_cast<uint32_t>(side));
  put_be32(&ihdr, static_cast<uint32_t>(side));
  ihdr += std::string("\x01\x00\x00\x00\x00", 5);
  put_chunk(out, "IHDR", ihdr);
  z_stream z{};
  deflateInit(&z, 9);
  const std::string row(1 + (side + 7) / 8, '\0');
  std::string compressed;
  std::vector<unsigned char> buf(1 << 16);
  for (int r = 0; r <= side; ++r) {
    const bool last = r == side;
    z.next_in = reinterpret_cast<Bytef*>(const_cast<char*>(row.data()));
    z.avail_in = last ? 0 : static_cast<uInt>(row.size());
    do {
      z.next_out = buf.data();
      z.avail_out = static_cast<uInt>(buf.size());
      deflate(&z, last ? Z_FINISH : Z_NO_FLUSH);
      compressed.append(reinterpret_cast<char*>(buf.data()), buf.size() - z.avail_out);
    } while (z.avail_out == 0);
  }
  deflateEnd(&z);
  put_chunk(out, "IDAT", compressed);
  put_chunk(out, "IEND", "");
}

double seconds_since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

}  // namespace

// A 64x48 simulated camera: the board is never detected in it (its squares are a few pixels).
// Before board_timeout_s the station held this camera for --max-seconds.
TEST(CliBounded, AStationCameraThatNeverSeesTheBoardEndsAfterTheBoardTimeout) {
  const fs::path dir = fresh_dir("posecal_cli_bounded_station");
  const std::string model = (dir / "tiny.yml").string();
  posecal::write_camera_model(
      model, posecal::CameraModel::opencv5(64, 48, 60, 60, 31.5, 23.5, {0, 0, 0, 0, 0}));
  const auto t0 = std::chrono::steady_clock::now();
  const CliRun r =
      run_cli("station --cameras 'sim://?model=" + model + "' --out-dir " + (dir / "out").string() +
              " --board-timeout-s 2 --max-seconds 300 --events");
  const double s = seconds_since(t0);
  EXPECT_LT(s, 60.0) << r.out;
  EXPECT_NE(r.status, 0) << r.out;
  // The session's end, with its reason, is in the events...
  EXPECT_NE(r.out.find("no board (charuco:9x6"), std::string::npos) << r.out;
  EXPECT_NE(r.out.find("board_timeout_s = 2"), std::string::npos) << r.out;
  // ... and the summary says the camera failed.
  std::ifstream in(dir / "out" / "summary.json");
  ASSERT_TRUE(in.good()) << r.out;
  const auto sum = nlohmann::json::parse(in);
  ASSERT_EQ(sum["cameras"].size(), 1u);
  const auto& cam = sum["cameras"][0];
  EXPECT_FALSE(cam["converged"].get<bool>());
  EXPECT_TRUE(cam["error"].is_string()) << cam.dump();
  EXPECT_LT(cam["wall_ms"].get<double>(), 60000.0);
  std::printf("station ended after %.1f s: %s\n", s, cam["error"].dump().c_str());
}

// calibrate --images: a 20000x20000 PNG (99.5 s and 2.4 GB to decode before) is rejected from
// its header with the limit named, a FIFO does not block, and the rest calibrates.
TEST(CliBounded, CalibrateImagesRejectsAHugeImageAndSkipsAFifo) {
  const fs::path dir = fresh_dir("posecal_cli_bounded_images");
  const posecal::CameraModel cam = posecal::c525_reference_model();
  const posecal::Board board;
  posecal::SyntheticCamera sc(cam, board);
  int n = 0;
  for (const posecal::Pose& p : posecal::random_board_views(5, 6, cam, board))
    cv::imwrite((dir / ("frame" + std::to_string(n++) + ".png")).string(), sc.render(p));
  write_black_png(dir / "huge.png", 20000);
  ASSERT_EQ(mkfifo((dir / "pipe.png").c_str(), 0600), 0);
  const auto t0 = std::chrono::steady_clock::now();
  const CliRun r = run_cli("calibrate --images " + dir.string() + " --out " +
                               (dir.parent_path() / "posecal_cli_bounded.yml").string() + " --json",
                           true);
  EXPECT_LT(seconds_since(t0), 60.0);
  ASSERT_EQ(r.status, 0) << r.out;
  const auto j = nlohmann::json::parse(r.out);
  bool huge = false;
  for (const auto& rej : j["rejected"]) {
    if (rej["file"] != "huge.png") continue;
    huge = true;
    const std::string why = rej["reason"];
    EXPECT_NE(why.find("20000x20000"), std::string::npos) << why;
    EXPECT_NE(why.find("limit of 50.0 MP"), std::string::npos) << why;
  }
  EXPECT_TRUE(huge) << r.out;
  EXPECT_GE(j["frames_used"].get<int>(), 5) << r.out;
}

// Text-mode station was silent until the end (half a minute and more). Now each camera's steps
// are lines as they happen, and a camera that sees nothing still says where it is every 10 s.
TEST(CliBounded, TextModeStationShowsProgressAndAHeartbeat) {
  const fs::path dir = fresh_dir("posecal_cli_station_text");
  CliRun r = run_cli("station --cameras 'sim://?seed=3' --out-dir " + (dir / "a").string(), true);
  ASSERT_EQ(r.status, 0) << r.out;
  for (const char* line : {"sim://?seed=3: calibrating camera 'sim-3'",
                           "sim://?seed=3: keyframe 1 captured", "sim://?seed=3: keyframe 2 captured",
                           "-> refining", "-> converged", " converged ("})
    EXPECT_NE(r.out.find(line), std::string::npos) << line << "\n" << r.out;

  const std::string model = (dir / "tiny.yml").string();
  posecal::write_camera_model(
      model, posecal::CameraModel::opencv5(64, 48, 60, 60, 31.5, 23.5, {0, 0, 0, 0, 0}));
  r = run_cli("station --cameras 'sim://?model=" + model + "' --out-dir " + (dir / "b").string() +
                  " --board-timeout-s 12 --max-seconds 300",
              true);
  EXPECT_NE(r.status, 0) << r.out;
  EXPECT_NE(r.out.find("10 s: "), std::string::npos) << r.out;
  EXPECT_NE(r.out.find(" frames, 0 keyframes, waiting_for_board"), std::string::npos) << r.out;
}
