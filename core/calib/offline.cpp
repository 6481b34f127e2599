#include "calib/offline.hpp"

#include <algorithm>
#include <cctype>
#include <filesystem>
#include <map>
#include <set>

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

namespace {

// The camera part of a file name: without its extension and its last run of digits (the frame
// number), separators trimmed at both ends.
std::string camera_key(const std::string& file_name) {
  std::string stem = fs::path(file_name).stem().string();
  const size_t last = stem.find_last_of("0123456789");
  if (last != std::string::npos) {
    size_t first = last;
    while (first > 0 && std::isdigit(static_cast<unsigned char>(stem[first - 1]))) --first;
    stem.erase(first, last + 1 - first);
  }
  const size_t b = stem.find_first_not_of("_-. ");
  if (b == std::string::npos) return "";
  return stem.substr(b, stem.find_last_not_of("_-. ") - b + 1);
}

std::string size_text(const cv::Size& s) {
  return std::to_string(s.width) + "x" + std::to_string(s.height);
}

std::string group_list(const std::vector<ImageGroup>& groups) {
  std::string text;
  for (const ImageGroup& g : groups) {
    if (!text.empty()) text += ", ";
    text += "'" + g.name + "' (" + std::to_string(g.files.size()) +
            (g.files.size() == 1 ? " image)" : " images)");
  }
  return text;
}

const ImageGroup& choose_group(const std::vector<ImageGroup>& groups, const std::string& wanted,
                               const std::string& dir) {
  if (wanted.empty()) {
    if (groups.size() == 1) return groups.front();
    throw Error(ErrorCode::kInvalidArgument,
                "'" + dir + "' holds images of " + std::to_string(groups.size()) +
                    " cameras or sizes (grouped by image size and file name): " +
                    group_list(groups) + "; choose one with camera_group (--camera-group NAME)");
  }
  for (const ImageGroup& g : groups)
    if (g.name == wanted) return g;
  // The camera name alone or the size alone, where it names one group.
  const ImageGroup* match = nullptr;
  int matches = 0;
  for (const ImageGroup& g : groups) {
    if (g.camera == wanted || size_text(g.size) == wanted) {
      match = &g;
      ++matches;
    }
  }
  if (matches == 1) return *match;
  throw Error(ErrorCode::kInvalidArgument,
              "camera_group '" + wanted + "' " +
                  (matches == 0 ? "is none of" : "names more than one of") + " the groups of '" +
                  dir + "': " + group_list(groups));
}

}  // namespace

std::vector<ImageGroup> group_images(const std::vector<std::string>& files,
                                     std::vector<ImageVerdict>* unreadable) {
  struct Item {
    std::string path, camera;
    cv::Size size;
  };
  std::vector<Item> items;
  std::map<std::string, int> shared;
  for (const std::string& file : files) {
    const std::string name = fs::path(file).filename().string();
    try {
      // The header only: a FIFO, a non-image or an image above kMaxImagePixels is refused
      // before anything is decoded (common/image_file.hpp).
      const ImageFileInfo info = check_image_file(file);
      items.push_back({file, camera_key(name),
                       cv::Size(static_cast<int>(info.width), static_cast<int>(info.height))});
      ++shared[items.back().camera];
    } catch (const Error& e) {
      unreadable->push_back({name, e.what()});
    }
  }
  // A name no other image shares names no camera ...
  for (Item& it : items)
    if (shared[it.camera] < 2) it.camera.clear();
  // ... and such an image goes with the one named camera of its size, where there is one.
  std::map<std::pair<int, int>, std::set<std::string>> cameras_of_size;
  for (const Item& it : items)
    if (!it.camera.empty()) cameras_of_size[{it.size.width, it.size.height}].insert(it.camera);
  std::vector<ImageGroup> groups;
  for (Item& it : items) {
    const auto& named = cameras_of_size[{it.size.width, it.size.height}];
    if (it.camera.empty() && named.size() == 1) it.camera = *named.begin();
    const std::string name =
        it.camera.empty() ? size_text(it.size) : it.camera + "@" + size_text(it.size);
    auto g = std::find_if(groups.begin(), groups.end(),
                          [&](const ImageGroup& x) { return x.name == name; });
    if (g == groups.end()) {
      groups.push_back({name, it.camera, it.size, {}});
      g = groups.end() - 1;
    }
    g->files.push_back(it.path);
  }
  return groups;
}

OfflineCalibration calibrate_images(const std::string& dir, const BoardSpec& spec,
                                    const OfflineOptions& options) {
  const Board target(spec);
  OfflineCalibration out;
  out.groups = group_images(list_files_sorted(dir), &out.rejected);
  if (out.groups.empty()) {
    throw Error(ErrorCode::kDegenerate,
                "no image in '" + dir + "' shows the target " + spec.to_string() + " (" +
                    std::to_string(out.rejected.size()) + " unreadable files)");
  }
  const ImageGroup& group = choose_group(out.groups, options.camera_group, dir);
  out.group = group.name;
  for (const ImageGroup& g : out.groups) {
    if (&g == &group) continue;
    for (const std::string& file : g.files)
      out.rejected.push_back({fs::path(file).filename().string(),
                              "in group '" + g.name + "', not the calibrated '" + group.name + "'"});
  }
  ImageProgress progress;
  progress.total = group.files.size();
  for (const std::string& file : group.files) {
    progress.index++;
    progress.file = fs::path(file).filename().string();
    progress.corners = 0;
    progress.used = false;
    progress.reason.clear();
    cv::Mat img;
    try {
      img = read_grey_image(file);
    } catch (const Error& e) {
      progress.reason = e.what();
    }
    if (!img.empty() && img.size() != group.size) {
      // The header said otherwise (a JPEG that the decoder turns by its EXIF orientation).
      progress.reason = "image size " + size_text(img.size()) + " differs from its group's " +
                        size_text(group.size);
    } else if (!img.empty()) {
      const Detection det = target.detect(img, options.detector);
      progress.corners = static_cast<int>(det.size());
      if (progress.corners < options.min_corners) {
        progress.reason = det.empty() ? "target not found"
                                      : "only " + std::to_string(det.size()) + " corners found";
      } else {
        progress.used = true;
        out.used.push_back(progress.file);
        out.observations.push_back(Observation::from(det));
      }
    }
    if (!progress.used) out.rejected.push_back({progress.file, progress.reason});
    if (options.progress) options.progress(progress);
  }
  std::sort(out.rejected.begin(), out.rejected.end(),
            [](const ImageVerdict& a, const ImageVerdict& b) { return a.file < b.file; });
  if (out.observations.empty()) {
    // One example of why: the images were there, so a wrong target spec or a folder of
    // another camera is the usual cause.
    const auto example = std::find_if(out.rejected.begin(), out.rejected.end(), [&](const auto& r) {
      return fs::path(group.files.front()).filename().string() == r.file;
    });
    throw Error(ErrorCode::kDegenerate,
                "no image of group '" + group.name + "' in '" + dir + "' shows the target " +
                    spec.to_string() + " (" + std::to_string(group.files.size()) +
                    " images; the first, " + example->file + ": " + example->reason + ")");
  }
  out.result = calibrate(out.observations, group.size, options.calibration);
  return out;
}

}  // namespace posecal
