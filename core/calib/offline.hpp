// Offline calibration from a folder of images (posecal calibrate --images DIR).
#pragma once

#include <functional>
#include <string>
#include <vector>

#include "calib/calibration.hpp"
#include "board/board.hpp"

namespace posecal {

struct ImageVerdict {
  std::string file;
  std::string reason;  // why the image was not used
};

// Images of one camera in one mode, as far as a folder tells: the same size and the same file
// name once its frame number is taken out (group_images).
struct ImageGroup {
  std::string name;   // "<camera>@<W>x<H>", or "<W>x<H>" where the names carry no camera
  std::string camera; // the names' common part ("left" for left01.jpg .. left14.jpg), or ""
  cv::Size size;
  std::vector<std::string> files;  // paths, in name order
};

// One image of an offline calibration, as it is done (OfflineOptions::progress).
struct ImageProgress {
  size_t index = 0;  // 1-based, of `total`
  size_t total = 0;
  std::string file;  // name within the folder
  int corners = 0;
  bool used = false;
  std::string reason;  // why it was not used
};

struct OfflineCalibration {
  std::string group;                      // the group calibrated (ImageGroup::name)
  std::vector<ImageGroup> groups;         // every group of the folder
  CalibrationResult result;
  std::vector<std::string> used;          // files whose detections were calibrated, in name order
  // unreadable, another group (camera or size), target not found ... with the reason, in name
  // order
  std::vector<ImageVerdict> rejected;
  std::vector<Observation> observations;  // of the used files
};

struct OfflineOptions {
  CalibrationOptions calibration;
  DetectorOptions detector;
  // Frames with fewer corners are rejected (a pose needs >= 4; more keeps weak views out).
  int min_corners = 6;
  // The group to calibrate where the folder holds several (group_images): its name, its camera
  // name alone or its size "WxH" alone, each where it names exactly one group. Empty: the folder
  // must hold one group.
  std::string camera_group;
  // Called after each image of the group is detected, on the calling thread.
  std::function<void(const ImageProgress&)> progress;
};

// Lists the regular files of `dir` in name order (throws Error(kNotFound/kIo)).
std::vector<std::string> list_files_sorted(const std::string& dir);

// Groups image files by size (from their headers: common/image_file.hpp) and by camera: the file
// name without its extension and its last run of digits (the frame number), separators trimmed,
// where at least two images share it ("left" for left01.jpg .. left14.jpg, "cam0" for
// cam0_0001.png, "right" for 0001_right.png); names that no other image shares ("a.png",
// "board.png") carry no camera. Files whose header cannot be read are returned in `unreadable`
// with the reason. Groups in order of their first file.
std::vector<ImageGroup> group_images(const std::vector<std::string>& files,
                                     std::vector<ImageVerdict>* unreadable);

// Reads the files of `dir` in name order, groups them (group_images), detects the target in the
// chosen group's images and calibrates. A folder with several groups needs
// OfflineOptions::camera_group: without it Error(kInvalidArgument) lists the groups; the other
// groups' images are listed in `rejected`. Images that cannot be read, are above kMaxImagePixels
// (refused from the header, before decoding) or show no target are listed in `rejected` with the
// reason, never fatal. Throws Error(kNotFound) for a missing directory, Error(kDegenerate) if the
// usable images cannot determine the calibration.
OfflineCalibration calibrate_images(const std::string& dir, const BoardSpec& board,
                                    const OfflineOptions& options = {});

}  // namespace posecal
