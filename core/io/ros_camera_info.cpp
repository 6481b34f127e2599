// ROS camera_info YAML, the layout camera_calibration and camera_calibration_parsers write and
// camera_info_manager reads (docs/formats.md). One camera: K, D in the ROS distortion model that
// matches posecal's lens model, R the identity and P = [K | 0] (a monocular camera whose
// rectified image is the undistorted one with the same K).
#include <cctype>

#include "io/model_file_internal.hpp"

namespace posecal::model_io {

namespace {

// ROS' name of the distortion model of an OpenCV coefficient vector of this length.
// ROS's distortion_model of a lens model, nullptr if it has none. ROS's equidistant is the
// Kannala-Brandt model with cv::fisheye's k1..k4 (image_geometry).
const char* ros_distortion_model(LensModel model) {
  if (model == LensModel::kFisheye) return "equidistant";
  if (opencv_coefficients(model) == 5) return "plumb_bob";
  if (opencv_coefficients(model) == 8) return "rational_polynomial";
  return nullptr;
}

// camera_info_manager accepts names of letters, digits and '_' only.
std::string ros_camera_name(const CalibrationFileExtras& extras) {
  std::string name;
  for (const auto& [key, value] : extras.strings) {
    if (key == "camera_id") name = value;
  }
  for (char& c : name) {
    if (!std::isalnum(static_cast<unsigned char>(c))) c = '_';
  }
  return name.empty() ? "camera" : name;
}

std::string matrix_text(const char* key, int rows, int cols, const std::vector<double>& data) {
  return std::string(key) + ":\n  rows: " + std::to_string(rows) +
         "\n  cols: " + std::to_string(cols) + "\n  data: " + number_list(data) + "\n";
}

// A matrix {rows, cols, data} of the given shape (cols < 0: any, returned in *cols_out).
std::vector<double> read_matrix(const Fields& f, const TextNode& root, const std::string& key,
                                int rows, int cols, int* cols_out = nullptr) {
  const TextNode& m = f.need(root, key, "");
  const std::string what = "'" + key + "'";
  if (m.kind != TextNode::Kind::kMap) f.fail(m, what, "is not a matrix {rows, cols, data}");
  f.only_keys(m, {"rows", "cols", "data"}, key + ".");
  const int r = f.integer(f.need(m, "rows", key + "."), "'" + key + ".rows'", 0, 16);
  const int c = f.integer(f.need(m, "cols", key + "."), "'" + key + ".cols'", 0, 16);
  if (r != rows || (cols >= 0 && c != cols)) {
    f.fail(m, what,
           "is " + std::to_string(r) + "x" + std::to_string(c) + "; expected " +
               std::to_string(rows) + "x" + (cols >= 0 ? std::to_string(cols) : "N"));
  }
  if (cols_out != nullptr) *cols_out = c;
  const size_t n = static_cast<size_t>(r) * static_cast<size_t>(c);
  return f.numbers(f.need(m, "data", key + "."), "'" + key + ".data'", n, n);
}

}  // namespace

std::string compose_ros(const std::string& path, const CameraModel& model,
                        const CalibrationFileExtras& extras) {
  const std::vector<double> d = model.distortion_coefficients();
  const char* distortion = ros_distortion_model(model.lens_model());
  if (distortion == nullptr) {
    cannot_hold(path, ModelFormat::kRos, model, "has no ROS distortion_model");
  }
  const double fx = model.fx(), fy = model.fy(), cx = model.cx(), cy = model.cy();
  return "image_width: " + std::to_string(model.width()) +
         "\nimage_height: " + std::to_string(model.height()) +
         "\ncamera_name: " + ros_camera_name(extras) + "\n" +
         matrix_text("camera_matrix", 3, 3, {fx, 0, cx, 0, fy, cy, 0, 0, 1}) +
         "distortion_model: " + distortion + "\n" +
         matrix_text("distortion_coefficients", 1, static_cast<int>(d.size()), d) +
         matrix_text("rectification_matrix", 3, 3, {1, 0, 0, 0, 1, 0, 0, 0, 1}) +
         matrix_text("projection_matrix", 3, 4, {fx, 0, cx, 0, 0, fy, cy, 0, 0, 0, 1, 0});
}

ModelFile parse_ros(const std::string& path, std::string_view text) {
  const TextNode root = parse_yaml_subset(path, text);
  const Fields f(path);
  f.only_keys(root,
              {"image_width", "image_height", "camera_name", "camera_matrix", "distortion_model",
               "distortion_coefficients", "rectification_matrix", "projection_matrix"},
              "");
  const int w =
      f.integer(f.need(root, "image_width", ""), "'image_width'", 1, CameraModel::kMaxImageSide);
  const int h =
      f.integer(f.need(root, "image_height", ""), "'image_height'", 1, CameraModel::kMaxImageSide);
  f.string(f.need(root, "camera_name", ""), "'camera_name'");
  const std::vector<double> K = read_matrix(f, root, "camera_matrix", 3, 3);
  if (K[1] != 0 || K[3] != 0 || K[6] != 0 || K[7] != 0 || K[8] != 1) {
    bad_file(path, "'camera_matrix' must be [fx 0 cx; 0 fy cy; 0 0 1]");
  }
  int n = 0;
  const std::vector<double> D = read_matrix(f, root, "distortion_coefficients", 1, -1, &n);
  // camera_calibration_parsers reads files without distortion_model as plumb_bob.
  const TextNode* model_node = f.find(root, "distortion_model");
  const std::string distortion =
      model_node ? f.string(*model_node, "'distortion_model'") : std::string("plumb_bob");
  if (distortion != "plumb_bob" && distortion != "rational_polynomial" &&
      distortion != "equidistant") {
    bad_file(path, "'distortion_model' '" + distortion +
                       "' is not read: posecal reads plumb_bob (opencv5), rational_polynomial "
                       "(opencv8) and equidistant (fisheye)");
  }
  const size_t expected = distortion == "plumb_bob" ? 5 : distortion == "equidistant" ? 4 : 8;
  if (D.size() != expected) {
    bad_file(path, "'distortion_coefficients' has " + std::to_string(D.size()) + " values; " +
                       distortion + " has " + std::to_string(expected));
  }
  read_matrix(f, root, "rectification_matrix", 3, 3);
  read_matrix(f, root, "projection_matrix", 3, 4);
  ModelFile file;
  file.format = ModelFormat::kRos;
  file.model = distortion == "equidistant"
                   ? model_from_opencv_fisheye(path, w, h, K, D, "'distortion_coefficients'")
                   : model_from_opencv(path, w, h, K, D, "'distortion_coefficients'");
  return file;
}

}  // namespace posecal::model_io
