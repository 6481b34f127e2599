// Offline calibration from a folder of images (posecal calibrate --images DIR).
#pragma once

#include <string>
#include <vector>

#include "calib/calibration.hpp"
#include "board/board.hpp"

namespace posecal {

struct ImageVerdict {
  std::string file;
  std::string reason;  // why the image was not used
};

struct OfflineCalibration {
  CalibrationResult result;
  std::vector<std::string> used;          // files whose detections were calibrated, in name order
  std::vector<ImageVerdict> rejected;     // unreadable, wrong size, target not found ...
  std::vector<Observation> observations;  // of the used files
};

struct OfflineOptions {
  CalibrationOptions calibration;
  DetectorOptions detector;
  // Frames with fewer corners are rejected (a pose needs >= 4; more keeps weak views out).
  int min_corners = 6;
};

// Lists the regular files of `dir` in name order (throws Error(kNotFound/kIo)).
std::vector<std::string> list_files_sorted(const std::string& dir);

// Reads every file of `dir` in name order, detects the target and calibrates. Images that cannot
// be read, are above kMaxImagePixels (refused from the header, before decoding:
// common/image_file.hpp) or show no target are listed in `rejected` with the reason, never fatal.
// Throws Error(kNotFound) for a missing directory, Error(kDegenerate) if the usable images cannot
// determine the calibration.
OfflineCalibration calibrate_images(const std::string& dir, const BoardSpec& board,
                                    const OfflineOptions& options = {});

}  // namespace posecal
