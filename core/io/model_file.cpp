#include "io/model_file.hpp"

#include <ctime>
#include <fstream>
#include <opencv2/core/persistence.hpp>

#include "common/atomic_file.hpp"
#include "common/clock.hpp"
#include "common/error.hpp"

namespace posecal {

CameraModel read_camera_model(const std::string& path) {
  // Checked here so OpenCV does not log its own error into the host's stderr.
  if (!std::ifstream(path).good()) throw Error(ErrorCode::kIo, "cannot open camera model file '" + path + "'");
  cv::FileStorage fs;
  try {
    if (!fs.open(path, cv::FileStorage::READ)) {
      throw Error(ErrorCode::kIo, "cannot open camera model file '" + path + "'");
    }
  } catch (const cv::Exception& e) {
    throw Error(ErrorCode::kInvalidArgument,
                "camera model file '" + path + "' is not valid OpenCV YAML/JSON: " + e.msg);
  }
  auto need = [&](const char* key) {
    cv::FileNode n = fs[key];
    if (n.empty() || n.isNone()) {
      throw Error(ErrorCode::kInvalidArgument,
                  "camera model file '" + path + "' has no field '" + key + "'");
    }
    return n;
  };
  try {
    cv::Mat K, D;
    need("camera_matrix") >> K;
    need("distortion_coefficients") >> D;
    const cv::FileNode wn = need("image_width"), hn = need("image_height");
    if (!wn.isReal() && !wn.isInt()) {
      throw Error(ErrorCode::kInvalidArgument, "'" + path + "': image_width is not a number");
    }
    if (!hn.isReal() && !hn.isInt()) {
      throw Error(ErrorCode::kInvalidArgument, "'" + path + "': image_height is not a number");
    }
    const double w = static_cast<double>(wn), h = static_cast<double>(hn);
    if (K.rows != 3 || K.cols != 3) {
      throw Error(ErrorCode::kInvalidArgument, "'" + path + "': camera_matrix is not 3x3");
    }
    if (D.total() == 0 || (D.rows != 1 && D.cols != 1)) {
      throw Error(ErrorCode::kInvalidArgument,
                  "'" + path + "': distortion_coefficients is not a vector");
    }
    if (!(w > 0 && h > 0 && w < 1e6 && h < 1e6 && w == std::floor(w) && h == std::floor(h))) {
      throw Error(ErrorCode::kInvalidArgument,
                  "'" + path + "': image_width/image_height must be positive integers");
    }
    K.convertTo(K, CV_64F);
    D.convertTo(D, CV_64F);
    std::vector<double> d(D.begin<double>(), D.end<double>());
    CameraModel model = CameraModel::from_opencv(static_cast<int>(w), static_cast<int>(h),
                                                 cv::Matx33d(K.ptr<double>()), d);
    std::string why;
    if (!model.is_valid(&why)) {
      throw Error(ErrorCode::kInvalidArgument, "'" + path + "': " + why);
    }
    return model;
  } catch (const cv::Exception& e) {
    throw Error(ErrorCode::kInvalidArgument, "camera model file '" + path + "': " + e.msg);
  }
}

void write_camera_model(const std::string& path, const CameraModel& model,
                        const CalibrationFileExtras& extras) {
  // Composed in memory, then written atomically: a full disk or a kill leaves the old file.
  const bool json = path.size() >= 5 && path.compare(path.size() - 5, 5, ".json") == 0;
  cv::FileStorage fs;
  try {
    fs.open("", cv::FileStorage::WRITE | cv::FileStorage::MEMORY |
                    (json ? cv::FileStorage::FORMAT_JSON : cv::FileStorage::FORMAT_YAML));
  } catch (const cv::Exception& e) {
    throw Error(ErrorCode::kInternal, "cannot compose calibration file '" + path + "': " + e.msg);
  }
  fs << "calibration_time" << utc_now_iso8601();
  if (extras.nr_of_frames >= 0) fs << "nr_of_frames" << extras.nr_of_frames;
  fs << "image_width" << model.width();
  fs << "image_height" << model.height();
  fs << "lens_model" << std::string(lens_model_name(model.lens_model()));
  fs << "camera_matrix" << cv::Mat(model.camera_matrix());
  const std::vector<double> d = model.distortion_coefficients();
  fs << "distortion_coefficients"
     << cv::Mat(1, static_cast<int>(d.size()), CV_64F, const_cast<double*>(d.data()));
  if (extras.avg_reprojection_error >= 0) {
    fs << "avg_reprojection_error" << extras.avg_reprojection_error;
  }
  if (!extras.param_std.empty()) {
    std::string names;
    for (const auto& n : model.param_names()) names += (names.empty() ? "" : " ") + n;
    fs << "intrinsic_names" << names;
    fs << "std_deviations_intrinsics"
       << cv::Mat(1, static_cast<int>(extras.param_std.size()), CV_64F,
                  const_cast<double*>(extras.param_std.data()));
  }
  for (const auto& [key, value] : extras.strings) fs << key << value;
  const std::string text = fs.releaseAndGetString();
  std::string error;
  if (!write_file_atomic(path, text, &error)) throw Error(ErrorCode::kIo, error);
}

}  // namespace posecal
