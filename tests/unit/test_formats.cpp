// Camera-model file formats (core/io/model_file.hpp, docs/formats.md): every format written and
// read back to the same projection, the hand-written sample of each format's own tools reads,
// and bad input is refused with Error(kInvalidArgument) naming the file and the key, nothing
// written on a write error.
#include <gtest/gtest.h>

#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <opencv2/core/persistence.hpp>
#include <sstream>

#include "common/error.hpp"
#include "io/model_file.hpp"
#include "lens/camera_model.hpp"
#include "test_time.hpp"

using namespace posecal;

namespace {

const std::string kSamples = std::string(POSECAL_SOURCE_DIR) + "/tests/data/formats/";

std::string temp_path(const std::string& name) {
  return (std::filesystem::path(testing::TempDir()) / ("posecal_formats_" + name)).string();
}

std::string write_text(const std::string& name, const std::string& text) {
  const std::string path = temp_path(name);
  std::ofstream(path, std::ios::binary) << text;
  return path;
}

std::string read_text(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  return std::string((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
}

std::string replaced(std::string s, const std::string& from, const std::string& to) {
  const size_t at = s.find(from);
  EXPECT_NE(at, std::string::npos) << from;
  if (at != std::string::npos) s.replace(at, from.size(), to);
  return s;
}

// A strongly distorted model (the corners move by tens of pixels), with and without k3.
CameraModel model_with_k3() {
  return CameraModel::opencv5(1280, 720, 1000.123456789, 1010.987654321, 650.5, 350.25,
                              {-0.25, 0.12, 0.001, -0.002, -0.02});
}
// The richer OpenCV models: rational, thin prism, tilted sensor (OpenCV's order).
CameraModel model_of(LensModel lens) {
  const std::vector<double> all{0.8,  -0.1,  0.001,  -0.002, 0.02,   1.1,   0.05,
                                0.01, 0.002, -0.001, 0.0015, 0.0005, 0.009, -0.007};
  std::vector<double> p{1000.5, 1010.25, 650.5, 350.25};
  p.insert(p.end(), all.begin(), all.begin() + num_distortion_params(lens));
  return CameraModel(1280, 720, lens, p);
}
// A 185-degree fisheye on a 1280x1024 sensor (cv::fisheye's k1..k4).
CameraModel fisheye_model() {
  return CameraModel(1280, 1024, LensModel::kFisheye,
                     {317.25, 318.5, 640.25, 511.75, 0.012, -0.0021, 0.00031, -0.00002});
}
CameraModel model_without_k3() {
  return CameraModel::opencv5(752, 480, 458.123, 457.456, 367.891, 248.345,
                              {-0.2841, 0.0822, 0.00031, -0.00012, 0});
}

// The largest projection difference of the two models over rays through a 33 x 25 pixel grid
// that covers the whole image of `a`, edge to edge (beyond 90 degrees for a fisheye).
double max_projection_difference(const CameraModel& a, const CameraModel& b) {
  double worst = 0;
  for (int j = 0; j <= 24; ++j) {
    for (int i = 0; i <= 32; ++i) {
      const Eigen::Vector2d px((a.width() - 1) * i / 32.0, (a.height() - 1) * j / 24.0);
      Eigen::Vector3d ray;
      EXPECT_TRUE(a.unproject_ray(px, &ray)) << px.transpose();
      Eigen::Vector2d ua, ub;
      EXPECT_TRUE(a.project(ray, &ua));
      EXPECT_TRUE(b.project(ray, &ub));
      worst = std::max(worst, (ua - ub).norm());
    }
  }
  return worst;
}

// `call` throws Error(kInvalidArgument) whose message contains every needle.
template <class Call>
void expect_invalid(Call&& call, const std::vector<std::string>& needles,
                    const std::string& context = "") {
  try {
    call();
    ADD_FAILURE() << "no error: " << context;
  } catch (const Error& e) {
    EXPECT_EQ(e.code(), ErrorCode::kInvalidArgument) << e.what();
    for (const auto& n : needles) {
      EXPECT_NE(std::string(e.what()).find(n), std::string::npos)
          << "'" << n << "' not in: " << e.what() << " " << context;
    }
  }
}

void expect_refused(const std::string& path, const std::vector<std::string>& needles) {
  std::vector<std::string> all = needles;
  all.push_back(path);
  expect_invalid([&] { read_camera_model(path); }, all, path);
}

// Every prefix of `text` cut at a line's end (and in the middle of the last line) is refused.
void expect_truncations_refused(const std::string& name, const std::string& text) {
  for (size_t n = 0; n + 1 < text.size(); ++n) {
    if (text[n] != '\n' && n % 7 != 0) continue;
    const std::string path = write_text(name, text.substr(0, n));
    try {
      read_camera_model(path);
      ADD_FAILURE() << name << ": accepted the first " << n << " bytes:\n" << text.substr(0, n);
      return;
    } catch (const Error& e) {
      ASSERT_EQ(e.code(), ErrorCode::kInvalidArgument) << n << ": " << e.what();
    }
  }
}

}  // namespace

TEST(Formats, NamesAndExtensions) {
  for (const ModelFormat f : model_formats()) {
    EXPECT_EQ(model_format_from_name(model_format_name(f)), f);
  }
  EXPECT_FALSE(model_format_from_name("halcon7").has_value());
  EXPECT_FALSE(model_format_from_name("OpenCV").has_value());
  EXPECT_EQ(model_format_from_path("a/b.cameramodel"), ModelFormat::kMrcal);
  for (const char* p : {"x.yml", "x.yaml", "x.json", "x.xml"}) {
    EXPECT_EQ(model_format_from_path(p), ModelFormat::kOpenCV) << p;
  }
  EXPECT_FALSE(model_format_from_path("x.txt").has_value());
  EXPECT_FALSE(model_format_from_path(".yml").has_value());
}

// write -> read back -> the same format, size and parameters, projections equal to 1e-9 px.
TEST(Formats, EveryFormatRoundTrips) {
  struct Case {
    ModelFormat format;
    std::string file;
    CameraModel model;
  };
  const std::vector<Case> cases = {
      {ModelFormat::kOpenCV, "rt.yml", model_with_k3()},
      {ModelFormat::kOpenCV, "rt.json", model_with_k3()},
      {ModelFormat::kOpenCV, "rt.xml", model_with_k3()},
      {ModelFormat::kRos, "rt_ros.yaml", model_with_k3()},
      {ModelFormat::kMrcal, "rt.cameramodel", model_with_k3()},
      {ModelFormat::kKalibr, "rt_kalibr.yaml", model_without_k3()},
      {ModelFormat::kOpenCV, "rt8.yml", model_of(LensModel::kOpenCV8)},
      {ModelFormat::kOpenCV, "rt12.json", model_of(LensModel::kOpenCV12)},
      {ModelFormat::kOpenCV, "rt14.xml", model_of(LensModel::kOpenCV14)},
      {ModelFormat::kRos, "rt8_ros.yaml", model_of(LensModel::kOpenCV8)},
      {ModelFormat::kMrcal, "rt8.cameramodel", model_of(LensModel::kOpenCV8)},
      {ModelFormat::kMrcal, "rt12.cameramodel", model_of(LensModel::kOpenCV12)},
      {ModelFormat::kOpenCV, "rt_fisheye.yml", fisheye_model()},
      {ModelFormat::kOpenCV, "rt_fisheye.json", fisheye_model()},
      {ModelFormat::kOpenCV, "rt_fisheye.xml", fisheye_model()},
      {ModelFormat::kRos, "rt_fisheye_ros.yaml", fisheye_model()},
      {ModelFormat::kKalibr, "rt_fisheye_kalibr.yaml", fisheye_model()},
  };
  for (const Case& c : cases) {
    SCOPED_TRACE(c.file);
    const std::string path = temp_path(c.file);
    write_camera_model(path, c.model, {}, c.format);
    const ModelFile r = read_model_file(path);
    EXPECT_EQ(r.format, c.format);
    EXPECT_EQ(r.model.width(), c.model.width());
    EXPECT_EQ(r.model.height(), c.model.height());
    EXPECT_EQ(r.model.lens_model(), c.model.lens_model());
    EXPECT_EQ(r.model.params(), c.model.params());
    EXPECT_LT(max_projection_difference(c.model, r.model), 1e-9);
    std::filesystem::remove(path);
  }
  // Formats without a name for a model refuse it and write nothing.
  for (const auto& [format, lens] : std::vector<std::pair<ModelFormat, LensModel>>{
           {ModelFormat::kRos, LensModel::kOpenCV12},
           {ModelFormat::kRos, LensModel::kOpenCV14},
           {ModelFormat::kMrcal, LensModel::kOpenCV14},
           {ModelFormat::kKalibr, LensModel::kOpenCV8},
           {ModelFormat::kHalcon, LensModel::kOpenCV8},
           {ModelFormat::kMrcal, LensModel::kFisheye},
           {ModelFormat::kHalcon, LensModel::kFisheye}}) {
    const std::string path = temp_path("refused.txt");
    std::filesystem::remove(path);
    const CameraModel model = lens == LensModel::kFisheye ? fisheye_model() : model_of(lens);
    expect_invalid([&] { write_camera_model(path, model, {}, format); },
                   {model_format_name(format), lens_model_name(lens), "nothing written"},
                   lens_model_name(lens));
    EXPECT_FALSE(std::filesystem::exists(path));
  }
  // By extension alone: .cameramodel is mrcal, .xml OpenCV.
  write_camera_model(temp_path("ext.cameramodel"), model_with_k3());
  EXPECT_EQ(read_model_file(temp_path("ext.cameramodel")).format, ModelFormat::kMrcal);
  write_camera_model(temp_path("ext.xml"), model_with_k3());
  EXPECT_EQ(read_text(temp_path("ext.xml")).substr(0, 5), "<?xml");
  // The reader decides by content where the name does not: a ROS file and an mrcal file as .txt.
  write_camera_model(temp_path("ros.txt"), model_with_k3(), {}, ModelFormat::kRos);
  EXPECT_EQ(read_model_file(temp_path("ros.txt")).format, ModelFormat::kRos);
  write_camera_model(temp_path("kalibr.txt"), model_without_k3(), {}, ModelFormat::kKalibr);
  EXPECT_EQ(read_model_file(temp_path("kalibr.txt")).format, ModelFormat::kKalibr);
  std::filesystem::copy_file(temp_path("ext.cameramodel"), temp_path("mrcal.txt"),
                             std::filesystem::copy_options::overwrite_existing);
  EXPECT_EQ(read_model_file(temp_path("mrcal.txt")).format, ModelFormat::kMrcal);
}

// ---- OpenCV ---------------------------------------------------------------------------------

// Booleans as the integers 0/1 (cv2.FileStorage reads numbers; "false" as a string is truthy in
// Python), the covariance and the expected error stored, and read back.
TEST(Formats, OpenCVStoresBooleansCovarianceAndExpectedError) {
  const CameraModel m = model_with_k3();
  const int n = m.num_params();
  CalibrationFileExtras extras;
  extras.nr_of_frames = 12;
  extras.avg_reprojection_error = 0.21;
  extras.param_std = std::vector<double>(n, 0.5);
  for (int a = 0; a < n; ++a) {
    for (int b = 0; b < n; ++b) extras.covariance.push_back(a == b ? 0.25 : 0.01 * (a + b));
  }
  extras.expected_error_px = 0.137;
  extras.converged = true;
  extras.interrupted = false;
  extras.strings = {{"camera_id", "cam-1"}, {"target", "charuco:9x6:0.028:0.0182:DICT_4X4_50"}};
  for (const std::string ext : {".yml", ".json", ".xml"}) {
    SCOPED_TRACE(ext);
    const std::string path = temp_path("extras" + ext);
    write_camera_model(path, m, extras);
    cv::FileStorage fs(path, cv::FileStorage::READ);
    ASSERT_TRUE(fs.isOpened());
    EXPECT_TRUE(fs["converged"].isInt());
    EXPECT_EQ(static_cast<int>(fs["converged"]), 1);
    EXPECT_EQ(static_cast<int>(fs["interrupted"]), 0);
    EXPECT_DOUBLE_EQ(static_cast<double>(fs["expected_error_px"]), 0.137);
    cv::Mat cov;
    fs["intrinsics_covariance"] >> cov;
    ASSERT_EQ(cov.rows, n);
    ASSERT_EQ(cov.cols, n);
    EXPECT_DOUBLE_EQ(cov.at<double>(2, 5), 0.07);
    const ModelFile r = read_model_file(path);
    EXPECT_EQ(r.extras.covariance, extras.covariance);
    EXPECT_EQ(r.extras.param_std, extras.param_std);
    EXPECT_EQ(r.extras.converged, std::optional<bool>(true));
    EXPECT_EQ(r.extras.interrupted, std::optional<bool>(false));
    EXPECT_DOUBLE_EQ(r.extras.expected_error_px, 0.137);
    EXPECT_EQ(r.extras.nr_of_frames, 12);
    EXPECT_EQ(r.model.params(), m.params());
  }
  // Files written before: converged and interrupted as the strings "true" / "false".
  const std::string old =
      replaced(replaced(read_text(temp_path("extras.yml")), "converged: 1", "converged: \"false\""),
               "interrupted: 0", "interrupted: \"true\"");
  const ModelFile r = read_model_file(write_text("old.yml", old));
  EXPECT_EQ(r.extras.converged, std::optional<bool>(false));
  EXPECT_EQ(r.extras.interrupted, std::optional<bool>(true));
  expect_refused(write_text("bad_flag.yml", replaced(old, "\"false\"", "\"yes\"")),
                 {"'converged'"});
  expect_refused(write_text("bad_flag2.yml", replaced(old, "\"false\"", "2")), {"'converged'"});
  const std::string text = read_text(temp_path("extras.yml"));
  expect_refused(
      write_text("bad_cov.yml", replaced(text, "rows: 9\n   cols: 9", "rows: 3\n   cols: 27")),
      {"'intrinsics_covariance'"});
}

// The coefficients held and their covariance (CalibrationResult::held, held_covariance): written
// with the result, read back, and refused naming the key when they do not fit the model.
TEST(Formats, OpenCVStoresHeldCoefficients) {
  const CameraModel m = model_of(LensModel::kOpenCV8);
  const int n = m.num_params();
  CalibrationFileExtras extras;
  for (int a = 0; a < n; ++a) {
    for (int b = 0; b < n; ++b) {
      extras.covariance.push_back(a == b && a < n - 2 ? 0.25 : 0.0);
      extras.held_covariance.push_back(a == b ? 0.5 : 0.001 * (a + b));
    }
  }
  extras.held = {"k6", "k5"};
  for (const std::string ext : {".yml", ".json", ".xml"}) {
    SCOPED_TRACE(ext);
    const std::string path = temp_path("held" + ext);
    write_camera_model(path, m, extras);
    const ModelFile r = read_model_file(path);
    EXPECT_EQ(r.extras.held, extras.held);
    EXPECT_EQ(r.extras.held_covariance, extras.held_covariance);
    EXPECT_EQ(r.extras.covariance, extras.covariance);
  }
  const std::string text = read_text(temp_path("held.yml"));
  ASSERT_NE(text.find("held_intrinsics: k6 k5"), std::string::npos) << text;
  expect_refused(write_text("held_unknown.yml",
                            replaced(text, "held_intrinsics: k6 k5", "held_intrinsics: k6 s1")),
                 {"'held_intrinsics'", "'s1'", "opencv8"});
  expect_refused(write_text("held_twice.yml",
                            replaced(text, "held_intrinsics: k6 k5", "held_intrinsics: k6 k6")),
                 {"'held_intrinsics'", "twice"});
  expect_refused(write_text("held_empty.yml",
                            replaced(text, "held_intrinsics: k6 k5", "held_intrinsics: \" \"")),
                 {"'held_intrinsics' is empty"});
  const size_t cov_at = text.find("held_intrinsics_covariance:");
  const size_t cov_end = text.find("posecal_file_end");
  ASSERT_NE(cov_at, std::string::npos);
  expect_refused(write_text("held_no_cov.yml", text.substr(0, cov_at) + text.substr(cov_end)),
                 {"'held_intrinsics' without 'held_intrinsics_covariance'"});
  const size_t names_at = text.find("held_intrinsics:");
  expect_refused(write_text("held_no_names.yml", text.substr(0, names_at) + text.substr(cov_at)),
                 {"'held_intrinsics_covariance' without 'held_intrinsics'"});
  const std::string rows = "rows: " + std::to_string(n) + "\n   cols: " + std::to_string(n);
  const std::string wrong = "rows: 2\n   cols: " + std::to_string(n * n / 2);
  expect_refused(write_text("held_bad_cov.yml",
                            text.substr(0, cov_at) + replaced(text.substr(cov_at), rows, wrong)),
                 {"'held_intrinsics_covariance'"});
}

TEST(Formats, OpenCVXmlIsReadAsStrictlyAsYaml) {
  const std::string path = temp_path("strict.xml");
  write_camera_model(path, model_with_k3());
  const std::string text = read_text(path);
  EXPECT_EQ(read_camera_model(path).params(), model_with_k3().params());
  const std::string head = "<?xml version=\"1.0\"?>\n";
  const std::string body = text.substr(head.size());
  expect_refused(write_text("doctype.xml", head + "<!DOCTYPE x [<!ENTITY a \"aaaa\">]>\n" + body),
                 {"DOCTYPE"});
  expect_refused(write_text("entity.xml", replaced(text, "<dt>d</dt>", "<dt>&a;</dt>")),
                 {"entity"});
  expect_refused(write_text("cdata.xml", replaced(text, "<dt>d</dt>", "<dt><![CDATA[d]]></dt>")),
                 {"CDATA"});
  std::string deep = head + "<opencv_storage>\n";
  for (int i = 0; i < 200; ++i) deep += "<a>";
  expect_refused(write_text("deep.xml", deep), {"deeper than the limit of 64"});
  expect_refused(
      write_text("unknown.xml", replaced(text, "<image_width>", "<foo>1</foo><image_width>")),
      {"unknown key 'foo'"});
  expect_refused(
      write_text("pi.xml", replaced(text, "<opencv_storage>", "<?php x ?><opencv_storage>")),
      {"processing instruction"});
  expect_truncations_refused("cut.xml", text);
}

// ---- ROS camera_info ------------------------------------------------------------------------

// sensor_msgs/CameraInfo: width, height, distortion_model, D, K (3x3), R (3x3), P (3x4); the
// camera_info YAML adds camera_name and stores each matrix as {rows, cols, data}.
TEST(Formats, RosFileHasThePublishedFields) {
  const std::string path = temp_path("fields_ros.yaml");
  CalibrationFileExtras extras;
  extras.strings = {{"camera_id", "sim-3 left"}};
  write_camera_model(path, model_with_k3(), extras, ModelFormat::kRos);
  const std::string text = read_text(path);
  std::vector<std::string> keys;
  std::istringstream lines(text);
  for (std::string line; std::getline(lines, line);) {
    if (!line.empty() && line[0] != ' ') keys.push_back(line.substr(0, line.find(':')));
  }
  EXPECT_EQ(keys,
            (std::vector<std::string>{"image_width", "image_height", "camera_name", "camera_matrix",
                                      "distortion_model", "distortion_coefficients",
                                      "rectification_matrix", "projection_matrix"}));
  EXPECT_NE(text.find("camera_name: sim_3_left\n"), std::string::npos) << text;
  EXPECT_NE(text.find("distortion_model: plumb_bob\n"), std::string::npos);
  EXPECT_NE(text.find("rectification_matrix:\n  rows: 3\n  cols: 3\n  data: [1, 0, 0, 0, 1, 0, "
                      "0, 0, 1]\n"),
            std::string::npos)
      << text;
  EXPECT_NE(text.find("projection_matrix:\n  rows: 3\n  cols: 4\n  data: [1000.123456789, 0, "
                      "650.5, 0, 0, 1010.987654321, 350.25, 0, 0, 0, 1, 0]\n"),
            std::string::npos)
      << text;
}

TEST(Formats, RosSampleReads) {
  const ModelFile f = read_model_file(kSamples + "ros_camera_info.yaml");
  EXPECT_EQ(f.format, ModelFormat::kRos);
  EXPECT_EQ(f.model.width(), 1920);
  EXPECT_EQ(f.model.height(), 1080);
  EXPECT_EQ(f.model.params(), (std::vector<double>{1402.512, 1398.774, 955.331, 541.208, -0.3182,
                                                   0.1417, 0.00082, -0.00031, -0.0319}));
}

TEST(Formats, RosBadInput) {
  const std::string good = read_text(kSamples + "ros_camera_info.yaml");
  expect_truncations_refused("cut_ros.yaml", good);
  expect_refused(
      write_text("type_ros.yaml", replaced(good, "image_width: 1920", "image_width: wide")),
      {"'image_width'", "not a number"});
  expect_refused(
      write_text("float_ros.yaml", replaced(good, "image_width: 1920", "image_width: 19.5")),
      {"'image_width'", "integer"});
  expect_refused(write_text("quoted_ros.yaml", replaced(good, "rows: 1", "rows: \"1\"")),
                 {"'distortion_coefficients.rows'"});
  expect_refused(
      write_text("missing_ros.yaml", replaced(good, "camera_matrix:", "camera_matrixx:")),
      {"unknown key 'camera_matrixx'"});
  std::string no_k = good;
  no_k.erase(no_k.find("camera_matrix:"),
             no_k.find("distortion_model:") - no_k.find("camera_matrix:"));
  expect_refused(write_text("nok_ros.yaml", no_k), {"no field 'camera_matrix'"});
  // equidistant is the fisheye, with 4 coefficients.
  expect_refused(write_text("equi_ros.yaml", replaced(good, "plumb_bob", "equidistant")),
                 {"'distortion_coefficients' has 5 values; equidistant has 4"});
  expect_refused(write_text("fov_ros.yaml", replaced(good, "plumb_bob", "fov")),
                 {"'distortion_model' 'fov'"});
  expect_refused(write_text("count_ros.yaml", replaced(good, "-0.031900]", "-0.031900, 0.1]")),
                 {"'distortion_coefficients.data'", "6 values"});
  expect_refused(
      write_text("shape_ros.yaml", replaced(good, "  rows: 3\n  cols: 4", "  rows: 3\n  cols: 3")),
      {"'projection_matrix'"});
  expect_refused(write_text("skew_ros.yaml",
                            replaced(good, "1402.51200,    0.     ", "1402.51200,    1.     ")),
                 {"'camera_matrix'"});
  expect_refused(write_text("dup_ros.yaml", good + "image_width: 10\n"),
                 {"'image_width' appears twice"});
  expect_refused(write_text("tab_ros.yaml", replaced(good, "image_width: ", "image_width:\t")),
                 {"tab"});
  expect_refused(write_text("anchor_ros.yaml",
                            replaced(good, "camera_name: bench_cam_left", "camera_name: &a x")),
                 {"anchors"});
  expect_refused(write_text("docs_ros.yaml", good + "---\n" + good), {"more than one document"});
  // rational_polynomial is opencv8; with 5 coefficients it is refused naming the count.
  const ModelFile rational = read_model_file(
      write_text("rational_ros.yaml",
                 replaced(replaced(good, "plumb_bob", "rational_polynomial"),
                          "cols: 5\n  data: [-0.318200, 0.141700, 0.000820, -0.000310, -0.031900]",
                          "cols: 8\n  data: [-0.3, 0.1, 0, 0, -0.03, 0.2, 0, 0]")));
  EXPECT_EQ(rational.model.lens_model(), LensModel::kOpenCV8);
  EXPECT_EQ(rational.model.params()[9], 0.2);
  expect_refused(
      write_text("rational5_ros.yaml", replaced(good, "plumb_bob", "rational_polynomial")),
      {"'distortion_coefficients' has 5 values; rational_polynomial has 8"});
  std::string deep = "image_width: ";
  for (int i = 0; i < 100; ++i) deep += "[";
  expect_refused(write_text("deep_ros.yaml", deep + "\n"), {"deeper than the limit of 64"});
  std::string nested = "image_width:\n";
  for (int i = 1; i < 100; ++i) nested += std::string(static_cast<size_t>(i), ' ') + "a:\n";
  expect_refused(write_text("nested_ros.yaml", nested), {"deeper than the limit of 64"});
  std::string big = good;
  while (big.size() <= kMaxModelFileBytes) big += "# padding padding padding padding padding\n";
  expect_refused(write_text("big_ros.yaml", big), {"bytes; the limit is 1048576 bytes"});
}

// ---- mrcal ----------------------------------------------------------------------------------

TEST(Formats, MrcalSampleReads) {
  const ModelFile f = read_model_file(kSamples + "mrcal_opencv5.cameramodel");
  EXPECT_EQ(f.format, ModelFormat::kMrcal);
  EXPECT_EQ(f.model.width(), 4032);
  EXPECT_EQ(f.model.height(), 3024);
  EXPECT_EQ(f.model.params(), (std::vector<double>{2712.5, 2709.25, 2015.75, 1511.125, -0.0912,
                                                   0.0731, 0.00042, -0.00018, -0.0123}));
  // mrcal's other OpenCV models read when they hold no more than opencv5.
  const std::string text = read_text(kSamples + "mrcal_opencv5.cameramodel");
  const ModelFile four = read_model_file(write_text(
      "four.cameramodel", replaced(replaced(text, "OPENCV5", "OPENCV4"), " -0.0123,", "")));
  EXPECT_EQ(four.model.params()[8], 0.0);
  const ModelFile pinhole = read_model_file(write_text(
      "pinhole.cameramodel", replaced(replaced(text, "OPENCV5", "PINHOLE"),
                                      " -0.0912, 0.0731, 0.00042, -0.00018, -0.0123,", "")));
  EXPECT_EQ(pinhole.model.params()[4], 0.0);
  // OPENCV8 is opencv8, its k4 where OpenCV has it.
  const ModelFile eight =
      read_model_file(write_text("eight.cameramodel", replaced(replaced(text, "OPENCV5", "OPENCV8"),
                                                               "-0.0123,", "-0.0123, 0.5, 0, 0,")));
  EXPECT_EQ(eight.model.lens_model(), LensModel::kOpenCV8);
  EXPECT_EQ(eight.model.params()[9], 0.5);
}

TEST(Formats, MrcalBadInput) {
  const std::string good = read_text(kSamples + "mrcal_opencv5.cameramodel");
  expect_truncations_refused("cut.cameramodel", good);
  expect_refused(
      write_text("cahvor.cameramodel", replaced(good, "LENSMODEL_OPENCV5", "LENSMODEL_CAHVOR")),
      {"'lensmodel' 'LENSMODEL_CAHVOR'"});
  expect_refused(write_text("opencv8.cameramodel", replaced(good, "OPENCV5", "OPENCV8")),
                 {"'intrinsics'", "has 9 values; expected 12"});
  expect_refused(write_text("count.cameramodel", replaced(good, " -0.0123,", "")),
                 {"'intrinsics'", "8 values"});
  expect_refused(write_text("type.cameramodel", replaced(good, "2712.5", "'2712.5'")),
                 {"'intrinsics'", "not a number"});
  expect_refused(write_text("size.cameramodel", replaced(good, "4032", "4032.5")),
                 {"'imagersize'"});
  expect_refused(
      write_text("nosize.cameramodel", replaced(good, "'imagersize': [ 4032, 3024,],", "")),
      {"no field 'imagersize'"});
  expect_refused(write_text("unknown.cameramodel", replaced(good, "'icam_intrinsics'", "'icam'")),
                 {"unknown key 'icam'"});
  expect_refused(write_text("dup.cameramodel",
                            replaced(good, "'icam_intrinsics': 0,", "'imagersize': [1, 1],")),
                 {"'imagersize' appears twice"});
  expect_refused(write_text("ext.cameramodel", replaced(good, "0.5, -0.1, 0.02,", "0.5, -0.1,")),
                 {"'extrinsics'"});
  std::string deep = "{'lensmodel': ";
  for (int i = 0; i < 100; ++i) deep += "[";
  expect_refused(write_text("deep.cameramodel", deep), {"deeper than the limit of 64"});
  expect_refused(write_text("after.cameramodel", good + "{}\n"), {"text after"});
  expect_refused(write_text("notdict.cameramodel", "[1, 2]\n"), {"not a Python dict"});
}

// ---- Kalibr ---------------------------------------------------------------------------------

TEST(Formats, KalibrSampleReadsCam0) {
  const ModelFile f = read_model_file(kSamples + "kalibr_camchain.yaml");
  EXPECT_EQ(f.format, ModelFormat::kKalibr);
  EXPECT_EQ(f.model.width(), 752);
  EXPECT_EQ(f.model.params(), (std::vector<double>{458.123, 457.456, 367.891, 248.345, -0.2841,
                                                   0.0822, 0.00031, -0.00012, 0}));
  const std::string path = temp_path("fields_kalibr.yaml");
  write_camera_model(path, model_without_k3(), {}, ModelFormat::kKalibr);
  EXPECT_EQ(
      read_text(path),
      "cam0:\n  camera_model: pinhole\n  intrinsics: [458.123, 457.456, 367.891, 248.345]\n"
      "  distortion_model: radtan\n  distortion_coeffs: [-0.2841, 0.0822, 0.00031, -0.00012]\n"
      "  resolution: [752, 480]\n");
}

// A model with k3 != 0 cannot be radtan: refused naming the format and the model, nothing
// written (a file already there is kept).
TEST(Formats, KalibrRefusesK3AndWritesNothing) {
  const std::string path = temp_path("k3_kalibr.yaml");
  std::filesystem::remove(path);
  expect_invalid([&] { write_camera_model(path, model_with_k3(), {}, ModelFormat::kKalibr); },
                 {"kalibr", "opencv5", "k3", path, "nothing written"});
  EXPECT_FALSE(std::filesystem::exists(path));
  write_text("k3_kalibr.yaml", "previous\n");
  expect_invalid([&] { write_camera_model(path, model_with_k3(), {}, ModelFormat::kKalibr); },
                 {"kalibr"});
  EXPECT_EQ(read_text(path), "previous\n");
}

TEST(Formats, KalibrBadInput) {
  const std::string good = read_text(kSamples + "kalibr_camchain.yaml");
  const std::string cam0 = good.substr(0, good.find("cam1:"));
  expect_truncations_refused("cut_kalibr.yaml",
                             replaced(cam0, "  rostopic: /cam0/image_raw\n", ""));
  expect_refused(write_text("fov_kalibr.yaml", replaced(good, "radtan", "fov")),
                 {"'cam0.distortion_model' 'fov'"});
  expect_refused(
      write_text("omni_kalibr.yaml", replaced(good, "camera_model: pinhole", "camera_model: omni")),
      {"'cam0.camera_model' 'omni'"});
  expect_refused(
      write_text("res_kalibr.yaml", replaced(good, "resolution: [752, 480]", "resolution: 752")),
      {"'cam0.resolution'"});
  expect_refused(
      write_text("noin_kalibr.yaml",
                 replaced(good, "  intrinsics: [458.123, 457.456, 367.891, 248.345]\n", "")),
      {"no field 'cam0.intrinsics'"});
  expect_refused(write_text("key_kalibr.yaml", replaced(good, "rostopic: /cam0", "topic: /cam0")),
                 {"unknown key 'cam0.topic'"});
  expect_refused(write_text("top_kalibr.yaml", good + "imu0:\n  a: 1\n"), {"unknown key 'imu0'"});
  expect_refused(write_text("coeffs_kalibr.yaml", replaced(good, "-0.00012]", "-0.00012, 0.1]")),
                 {"'cam0.distortion_coeffs'", "5 values"});
}

// ---- HALCON ---------------------------------------------------------------------------------

// HALCON's polynomial undistorts (distorted -> undistorted, metres on the sensor): the
// conversion is a fit each way, within 0.1 px over the whole image (halcon_campar.cpp).
TEST(Formats, HalconRoundTripIsAFitWithinItsLimit) {
  const CameraModel mild = CameraModel::opencv5(1920, 1080, 1400, 1390, 950.5, 545.25,
                                                {-0.05, 0.01, 0.0005, -0.0003, 0});
  const std::string path = temp_path("mild.dat");
  write_camera_model(path, mild, {}, ModelFormat::kHalcon);
  const std::string text = read_text(path);
  EXPECT_NE(text.find("worst difference"), std::string::npos) << text;
  EXPECT_NE(text.find("Focus:foc:\t0.007;"), std::string::npos) << text;  // fx Sx, Sx = 5 um
  EXPECT_NE(text.find("Cx:cx:\t950.5;"), std::string::npos) << text;
  EXPECT_NE(text.find("ImageHeight:imgh:\t1080;"), std::string::npos) << text;
  const ModelFile r = read_model_file(path);
  EXPECT_EQ(r.format, ModelFormat::kHalcon);
  EXPECT_NEAR(r.model.fx(), 1400, 1e-9);
  EXPECT_NEAR(r.model.fy(), 1390, 1e-9);
  EXPECT_EQ(r.model.cx(), 950.5);
  // Two fits, each within 0.1 px.
  const double diff = max_projection_difference(mild, r.model);
  std::printf("HALCON round trip of a mild lens: %.4f px at the worst pixel\n", diff);
  EXPECT_LT(diff, 0.2);
  // Without distortion the conversion is exact.
  const CameraModel pinhole =
      CameraModel::opencv5(640, 480, 500, 510, 319.5, 239.5, {0, 0, 0, 0, 0});
  write_camera_model(path, pinhole, {}, ModelFormat::kHalcon);
  EXPECT_LT(max_projection_difference(pinhole, read_camera_model(path)), 1e-9);
}

TEST(Formats, HalconSampleReads) {
  const ModelFile f = read_model_file(kSamples + "halcon_polynomial.dat");
  EXPECT_EQ(f.format, ModelFormat::kHalcon);
  EXPECT_EQ(f.model.width(), 2448);
  EXPECT_EQ(f.model.height(), 2048);
  EXPECT_NEAR(f.model.fx(), 0.01602 / 3.45e-6, 1e-9);
  EXPECT_EQ(f.model.cx(), 1231.5);
  EXPECT_EQ(f.model.cy(), 1019.25);
  // First order: OpenCV's k1 = -K1 Focus^2 (the polynomial runs the other way).
  EXPECT_NEAR(f.model.params()[4], 1000 * 0.01602 * 0.01602, 0.01);
}

TEST(Formats, HalconRefusesALensItsPolynomialCannotFollow) {
  const std::string path = temp_path("strong.dat");
  std::filesystem::remove(path);
  expect_invalid([&] { write_camera_model(path, model_with_k3(), {}, ModelFormat::kHalcon); },
                 {"halcon", "opencv5", "the limit is 0.1 px", "nothing written"});
  EXPECT_FALSE(std::filesystem::exists(path));
}

TEST(Formats, HalconBadInput) {
  const std::string good = read_text(kSamples + "halcon_polynomial.dat");
  expect_truncations_refused("cut.dat", good);
  expect_refused(write_text("kappa.dat", replaced(good, "Poly1:poly1:", "Kappa:kappa:")),
                 {"'Kappa'", "division model"});
  expect_refused(write_text("unknown.dat", replaced(good, "Poly3:poly3:", "Poly6:poly6:")),
                 {"unknown parameter 'Poly6'"});
  expect_refused(write_text("type.dat", replaced(good, "0.01602;", "short;")),
                 {"'Focus'", "not a number"});
  expect_refused(write_text("size.dat", replaced(good, "2448;", "2448.5;")), {"'ImageWidth'"});
  expect_refused(write_text("sx.dat", replaced(good, "Sx:sx:\t3.45e-06;", "Sx:sx:\t-3.45e-06;")),
                 {"'Sx' must be positive"});
  std::string no_sy = good;
  no_sy.erase(no_sy.find("Sy:sy:"), no_sy.find("Cx:cx:") - no_sy.find("Sy:sy:"));
  expect_refused(write_text("nosy.dat", no_sy), {"has no parameter 'Sy'"});
  expect_refused(write_text("dup.dat", replaced(good, "Poly3:poly3:", "Poly2:poly2:")),
                 {"'Poly2' appears twice"});
  expect_refused(
      write_text(
          "camtype.dat",
          replaced(good, "Focus:foc:",
                   "Camera:Type:\t\"area_scan_division\";\n\tSTRING;\n\t\"Type\";\n\nFocus:foc:")),
      {"area_scan_division"});
  expect_refused(write_text("strong.dat", replaced(good, "-1000.0;", "-20000.0;")),
                 {"fits posecal's lens model opencv5 only to", "the limit is 0.1 px"});
  // The camera type line of newer files is accepted.
  const std::string typed =
      replaced(good, "Focus:foc:",
               "Camera:Type:\t\"area_scan_polynomial\";\n\tSTRING;\n\t\"Type\";\n\nFocus:foc:");
  EXPECT_EQ(read_camera_model(write_text("typed.dat", typed)).width(), 2448);
}

// Files at the size limit built to make a careless parser quadratic (many keys, one long
// statement, references without ';') are read or refused in well under a second each.
TEST(Formats, InputsAtTheSizeLimitTakeLinearTime) {
  const size_t n = kMaxModelFileBytes - 64;
  // (built with append: GCC 12 warns falsely on "literal" + std::string, -Wrestrict)
  std::string many_keys = "image_width: 640\n";
  for (int i = 0; many_keys.size() + 16 < n; ++i) {
    many_keys.append("k").append(std::to_string(i)).append(": 1\n");
  }
  std::string flow_keys = "{'lensmodel': 'LENSMODEL_OPENCV5'";
  for (int i = 0; flow_keys.size() + 16 < n; ++i) {
    flow_keys.append(", 'k").append(std::to_string(i)).append("': 1");
  }
  const auto padded = [&](std::string head, char fill, const char* tail) {
    head.append(n - 64, fill);
    return head.append(tail);
  };
  const std::vector<std::pair<std::string, std::string>> inputs = {
      {"keys.yaml", many_keys},
      {"flowkeys.cameramodel", flow_keys + "}\n"},
      {"statement.dat", padded("ParGroup: Camera: Parameter;\n\"x\";\nFocus:foc: ", '1', "")},
      {"amp.xml", padded("<?xml version=\"1.0\"?>\n<opencv_storage>", '&', "")},
      {"list.yaml", padded("image_width: [", '1', "]\n")},
  };
  for (const auto& [name, text] : inputs) {
    const std::string path = write_text(name, text);
    const auto t0 = std::chrono::steady_clock::now();
    try {
      read_camera_model(path);
    } catch (const Error& e) {
      EXPECT_EQ(e.code(), ErrorCode::kInvalidArgument) << name << ": " << e.what();
    }
    const double s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    EXPECT_LT(s, 1.0 * test::time_factor()) << name;
  }
}

// ---- Writing --------------------------------------------------------------------------------

TEST(Formats, WriteRefusesNamesOfOtherFormats) {
  const CameraModel m = model_with_k3();
  for (const auto& [file, format] :
       std::vector<std::pair<std::string, ModelFormat>>{{"a.json", ModelFormat::kRos},
                                                        {"a.xml", ModelFormat::kKalibr},
                                                        {"a.cameramodel", ModelFormat::kOpenCV},
                                                        {"a.yml", ModelFormat::kMrcal},
                                                        {"a.yaml", ModelFormat::kHalcon}}) {
    const std::string path = temp_path(file);
    std::filesystem::remove(path);
    expect_invalid([&] { write_camera_model(path, m, {}, format); },
                   {path, model_format_name(format)});
    EXPECT_FALSE(std::filesystem::exists(path)) << path;
  }
  expect_invalid([&] { write_camera_model(temp_path("a.txt"), m); }, {"a.txt", "name a format"});
  EXPECT_FALSE(std::filesystem::exists(temp_path("a.txt")));
  // YAML names take the YAML formats.
  write_camera_model(temp_path("b.yml"), m, {}, ModelFormat::kRos);
  EXPECT_EQ(read_model_file(temp_path("b.yml")).format, ModelFormat::kRos);
}
