// Camera model files: OpenCV's calibration YAML / JSON (cv::FileStorage), the format
// cv::undistort users read. Where further formats (ROS camera_info, mrcal, Kalibr, HALCON) go.
//
// Reading is strict and bounded: a model file comes from outside (evaluate --result,
// sim://?model=FILE, the C ABI), so read_camera_model
//  - opens it without blocking and refuses what is not a regular file (a FIFO, a device, a
//    directory) and files larger than kMaxModelFileBytes (1 MiB);
//  - decides the format by content, as OpenCV does ("%YAML" first: YAML; '{' first: JSON; XML
//    is not read), and before OpenCV parses anything refuses nesting deeper than
//    kMaxModelFileDepth (64) levels (OpenCV's recursive parser overflows the stack on a few
//    thousand) and YAML beyond what OpenCV writes (one document, plain keys, no tabs);
//  - accepts only known top-level keys, each once: posecal's (those write_camera_model writes,
//    and the extras.strings keys target, camera_uri, camera_id, converged; a caller passing
//    another key must add it to the reader) and those of OpenCV's calibration sample
//    (samples/cpp/calibration.cpp), so OpenCV's files load;
//  - needs camera_matrix (3x3, last row 0 0 1, no skew) and distortion_coefficients as OpenCV
//    matrices of dt d or f, image_width and image_height (integers, at most
//    CameraModel::kMaxImageSide per side and kMaxImagePixels in all); lens_model, if present,
//    names a model of the lens table (core/lens/lens_models.hpp) matching the coefficients;
//  - completeness: a file posecal wrote has lens_model, and posecal ends its files with
//    `posecal_file_end: 1` (kModelFileEndKey). A file with lens_model whose last key is not
//    that is refused as truncated (files posecal wrote before this rule must be saved again or
//    get the line appended). Other files must parse completely and have the required keys.
// Errors are Error(kIo) when the file cannot be opened or read, else Error(kInvalidArgument);
// both name the file and the key or limit.
#pragma once

#include <cstddef>
#include <string>
#include <utility>
#include <vector>

#include "lens/camera_model.hpp"

namespace posecal {

inline constexpr size_t kMaxModelFileBytes = size_t{1} << 20;
inline constexpr int kMaxModelFileDepth = 64;
inline constexpr const char* kModelFileEndKey = "posecal_file_end";

// Reads an OpenCV calibration YAML/JSON file (camera_matrix, distortion_coefficients,
// image_width, image_height), strictly (above). Throws Error(kIo / kInvalidArgument) naming the
// file and field.
CameraModel read_camera_model(const std::string& path);

// Extra fields written along with the model.
struct CalibrationFileExtras {
  int nr_of_frames = -1;               // omitted if < 0
  double avg_reprojection_error = -1;  // omitted if < 0
  std::vector<double> param_std;       // per-parameter standard deviations (omitted if empty)
  std::vector<std::pair<std::string, std::string>> strings;  // free-form text fields
};
// Writes OpenCV YAML (".yml"/".yaml") or JSON (".json") in cv::FileStorage format, ending with
// kModelFileEndKey: 1. extras.strings keys must be known to read_camera_model (above).
void write_camera_model(const std::string& path, const CameraModel& model,
                        const CalibrationFileExtras& extras = {});

}  // namespace posecal
