// What the camera-model file formats of core/io/ share: the error naming the file, each format's
// reader and writer (one .cpp per format), and the small strict parser for the YAML that ROS and
// Kalibr write and the Python literal that mrcal writes (text_tree.cpp).
#pragma once

#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "io/model_file.hpp"

namespace posecal::model_io {

// Error(kInvalidArgument) "camera model file 'PATH': WHY".
[[noreturn]] void bad_file(const std::string& path, const std::string& why);

// ---- The formats: each composes the whole text (written atomically by the caller) and reads a
// ---- text already read within kMaxModelFileBytes. `path` is for messages.
std::string compose_opencv(const std::string& path, const CameraModel& model,
                           const CalibrationFileExtras& extras);
ModelFile parse_opencv(const std::string& path, std::string_view text);
std::string compose_ros(const std::string& path, const CameraModel& model,
                        const CalibrationFileExtras& extras);
ModelFile parse_ros(const std::string& path, std::string_view text);
std::string compose_mrcal(const std::string& path, const CameraModel& model);
ModelFile parse_mrcal(const std::string& path, std::string_view text);
std::string compose_kalibr(const std::string& path, const CameraModel& model);
ModelFile parse_kalibr(const std::string& path, std::string_view text);
std::string compose_halcon(const std::string& path, const CameraModel& model);
ModelFile parse_halcon(const std::string& path, std::string_view text);

// Error(kInvalidArgument) for a model a format cannot hold: names the file, the format and the
// model.
[[noreturn]] void cannot_hold(const std::string& path, ModelFormat format, const CameraModel& model,
                              const std::string& why);

// ---- A parsed tree of the YAML subset / Python literal --------------------------------------
struct TextEntry;
struct TextNode {
  enum class Kind { kScalar, kSeq, kMap };
  Kind kind = Kind::kScalar;
  std::string scalar;           // a scalar's text, quotes removed
  bool quoted = false;          // a quoted string (never a number)
  bool empty = false;           // "key:" with nothing after it (YAML's null)
  int line = 0;                 // where it starts (1-based)
  std::vector<TextNode> items;  // kSeq
  // kMap, in file order, keys unique. (Not std::pair<std::string, TextNode>: a pair of the
  // incomplete TextNode instantiated inside this class fails with clang and libstdc++.)
  std::vector<TextEntry> entries;
};
// One key of a map; first/second as in a pair, so structured bindings read [key, value].
struct TextEntry {
  std::string first;
  TextNode second;
};

// YAML as camera_calibration, yaml-cpp and Kalibr write it: block maps and sequences by
// indentation (spaces), flow sequences and maps that may go on over lines, plain and quoted
// scalars, '#' comments, an optional leading '%YAML' directive and '---'. Refused (not written
// by these tools): tabs and control characters, anchors, aliases, tags, multi-line and block
// scalars, complex keys, more than one document, keys other than [A-Za-z0-9_.-/]+, nesting
// deeper than kMaxModelFileDepth. Throws bad_file naming the line.
TextNode parse_yaml_subset(const std::string& path, std::string_view text);
// A Python literal as mrcal writes a .cameramodel: one dict of string keys; lists, tuples,
// strings, bytes, numbers, True/False/None; '#' comments. Same limits.
TextNode parse_python_literal(const std::string& path, std::string_view text);

// Typed access to parsed nodes; every failure is bad_file naming `what` (a key path such as
// "'cam0.intrinsics'") and the line.
class Fields {
 public:
  explicit Fields(const std::string& path) : path_(path) {}
  [[noreturn]] void fail(const TextNode& n, const std::string& what, const std::string& why) const;
  // The map's keys are all in `known` (else "unknown key 'K'").
  void only_keys(const TextNode& map, const std::vector<std::string>& known,
                 const std::string& where) const;
  const TextNode* find(const TextNode& map, const std::string& key) const;
  const TextNode& need(const TextNode& map, const std::string& key, const std::string& where) const;
  double number(const TextNode& n, const std::string& what) const;  // finite
  int integer(const TextNode& n, const std::string& what, int lo, int hi) const;
  std::string string(const TextNode& n, const std::string& what) const;
  // A sequence of numbers; count_lo..count_hi elements.
  std::vector<double> numbers(const TextNode& n, const std::string& what, size_t count_lo,
                              size_t count_hi) const;
  const std::string& path() const { return path_; }

 private:
  const std::string& path_;
};

// A double as the shortest text that reads back to the same double.
std::string number_text(double v);
// "[a, b, c]" of number_text.
std::string number_list(const std::vector<double>& v);

// Builds the model from OpenCV's K (row-major, [fx 0 cx; 0 fy cy; 0 0 1]) and distortion vector
// and checks it; errors name the file and `what` (the key that held the coefficients).
CameraModel model_from_opencv(const std::string& path, int width, int height,
                              const std::vector<double>& K9, const std::vector<double>& dist,
                              const std::string& what);
// The same for cv::fisheye's K and k1..k4: the fisheye model.
CameraModel model_from_opencv_fisheye(const std::string& path, int width, int height,
                                      const std::vector<double>& K9,
                                      const std::vector<double>& dist, const std::string& what);

}  // namespace posecal::model_io
