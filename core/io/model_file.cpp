// The one entry to camera-model files: format names, the choice of a format by extension or
// content, the bounded read, the atomic write, and what the formats share.
#include "io/model_file.hpp"


#include <algorithm>

#include "common/atomic_file.hpp"
#include "common/error.hpp"
#include "common/regular_file.hpp"
#include "io/model_file_internal.hpp"

namespace posecal {

namespace model_io {

void bad_file(const std::string& path, const std::string& why) {
  throw Error(ErrorCode::kInvalidArgument, "camera model file '" + path + "': " + why);
}

void cannot_hold(const std::string& path, ModelFormat format, const CameraModel& model,
                 const std::string& why) {
  throw Error(ErrorCode::kInvalidArgument,
              "cannot write '" + path + "' as " + model_format_name(format) + ": the lens model " +
                  lens_model_name(model.lens_model()) + " " + why + "; nothing written");
}

namespace {

CameraModel checked_model(const std::string& path, int width, int height,
                          const std::vector<double>& K9, const std::vector<double>& dist,
                          const std::string& what, bool fisheye) {
  CameraModel model;
  try {
    model = fisheye ? CameraModel::from_opencv_fisheye(width, height, cv::Matx33d(K9.data()), dist)
                    : CameraModel::from_opencv(width, height, cv::Matx33d(K9.data()), dist);
  } catch (const Error& e) {
    bad_file(path, what + ": " + e.what());
  }
  std::string why;
  if (!model.is_valid(&why)) bad_file(path, why);
  return model;
}

}  // namespace

CameraModel model_from_opencv(const std::string& path, int width, int height,
                              const std::vector<double>& K9, const std::vector<double>& dist,
                              const std::string& what) {
  return checked_model(path, width, height, K9, dist, what, false);
}

CameraModel model_from_opencv_fisheye(const std::string& path, int width, int height,
                                      const std::vector<double>& K9,
                                      const std::vector<double>& dist, const std::string& what) {
  return checked_model(path, width, height, K9, dist, what, true);
}

}  // namespace model_io

using model_io::bad_file;

namespace {

struct FormatInfo {
  ModelFormat format;
  const char* name;
  const char* extension;
};
constexpr FormatInfo kFormats[] = {{ModelFormat::kOpenCV, "opencv", ".yml"},
                                   {ModelFormat::kRos, "ros", ".yaml"},
                                   {ModelFormat::kMrcal, "mrcal", ".cameramodel"},
                                   {ModelFormat::kKalibr, "kalibr", ".yaml"},
                                   {ModelFormat::kHalcon, "halcon", ".dat"}};

const FormatInfo& info(ModelFormat f) {
  for (const FormatInfo& i : kFormats) {
    if (i.format == f) return i;
  }
  throw Error(ErrorCode::kInternal, "unknown model format");
}

bool ends_with(const std::string& s, std::string_view suffix) {
  return s.size() > suffix.size() &&
         s.compare(s.size() - suffix.size(), suffix.size(), suffix) == 0;
}

// The first key of a text starting with '{' (JSON or a Python dict), skipping spaces and '#'
// comments; empty if there is none.
std::string first_brace_key(std::string_view t) {
  size_t i = 1;
  while (i < t.size()) {
    if (t[i] == '#') {
      i = t.find('\n', i);
      if (i == std::string_view::npos) return {};
    } else if (t[i] == ' ' || t[i] == '\n' || t[i] == '\r' || t[i] == '\t') {
      ++i;
    } else {
      break;
    }
  }
  if (i >= t.size() || (t[i] != '\'' && t[i] != '"')) return {};
  const size_t end = t.find(t[i], i + 1);
  return end == std::string_view::npos ? std::string() : std::string(t.substr(i + 1, end - i - 1));
}

// The format of a file's text (model_file.hpp: by content when the extension does not decide),
// from its first line that is not blank or a '#' comment.
ModelFormat format_of_text(std::string_view t) {
  if (t.substr(0, 3) == "\xEF\xBB\xBF") t.remove_prefix(3);
  for (size_t i = 0; i < t.size();) {
    const size_t nl = std::min(t.find('\n', i), t.size());
    const std::string_view line = t.substr(i, nl - i);
    i = nl + 1;
    const size_t first = line.find_first_not_of(" \t\r");
    if (first == std::string_view::npos || line[first] == '#') continue;
    const std::string_view content = line.substr(first);
    if (content.substr(0, 6) == "%YAML:") return ModelFormat::kOpenCV;  // OpenCV's "%YAML:1.0"
    if (content[0] == '<') return ModelFormat::kOpenCV;
    if (content.substr(0, 9) == "ParGroup:") return ModelFormat::kHalcon;
    if (content[0] == '{') {
      const std::string key = first_brace_key(t.substr(t.find('{')));
      return key == "lensmodel" || key == "intrinsics" || key == "extrinsics" ||
                     key == "imagersize" || key == "valid_intrinsics_region"
                 ? ModelFormat::kMrcal
                 : ModelFormat::kOpenCV;
    }
    // YAML without OpenCV's header (a "%YAML 1.x" directive and '---' skipped): Kalibr's
    // camchain starts with its cameras.
    if (content[0] == '%' || content.substr(0, 3) == "---") continue;
    return content.substr(0, 5) == "cam0:" ? ModelFormat::kKalibr : ModelFormat::kRos;
  }
  return ModelFormat::kOpenCV;  // no content: refused there as empty
}

}  // namespace

const char* model_format_name(ModelFormat format) { return info(format).name; }

const char* model_format_extension(ModelFormat format) { return info(format).extension; }

std::optional<ModelFormat> model_format_from_name(std::string_view name) {
  for (const FormatInfo& i : kFormats) {
    if (name == i.name) return i.format;
  }
  return std::nullopt;
}

const std::vector<ModelFormat>& model_formats() {
  static const std::vector<ModelFormat> all = [] {
    std::vector<ModelFormat> v;
    for (const FormatInfo& i : kFormats) v.push_back(i.format);
    return v;
  }();
  return all;
}

std::optional<ModelFormat> model_format_from_path(const std::string& path) {
  if (ends_with(path, ".cameramodel")) return ModelFormat::kMrcal;
  for (const char* e : {".yml", ".yaml", ".json", ".xml"}) {
    if (ends_with(path, e)) return ModelFormat::kOpenCV;
  }
  return std::nullopt;
}

ModelFile read_model_file(const std::string& path) {
  const std::string bytes = read_regular_file(path, kMaxModelFileBytes, "camera model file");
  const ModelFormat format =
      ends_with(path, ".cameramodel") ? ModelFormat::kMrcal : format_of_text(bytes);
  switch (format) {
    case ModelFormat::kOpenCV:
      return model_io::parse_opencv(path, bytes);
    case ModelFormat::kRos:
      return model_io::parse_ros(path, bytes);
    case ModelFormat::kMrcal:
      return model_io::parse_mrcal(path, bytes);
    case ModelFormat::kKalibr:
      return model_io::parse_kalibr(path, bytes);
    case ModelFormat::kHalcon:
      return model_io::parse_halcon(path, bytes);
  }
  throw Error(ErrorCode::kInternal, "unknown model format");
}

CameraModel read_camera_model(const std::string& path) { return read_model_file(path).model; }

void write_camera_model(const std::string& path, const CameraModel& model,
                        const CalibrationFileExtras& extras, std::optional<ModelFormat> format) {
  const std::optional<ModelFormat> by_extension = model_format_from_path(path);
  if (!format && !by_extension) {
    std::string names;
    for (const FormatInfo& i : kFormats) names += std::string(names.empty() ? "" : ", ") + i.name;
    throw Error(ErrorCode::kInvalidArgument,
                "output file '" + path +
                    "': use .yml, .yaml, .json or .xml (OpenCV) or .cameramodel (mrcal), or name "
                    "a format (" +
                    names + ")");
  }
  const ModelFormat f = format.value_or(*by_extension);
  // The reader decides .cameramodel by its name: another format under it would not read back;
  // the other names would, but say what they hold. ROS and Kalibr files are YAML (.yml, .yaml).
  const bool yaml_name = ends_with(path, ".yml") || ends_with(path, ".yaml");
  const bool yaml_format = f == ModelFormat::kRos || f == ModelFormat::kKalibr;
  if (by_extension && f != *by_extension && !(yaml_name && yaml_format)) {
    throw Error(ErrorCode::kInvalidArgument, "output file '" + path + "': the extension is for " +
                                                 model_format_name(*by_extension) + " files, not " +
                                                 model_format_name(f) + " (use " +
                                                 model_format_extension(f) + ")");
  }
  std::string text;
  switch (f) {
    case ModelFormat::kOpenCV:
      text = model_io::compose_opencv(path, model, extras);
      break;
    case ModelFormat::kRos:
      text = model_io::compose_ros(path, model, extras);
      break;
    case ModelFormat::kMrcal:
      text = model_io::compose_mrcal(path, model);
      break;
    case ModelFormat::kKalibr:
      text = model_io::compose_kalibr(path, model);
      break;
    case ModelFormat::kHalcon:
      text = model_io::compose_halcon(path, model);
      break;
  }
  std::string error;
  if (!write_file_atomic(path, text, &error)) throw Error(ErrorCode::kIo, error);
}

}  // namespace posecal
