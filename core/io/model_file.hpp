// Camera model files: OpenCV's calibration YAML / JSON (cv::FileStorage), the format
// cv::undistort users read. Where further formats (ROS camera_info, mrcal, Kalibr, HALCON) go.
#pragma once

#include <string>
#include <utility>
#include <vector>

#include "lens/camera_model.hpp"

namespace posecal {

// Reads an OpenCV calibration YAML/JSON file (camera_matrix, distortion_coefficients,
// image_width, image_height). Throws Error(kIo / kInvalidArgument) naming the file and field.
CameraModel read_camera_model(const std::string& path);

// Extra fields written along with the model.
struct CalibrationFileExtras {
  int nr_of_frames = -1;               // omitted if < 0
  double avg_reprojection_error = -1;  // omitted if < 0
  std::vector<double> param_std;       // per-parameter standard deviations (omitted if empty)
  std::vector<std::pair<std::string, std::string>> strings;  // free-form text fields
};
// Writes OpenCV YAML (".yml"/".yaml") or JSON (".json") in cv::FileStorage format.
void write_camera_model(const std::string& path, const CameraModel& model,
                        const CalibrationFileExtras& extras = {});

}  // namespace posecal
