#include "calib/offline.hpp"

#include <algorithm>
#include <filesystem>

#include "common/error.hpp"
#include "common/image_file.hpp"

namespace posecal {

namespace fs = std::filesystem;

std::vector<std::string> list_files_sorted(const std::string& dir) {
  std::error_code ec;
  if (!fs::exists(dir, ec))
    throw Error(ErrorCode::kNotFound, "directory '" + dir + "' does not exist");
  if (!fs::is_directory(dir, ec))
    throw Error(ErrorCode::kInvalidArgument, "'" + dir + "' is not a directory");
  std::vector<std::string> files;
  for (fs::directory_iterator it(dir, ec), end; !ec && it != end; it.increment(ec)) {
    std::error_code ec2;
    if (it->is_regular_file(ec2)) files.push_back(it->path().string());
  }
  if (ec) throw Error(ErrorCode::kIo, "cannot list '" + dir + "': " + ec.message());
  std::sort(files.begin(), files.end());
  return files;
}

OfflineCalibration calibrate_images(const std::string& dir, const BoardSpec& spec,
                                    const OfflineOptions& options) {
  const Board target(spec);
  OfflineCalibration out;
  cv::Size size;
  for (const std::string& file : list_files_sorted(dir)) {
    const std::string name = fs::path(file).filename().string();
    cv::Mat img;
    try {
      // The header first: an image above kMaxImagePixels, a FIFO or a non-image is refused
      // before anything is decoded (common/image_file.hpp).
      img = read_grey_image(file);
    } catch (const Error& e) {
      out.rejected.push_back({name, e.what()});
      continue;
    }
    if (size.empty()) {
      size = img.size();
    } else if (img.size() != size) {
      out.rejected.push_back(
          {name, "image size " + std::to_string(img.cols) + "x" + std::to_string(img.rows) +
                     " differs from the first image's " + std::to_string(size.width) + "x" +
                     std::to_string(size.height)});
      continue;
    }
    const Detection det = target.detect(img, options.detector);
    if (static_cast<int>(det.size()) < options.min_corners) {
      out.rejected.push_back({name, det.empty()
                                        ? "target not found"
                                        : "only " + std::to_string(det.size()) + " corners found"});
      continue;
    }
    out.used.push_back(name);
    out.observations.push_back(Observation::from(det));
  }
  if (out.observations.empty()) {
    throw Error(ErrorCode::kDegenerate,
                "no image in '" + dir + "' shows the target " + spec.to_string());
  }
  out.result = calibrate(out.observations, size, options.calibration);
  return out;
}

}  // namespace posecal
