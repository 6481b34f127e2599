// Camera-model files: the formats other vision tools read (docs/formats.md has each format's
// field mapping and what its reader accepts).
//
//   opencv  OpenCV's calibration YAML / JSON / XML (cv::FileStorage), the format cv::undistort
//           users read; the only one that also holds the uncertainty (std, covariance, expected
//           error) and the session's outcome (opencv_storage.cpp)
//   ros     ROS camera_info YAML as camera_calibration writes it (ros_camera_info.cpp)
//   mrcal   mrcal's .cameramodel, a Python literal (mrcal_cameramodel.cpp)
//   kalibr  Kalibr's camchain YAML, cam0 pinhole-radtan (kalibr_camchain.cpp)
//   halcon  HALCON's area_scan_polynomial camera parameters, a fit in either direction
//           (halcon_campar.cpp)
//
// Writing: the format is named, or follows the extension (.cameramodel: mrcal; .yml, .yaml,
// .json, .xml: OpenCV). The file is composed in memory and written with write_file_atomic: an
// error (a model the format cannot hold, a full disk) leaves the previous file as it was.
//
// Reading is strict and bounded: a model file comes from outside (evaluate --result,
// sim://?model=FILE, the C ABI), so read_camera_model
//  - opens it without blocking and refuses what is not a regular file (a FIFO, a device, a
//    directory) and files larger than kMaxModelFileBytes (1 MiB);
//  - decides the format by extension (.cameramodel: mrcal) and otherwise by the first line that
//    is not blank or a '#' comment: "%YAML:" OpenCV YAML; '<' OpenCV XML; '{' OpenCV JSON, or
//    mrcal when the first key is mrcal's; "ParGroup:" HALCON; other YAML: Kalibr when it starts
//    with cam0, else ROS;
//  - checks the text before any parser sees it: nesting at most kMaxModelFileDepth (64) levels,
//    only the subset of the syntax the format's writers produce (for OpenCV's own parsers, which
//    overflow the stack or loop forever on some inputs: no DOCTYPE or entities in XML, one YAML
//    document, ...);
//  - accepts only the format's known keys, each once, needs the keys that carry the model, and
//    checks types, sizes (integers, at most CameraModel::kMaxImageSide per side and
//    kMaxImagePixels in all) and the lens model (one of the lens table, core/lens/lens_models.hpp);
//  - refuses a file cut short: posecal's OpenCV files end with `posecal_file_end: 1`
//    (kModelFileEndKey; a file with lens_model whose last key is not that is refused as truncated),
//    mrcal's and JSON's closing brace and XML's closing tag must be there, and ROS and Kalibr need
//    every field that ends their files.
// Errors are Error(kIo) when the file cannot be opened or read, else Error(kInvalidArgument);
// both name the file and the key or limit.
#pragma once

#include <cstddef>
#include <optional>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "lens/camera_model.hpp"

namespace posecal {

inline constexpr size_t kMaxModelFileBytes = size_t{1} << 20;
inline constexpr int kMaxModelFileDepth = 64;
inline constexpr const char* kModelFileEndKey = "posecal_file_end";

enum class ModelFormat { kOpenCV, kRos, kMrcal, kKalibr, kHalcon };

// "opencv", "ros", "mrcal", "kalibr", "halcon".
const char* model_format_name(ModelFormat format);
std::optional<ModelFormat> model_format_from_name(std::string_view name);
// Every format, in the order above.
const std::vector<ModelFormat>& model_formats();
// By extension: .cameramodel: mrcal; .yml, .yaml, .json, .xml: OpenCV; otherwise none.
std::optional<ModelFormat> model_format_from_path(const std::string& path);
// The extension a file of the format gets when only the format is chosen (the station's
// per-camera files): ".yml", ".yaml", ".cameramodel", ".yaml", ".dat".
const char* model_format_extension(ModelFormat format);

// What a file holds besides the model. Written where the format has a place for it (OpenCV:
// everything; ROS: camera_id as camera_name; the others: the model only).
struct CalibrationFileExtras {
  int nr_of_frames = -1;               // omitted if < 0
  double avg_reprojection_error = -1;  // omitted if < 0
  std::vector<double> param_std;       // per-parameter standard deviations (omitted if empty)
  // The intrinsics covariance (scaled by the residual variance, as the result JSON's
  // "covariance"), num_params x num_params row-major; omitted if empty.
  std::vector<double> covariance;
  // The coefficients the keyframes did not determine (CalibrationResult::held) and the
  // covariance with them free under their prior (CalibrationResult::held_covariance, scaled as
  // `covariance`), num_params x num_params row-major; both omitted if `held` is empty. The
  // expected error (and its map) is taken over these when present.
  std::vector<std::string> held;
  std::vector<double> held_covariance;
  double expected_error_px = -1;  // the expected projection error, RMS px; omitted if < 0
  std::optional<bool> converged;  // the session's outcome; omitted if unset
  std::optional<bool> interrupted;
  // Free-form text fields (OpenCV: target, camera_uri, camera_id; other keys must be added to
  // the reader's known keys).
  std::vector<std::pair<std::string, std::string>> strings;
};

// A file as read: its format, the model and the extras the format holds (OpenCV's file: all of
// the above that are present; other formats: none).
struct ModelFile {
  ModelFormat format = ModelFormat::kOpenCV;
  CameraModel model;
  CalibrationFileExtras extras;
};

// Reads a camera-model file of any format, strictly (above). Throws Error(kIo /
// kInvalidArgument) naming the file and field.
ModelFile read_model_file(const std::string& path);
CameraModel read_camera_model(const std::string& path);

// Writes the model in `format` (none: by the extension, Error(kInvalidArgument) if it names no
// format). Error(kInvalidArgument) naming the file, the format and the model if the format
// cannot hold the model (Kalibr's radtan has no k3; HALCON's polynomial fits it worse than its
// limit), or if the extension is another format's (.cameramodel is mrcal's; .json and .xml
// OpenCV's; .yml and .yaml OpenCV's, ROS' or Kalibr's); nothing is written then.
void write_camera_model(const std::string& path, const CameraModel& model,
                        const CalibrationFileExtras& extras = {},
                        std::optional<ModelFormat> format = std::nullopt);

}  // namespace posecal
