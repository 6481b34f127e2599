// The posecal command line, end to end (it is built on the C ABI only).
#include <gtest/gtest.h>

#include <array>
#include <cstdio>
#include <filesystem>
#include <nlohmann/json.hpp>
#include <opencv2/calib3d.hpp>
#include <opencv2/imgcodecs.hpp>

#include "posecal/target.hpp"

namespace fs = std::filesystem;

namespace {

struct CliRun {
  int status = -1;
  std::string out;
};

CliRun run(const std::string& args) {
  CliRun r;
  const std::string cmd = std::string(POSECAL_CLI) + " " + args + " 2>&1";
  FILE* p = popen(cmd.c_str(), "r");
  if (!p) return r;
  std::array<char, 4096> buf;
  size_t n;
  while ((n = fread(buf.data(), 1, buf.size(), p)) > 0) r.out.append(buf.data(), n);
  const int rc = pclose(p);
  r.status = WIFEXITED(rc) ? WEXITSTATUS(rc) : -1;
  return r;
}

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
  const CliRun r = run("calibrate --images " + dir.string() +
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
  const posecal::Target target(posecal::TargetSpec::parse("chessboard:9x6:0.025"));
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

TEST(Cli, BadInputGivesMessageAndNonZeroExit) {
  CliRun r = run("calibrate --images /nonexistent/dir");
  EXPECT_EQ(r.status, 2);
  EXPECT_NE(r.out.find("does not exist"), std::string::npos) << r.out;
  r = run("calibrate --images /tmp --target charuco:9x6");
  EXPECT_EQ(r.status, 2);
  EXPECT_NE(r.out.find("target spec"), std::string::npos) << r.out;
  r = run("calibrate");
  EXPECT_EQ(r.status, 1);
  r = run("calibrate --images");
  EXPECT_EQ(r.status, 1);
  r = run("frobnicate");
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
  r = run("calibrate --images " + dir.string());
  EXPECT_EQ(r.status, 2);
  EXPECT_NE(r.out.find("no image"), std::string::npos) << r.out;
  // Images without enough views: a blank image set.
  for (int i = 0; i < 3; ++i)
    cv::imwrite((dir / ("blank" + std::to_string(i) + ".png")).string(),
                cv::Mat(480, 640, CV_8U, cv::Scalar(128)));
  r = run("calibrate --images " + dir.string() + " --json");
  EXPECT_EQ(r.status, 2) << r.out;
}

TEST(Cli, WritesPrintableBoard) {
  const std::string png = testing::TempDir() + "/cli_board.png";
  CliRun r = run("board --out " + png + " --dpi 200");
  ASSERT_EQ(r.status, 0) << r.out;
  const cv::Mat img = cv::imread(png, cv::IMREAD_GRAYSCALE);
  ASSERT_FALSE(img.empty());
  EXPECT_EQ(posecal::Target().detect(img).size(), 40u);
  r = run("board --out " + testing::TempDir() + "/cli_board.pdf --target chessboard:9x6:0.025");
  EXPECT_EQ(r.status, 0) << r.out;
  r = run("board --out /nonexistent/dir/board.pdf");
  EXPECT_EQ(r.status, 2) << r.out;
}
