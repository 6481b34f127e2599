// OpenCV's calibration files: YAML, JSON and XML through cv::FileStorage (model_file.hpp). The
// text is checked before OpenCV's parsers see it: they overflow the stack on deep nesting and
// loop forever on some malformed YAML.
#include <algorithm>
#include <cmath>
#include <opencv2/core/persistence.hpp>
#include <optional>
#include <set>
#include <sstream>
#include <string_view>

#include "common/clock.hpp"
#include "common/error.hpp"
#include "io/model_file_internal.hpp"

namespace posecal::model_io {

namespace {

// The deepest nesting of an OpenCV YAML text, following the structure OpenCV 4.6's recursive
// parser builds (persistence_yml.cpp): block levels (indentation, "- " entries, "key:" chains
// on one line) plus flow levels ([ and {). It accepts only the YAML OpenCV writes and people
// write by hand: a line's first token (a key) does not start with a quote, a bracket or a tag;
// every line outside brackets is a "key:" or a "- " entry; one document; no tabs, control
// characters, multi-line literals or complex keys. Throws bad_file on anything else, or as soon
// as the depth exceeds kMaxModelFileDepth.
class YamlDepth {
 public:
  YamlDepth(const std::string& path, std::string_view text) : path_(path), t_(text) {}

  void run() {
    bool header = true;
    while (p_ < t_.size()) {
      const size_t eol = line_end(p_);
      if (flow_.empty()) {
        block_line(eol, &header);
      } else {
        flow(eol);
      }
      p_ = eol + 1;
    }
    if (!flow_.empty()) fail("unclosed '" + std::string(1, flow_.back()) + "'");
  }

 private:
  [[noreturn]] void fail(const std::string& why) const {
    bad_file(path_, "not OpenCV YAML (line " + std::to_string(line_) + ": " + why + ")");
  }
  size_t line_end(size_t from) {
    ++line_;
    const size_t e = t_.find('\n', from);
    return e == std::string_view::npos ? t_.size() : e;
  }
  char at(size_t i, size_t eol) const { return i < eol ? t_[i] : '\n'; }
  size_t skip_spaces(size_t i, size_t eol) const {
    while (i < eol && t_[i] == ' ') ++i;
    return i;
  }
  void level(int depth) {
    if (depth > kMaxModelFileDepth) {
      fail("nesting deeper than the limit of " + std::to_string(kMaxModelFileDepth) + " levels");
    }
  }
  bool is_end(char c) const { return c == '\n' || c == '#'; }

  // A line outside flow collections.
  void block_line(size_t eol, bool* header) {
    const size_t col = skip_spaces(p_, eol);
    if (is_end(at(col, eol))) return;
    const std::string_view line = t_.substr(p_, eol - p_);
    if (col == p_ && line[0] == '%') {
      if (!*header) fail("a directive after the document's start");
      return;
    }
    if (col == p_ && (line.substr(0, 3) == "---" || line.substr(0, 3) == "...")) {
      if (!*header || line.find_first_not_of(' ', 3) != std::string_view::npos) {
        fail("one document, '---' on a line of its own");
      }
      *header = false;
      return;
    }
    *header = false;
    const int indent = static_cast<int>(col - p_);
    while (!indents_.empty() && indents_.back() > indent) indents_.pop_back();
    if (indents_.empty() || indents_.back() < indent) indents_.push_back(indent);
    const char c = at(col, eol);
    if (c == '"' || c == '\'' || c == '[' || c == '{' || c == '!') {
      fail("a line may not start with " + std::string(1, c) + " (keys are plain)");
    }
    value(col, eol, static_cast<int>(indents_.size()), true);
  }

  // A value (or a key, at a line's start) at position i in block context.
  void value(size_t i, size_t eol, int depth, bool line_start) {
    while (true) {
      level(depth);
      i = skip_spaces(i, eol);
      const char c = at(i, eol), d = at(i + 1, eol);
      if (is_end(c)) return;
      if (c == '-' && !std::isdigit(static_cast<unsigned char>(d)) && d != '.') {
        ++depth, ++i, line_start = false;  // a block sequence entry
        continue;
      }
      if (!line_start && (c == '"' || c == '\'')) {
        i = quoted(i, eol);
        return rest_is_comment(i, eol);
      }
      if (!line_start && (c == '[' || c == '{')) {
        base_ = depth;
        p_ = i + 1;
        open_flow(c);
        return flow(eol);
      }
      if (!line_start && c == '!') {  // a tag, then the value (here or on the next lines)
        while (i < eol && t_[i] != ' ') ++i;
        continue;
      }
      if (c == '?' || c == '|' || c == '>')
        fail("complex keys and multi-line literals are not supported");
      // A plain scalar, or a key: OpenCV's key ends at the line's first ':'.
      const size_t colon = t_.substr(0, eol).find(':', i);
      if (colon == std::string_view::npos) {
        // A line of a bare scalar (a plain value going on over lines, or a stray word): OpenCV
        // never writes one, and OpenCV 4.6's parser loops forever on some (" a: 1", then
        // "bb--", then any line; tests/fuzz/crashes/fuzz_model_file/hang-bare-scalar-line.yml).
        if (line_start) fail("a line with neither 'key:' nor '- ' (a value on a line of its own)");
        return;
      }
      ++depth, i = colon + 1, line_start = false;
    }
  }

  // A quoted string starting at i; returns the position after its closing quote.
  size_t quoted(size_t i, size_t eol) const {
    const char q = t_[i];
    for (++i; i < eol; ++i) {
      if (q == '"' && t_[i] == '\\') {
        ++i;
      } else if (t_[i] == q) {
        if (q == '\'' && at(i + 1, eol) == '\'') {
          ++i;
          continue;
        }
        return i + 1;
      }
    }
    fail("unterminated string");
  }
  void rest_is_comment(size_t i, size_t eol) const {
    i = skip_spaces(i, eol);
    if (!is_end(at(i, eol))) fail("text after a value");
  }

  void open_flow(char c) {
    flow_.push_back(c);
    state_ = kElementOrClose;
    level(base_ + static_cast<int>(flow_.size()));
  }

  // Flow collections from p_ to the line's end (they may go on over lines).
  void flow(size_t eol) {
    size_t i = p_;
    while (!flow_.empty()) {
      i = skip_spaces(i, eol);
      const char c = at(i, eol);
      if (is_end(c)) return;  // a comment or the line's end: the collection goes on
      if (c == ']' || c == '}') {
        if (state_ == kElement && c == '}') fail("',' before '}'");
        if ((c == ']') != (flow_.back() == '[')) fail("mismatched '" + std::string(1, c) + "'");
        flow_.pop_back();
        state_ = kSeparatorOrClose;
        ++i;
        continue;
      }
      if (state_ == kSeparatorOrClose) {
        if (c != ',') fail("expected ',' or a closing bracket");
        state_ = kElement;
        ++i;
        continue;
      }
      i = flow_element(i, eol);
    }
    rest_is_comment(i, eol);
  }

  // One element of the innermost flow collection at i (a key first, in a map).
  size_t flow_element(size_t i, size_t eol) {
    if (flow_.back() == '{') {
      const size_t colon = t_.substr(0, eol).find(':', i);
      if (colon == std::string_view::npos) fail("a flow map's key without ':'");
      i = skip_spaces(colon + 1, eol);
    }
    while (at(i, eol) == '!') {  // a tag
      while (i < eol && t_[i] != ' ') ++i;
      i = skip_spaces(i, eol);
    }
    const char c = at(i, eol);
    if (c == '[' || c == '{') {
      open_flow(c);
      return i + 1;
    }
    state_ = kSeparatorOrClose;
    if (c == '"' || c == '\'') return quoted(i, eol);
    while (i < eol && t_[i] != ',' && t_[i] != ']' && t_[i] != '}') ++i;  // a plain scalar
    return i;
  }

  enum State { kElementOrClose, kElement, kSeparatorOrClose };
  const std::string& path_;
  std::string_view t_;
  size_t p_ = 0;
  int line_ = 0;
  std::vector<int> indents_;
  std::string flow_;  // the open flow collections, '[' or '{'
  int base_ = 0;      // the block depth the flow collections sit in
  State state_ = kElementOrClose;
};

// The deepest bracket nesting of a JSON text (strings and OpenCV's // and /* */ comments
// skipped); throws bad_file beyond kMaxModelFileDepth.
void check_json_depth(const std::string& path, std::string_view t) {
  int depth = 0;
  for (size_t i = 0; i < t.size(); ++i) {
    const char c = t[i];
    if (c == '"') {
      for (++i; i < t.size() && t[i] != '"'; ++i) {
        if (t[i] == '\n') bad_file(path, "not JSON: a string runs over a line's end");
        if (t[i] == '\\') ++i;
      }
    } else if (c == '/' && i + 1 < t.size() && t[i + 1] == '/') {
      i = std::min(t.find('\n', i), t.size());
    } else if (c == '/' && i + 1 < t.size() && t[i + 1] == '*') {
      const size_t e = t.find("*/", i + 2);
      i = e == std::string_view::npos ? t.size() : e + 1;
    } else if (c == '[' || c == '{') {
      if (++depth > kMaxModelFileDepth) {
        bad_file(path, "nesting deeper than the limit of " + std::to_string(kMaxModelFileDepth) +
                           " levels");
      }
    } else if (c == ']' || c == '}') {
      if (--depth < 0) bad_file(path, "not JSON: unbalanced '" + std::string(1, c) + "'");
    }
  }
}

// The XML OpenCV writes (persistence_xml.cpp): the <?xml ...?> declaration, elements with
// quoted attributes, text and comments. Refused before OpenCV's recursive parser sees them: a
// DOCTYPE, entity declarations and CDATA (OpenCV reads none; entity expansion is the classic XML
// bomb), entity references other than the five predefined ones and character references,
// nesting deeper than kMaxModelFileDepth, and an element left open (a file cut short).
void check_xml(const std::string& path, std::string_view t) {
  const auto fail = [&](size_t i, const std::string& why) {
    bad_file(path, "not OpenCV XML (byte " + std::to_string(i) + ": " + why + ")");
  };
  int depth = 0;
  bool root_seen = false;
  for (size_t i = 0; i < t.size(); ++i) {
    if (t[i] == '&') {
      const size_t semi = t.substr(i, 13).find(';');  // a reference is short: no scan to the end
      const std::string_view ref = semi == std::string_view::npos ? "" : t.substr(i + 1, semi - 1);
      const bool numeric = ref.size() > 1 && ref[0] == '#' &&
                           ref.find_first_not_of("0123456789abcdefABCDEFx", 1) == ref.npos;
      if (!(numeric || ref == "lt" || ref == "gt" || ref == "amp" || ref == "quot" ||
            ref == "apos")) {
        fail(i, "an entity reference other than &lt; &gt; &amp; &quot; &apos; or &#N;");
      }
      continue;
    }
    if (t[i] != '<') continue;
    if (t.substr(i, 4) == "<!--") {
      const size_t e = t.find("-->", i + 4);
      if (e == std::string_view::npos) fail(i, "an unterminated comment");
      i = e + 2;
      continue;
    }
    if (t.substr(i, 2) == "<!") fail(i, "a DOCTYPE, entity declaration or CDATA section");
    if (t.substr(i, 2) == "<?") {
      const size_t e = t.find("?>", i);
      if (i != 0 || t.substr(0, 6) != "<?xml " || e == std::string_view::npos) {
        fail(i, "a processing instruction other than a leading <?xml ...?>");
      }
      i = e + 1;
      continue;
    }
    size_t j = i + 1;
    for (char quote = 0; j < t.size(); ++j) {
      if (quote != 0) {
        if (t[j] == quote) quote = 0;
      } else if (t[j] == '"' || t[j] == '\'') {
        quote = t[j];
      } else if (t[j] == '<') {
        fail(j, "'<' inside a tag");
      } else if (t[j] == '>') {
        break;
      }
    }
    if (j >= t.size()) fail(i, "a tag without its '>' (truncated?)");
    if (t[i + 1] == '/') {
      if (--depth < 0) fail(i, "a closing tag without its opening tag");
    } else if (t[j - 1] != '/') {
      if (depth == 0 && root_seen) fail(i, "a second top-level element");
      root_seen = true;
      if (++depth > kMaxModelFileDepth) {
        fail(i,
             "nesting deeper than the limit of " + std::to_string(kMaxModelFileDepth) + " levels");
      }
    }
    i = j;
  }
  if (depth != 0 || !root_seen) fail(t.size(), "an element is not closed (truncated?)");
}

// Checks the text before OpenCV parses it: printable, one of OpenCV's formats (by content, as
// OpenCV decides), nesting within the limit. Returns the text without a UTF-8 byte-order mark.
std::string_view check_text(const std::string& path, std::string_view t) {
  if (t.substr(0, 3) == "\xEF\xBB\xBF") t.remove_prefix(3);
  const bool yaml = t.substr(0, 5) == "%YAML";
  for (size_t i = 0; i < t.size(); ++i) {
    const auto u = static_cast<unsigned char>(t[i]);
    if (u >= 0x20 || t[i] == '\n' || (t[i] == '\r' && i + 1 < t.size() && t[i + 1] == '\n') ||
        (t[i] == '\t' && !yaml)) {
      continue;
    }
    bad_file(path, "control character" + std::string(yaml ? " or tab" : "") + " at byte " +
                       std::to_string(i));
  }
  if (yaml) {
    std::string no_cr(t);
    no_cr.erase(std::remove(no_cr.begin(), no_cr.end(), '\r'), no_cr.end());
    YamlDepth(path, no_cr).run();
  } else if (t.substr(0, 1) == "{") {
    check_json_depth(path, t);
  } else if (t.substr(0, 1) == "<") {
    check_xml(path, t);
  } else {
    bad_file(path,
             "neither OpenCV YAML (first line %YAML:1.0), JSON (starting with '{') nor XML "
             "(starting with '<')");
  }
  return t;
}

}  // namespace

namespace {

// The top-level keys read_camera_model accepts: posecal's own (write_camera_model and the
// extras.strings of its callers) and those of OpenCV's calibration sample
// (samples/cpp/calibration.cpp).
const std::set<std::string>& known_keys() {
  static const std::set<std::string> keys = {
      // posecal
      "calibration_time", "nr_of_frames", "image_width", "image_height", "lens_model",
      "distortion_model", "camera_matrix", "distortion_coefficients", "avg_reprojection_error",
      "intrinsic_names", "std_deviations_intrinsics", "intrinsics_covariance", "held_intrinsics",
      "held_intrinsics_covariance", "expected_error_px", "target", "camera_uri", "camera_id",
      "converged", "interrupted", kModelFileEndKey,
      // OpenCV's calibration sample
      "board_width", "board_height", "square_size", "aspectRatio", "flags", "flagValue",
      "fisheye_model", "per_view_reprojection_errors", "extrinsic_parameters", "image_points",
      "grid_points"};
  return keys;
}

// Unique, known top-level keys; a posecal-written file (one with lens_model) ends with
// kModelFileEndKey: 1.
void check_keys(const std::string& path, const cv::FileNode& root) {
  if (!root.isMap()) bad_file(path, "the top level is not a map of keys");
  std::set<std::string> seen;
  std::string last;
  for (const cv::FileNode& n : root) {
    last = n.name();
    if (!known_keys().count(last)) bad_file(path, "unknown key '" + last + "'");
    if (!seen.insert(last).second) bad_file(path, "key '" + last + "' appears twice");
  }
  if (!seen.count("lens_model")) return;
  const cv::FileNode end = root[kModelFileEndKey];
  if (last != kModelFileEndKey || !end.isInt() || static_cast<int>(end) != 1) {
    bad_file(path, std::string("written by posecal (it has lens_model) but does not end with '") +
                       kModelFileEndKey + ": 1': truncated, or written before posecal checked it");
  }
}

cv::FileNode need(const std::string& path, const cv::FileNode& root, const char* key) {
  const cv::FileNode n = root[key];
  if (n.empty() || n.isNone()) bad_file(path, std::string("has no field '") + key + "'");
  return n;
}

// An OpenCV matrix (rows, cols, dt d or f, data: rows x cols numbers), row-major.
std::vector<double> read_matrix(const std::string& path, const cv::FileNode& n, const char* key,
                                int* rows, int* cols) {
  const std::string what = std::string("'") + key + "' ";
  if (!n.isMap()) bad_file(path, what + "is not an OpenCV matrix (!!opencv-matrix)");
  for (const std::string& k : n.keys()) {
    if (k != "rows" && k != "cols" && k != "dt" && k != "data" && k != "type_id") {
      bad_file(path, what + "has an unknown field '" + k + "'");
    }
  }
  const cv::FileNode r = n["rows"], c = n["cols"], dt = n["dt"], data = n["data"];
  if (!r.isInt() || !c.isInt() || !dt.isString() || !data.isSeq()) {
    bad_file(path, what + "needs integer rows and cols, a dt and a data list");
  }
  if (dt.string() != "d" && dt.string() != "f") {
    bad_file(path, what + "has dt '" + dt.string() + "'; posecal reads dt d or f (floating point)");
  }
  *rows = static_cast<int>(r);
  *cols = static_cast<int>(c);
  // No matrix of a model file is larger than the covariance of the richest lens model.
  constexpr int kMaxSide = kMaxIntrinsics;
  if (*rows < 1 || *cols < 1 || *rows > kMaxSide || *cols > kMaxSide ||
      data.size() != static_cast<size_t>(*rows) * static_cast<size_t>(*cols)) {
    bad_file(path, what + "has " + std::to_string(data.size()) + " data values for " +
                       std::to_string(*rows) + "x" + std::to_string(*cols));
  }
  std::vector<double> v;
  for (const cv::FileNode& x : data) {
    if (!x.isInt() && !x.isReal()) bad_file(path, what + "has a data value that is not a number");
    v.push_back(static_cast<double>(x));
  }
  return v;
}

int read_size(const std::string& path, const cv::FileNode& root, const char* key) {
  const cv::FileNode n = need(path, root, key);
  const double v = n.isInt() || n.isReal() ? static_cast<double>(n) : 0.0;
  if (!(v >= 1 && v <= CameraModel::kMaxImageSide && v == std::floor(v))) {
    bad_file(path, std::string("'") + key + "' must be an integer within the limit [1, " +
                       std::to_string(CameraModel::kMaxImageSide) + "]");
  }
  return static_cast<int>(v);
}

// lens_model (or distortion_model, its name for other tools) names a model of the lens table,
// the one the coefficients give.
void check_lens_model(const std::string& path, const cv::FileNode& n, const std::string& key,
                      LensModel deduced) {
  std::string names;
  for (const LensModel m : lens_models()) {
    names += std::string(names.empty() ? "" : ", ") + lens_model_name(m);
  }
  const std::string value = n.isString() ? n.string() : std::string();
  const std::optional<LensModel> named = lens_model_from_name(value);
  if (!named.has_value()) bad_file(path, "'" + key + "' '" + value + "' is not one of: " + names);
  const LensModel m = named.value_or(deduced);
  if (m != deduced) {
    bad_file(path, "'" + key + "' " + value + " does not match the distortion_coefficients (" +
                       std::to_string(num_distortion_params(deduced)) +
                       " coefficients: " + lens_model_name(deduced) + ")");
  }
}

// A boolean of the file: written as the integer 0 or 1 (cv::FileStorage has no boolean; Python's
// cv2.FileStorage reads a number), read also as the strings "true" / "false" posecal wrote before.
bool read_flag(const std::string& path, const cv::FileNode& n, const char* key) {
  if (n.isInt() && (static_cast<int>(n) == 0 || static_cast<int>(n) == 1)) {
    return static_cast<int>(n) == 1;
  }
  if (n.isString() && (n.string() == "true" || n.string() == "false")) return n.string() == "true";
  bad_file(path, std::string("'") + key + "' must be 0 or 1 (or \"true\" / \"false\")");
}

double read_number(const std::string& path, const cv::FileNode& n, const char* key) {
  if (!n.isInt() && !n.isReal()) bad_file(path, std::string("'") + key + "' is not a number");
  const double v = static_cast<double>(n);
  if (!std::isfinite(v)) bad_file(path, std::string("'") + key + "' is not finite");
  return v;
}

// held_intrinsics: the names, space-separated, of parameters of `model`, each once; none if the
// key is absent.
std::vector<std::string> read_held(const std::string& path, const cv::FileNode& root,
                                   const CameraModel& model) {
  const cv::FileNode f = root["held_intrinsics"];
  if (f.empty()) return {};
  if (!f.isString()) bad_file(path, "'held_intrinsics' is not a string");
  const std::vector<std::string>& names = model.param_names();
  std::vector<std::string> held;
  std::istringstream words(f.string());
  for (std::string w; words >> w;) {
    if (std::find(names.begin(), names.end(), w) == names.end()) {
      bad_file(path, "'held_intrinsics' names '" + w + "', not a parameter of " +
                         lens_model_name(model.lens_model()));
    }
    if (std::find(held.begin(), held.end(), w) != held.end()) {
      bad_file(path, "'held_intrinsics' names '" + w + "' twice");
    }
    held.push_back(w);
  }
  if (held.empty()) bad_file(path, "'held_intrinsics' is empty");
  return held;
}

// What posecal writes besides the model; each key checked where present.
CalibrationFileExtras extras_from(const std::string& path, const cv::FileNode& root,
                                  const CameraModel& model) {
  CalibrationFileExtras x;
  const int n = model.num_params();
  if (const cv::FileNode f = root["nr_of_frames"]; !f.empty()) {
    x.nr_of_frames = static_cast<int>(read_number(path, f, "nr_of_frames"));
  }
  if (const cv::FileNode f = root["avg_reprojection_error"]; !f.empty()) {
    x.avg_reprojection_error = read_number(path, f, "avg_reprojection_error");
  }
  if (const cv::FileNode f = root["expected_error_px"]; !f.empty()) {
    x.expected_error_px = read_number(path, f, "expected_error_px");
  }
  if (const cv::FileNode f = root["std_deviations_intrinsics"]; !f.empty()) {
    int r = 0, c = 0;
    x.param_std = read_matrix(path, f, "std_deviations_intrinsics", &r, &c);
    if (static_cast<int>(x.param_std.size()) != n) {
      bad_file(path, "'std_deviations_intrinsics' has " + std::to_string(x.param_std.size()) +
                         " values for the " + std::to_string(n) + " parameters");
    }
  }
  if (const cv::FileNode f = root["intrinsics_covariance"]; !f.empty()) {
    int r = 0, c = 0;
    x.covariance = read_matrix(path, f, "intrinsics_covariance", &r, &c);
    if (r != n || c != n) {
      bad_file(path, "'intrinsics_covariance' is " + std::to_string(r) + "x" + std::to_string(c) +
                         "; the model has " + std::to_string(n) + " parameters");
    }
  }
  x.held = read_held(path, root, model);
  if (const cv::FileNode f = root["held_intrinsics_covariance"]; !f.empty()) {
    if (x.held.empty()) bad_file(path, "'held_intrinsics_covariance' without 'held_intrinsics'");
    int r = 0, c = 0;
    x.held_covariance = read_matrix(path, f, "held_intrinsics_covariance", &r, &c);
    if (r != n || c != n) {
      bad_file(path, "'held_intrinsics_covariance' is " + std::to_string(r) + "x" +
                         std::to_string(c) + "; the model has " + std::to_string(n) +
                         " parameters");
    }
  } else if (!x.held.empty()) {
    bad_file(path, "'held_intrinsics' without 'held_intrinsics_covariance'");
  }
  if (const cv::FileNode f = root["converged"]; !f.empty()) {
    x.converged = read_flag(path, f, "converged");
  }
  if (const cv::FileNode f = root["interrupted"]; !f.empty()) {
    x.interrupted = read_flag(path, f, "interrupted");
  }
  for (const char* key : {"target", "camera_uri", "camera_id"}) {
    if (const cv::FileNode f = root[key]; !f.empty()) {
      if (!f.isString()) bad_file(path, std::string("'") + key + "' is not a string");
      x.strings.emplace_back(key, f.string());
    }
  }
  return x;
}

ModelFile model_from(const std::string& path, const cv::FileNode& root) {
  check_keys(path, root);
  int kr = 0, kc = 0, dr = 0, dc = 0;
  const std::vector<double> k =
      read_matrix(path, need(path, root, "camera_matrix"), "camera_matrix", &kr, &kc);
  const std::vector<double> d = read_matrix(path, need(path, root, "distortion_coefficients"),
                                            "distortion_coefficients", &dr, &dc);
  const int w = read_size(path, root, "image_width"), h = read_size(path, root, "image_height");
  if (kr != 3 || kc != 3) bad_file(path, "'camera_matrix' is not 3x3");
  if (k[3] != 0 || k[6] != 0 || k[7] != 0 || k[8] != 1) {
    bad_file(path, "'camera_matrix' must be [fx s cx; 0 fy cy; 0 0 1]");
  }
  if (dr != 1 && dc != 1) bad_file(path, "'distortion_coefficients' is not a vector");
  // A fisheye file says so by name (distortion_model or lens_model: fisheye) or, as OpenCV's
  // calibration sample marks its cv::fisheye results, with fisheye_model: 1; its 4 coefficients
  // are then cv::fisheye's k1..k4, not the pinhole model's k1 k2 p1 p2.
  const char* fisheye_name = lens_model_name(LensModel::kFisheye);
  bool fisheye = false;
  for (const char* key : {"lens_model", "distortion_model"}) {
    const cv::FileNode f = root[key];
    fisheye = fisheye || (!f.empty() && f.isString() && f.string() == fisheye_name);
  }
  if (const cv::FileNode f = root["fisheye_model"]; !f.empty()) {
    if (!f.isInt() && !f.isReal()) bad_file(path, "'fisheye_model' must be 0 or 1");
    fisheye = fisheye || static_cast<double>(f) != 0;
  }
  ModelFile file;
  try {
    file.model = fisheye ? CameraModel::from_opencv_fisheye(w, h, cv::Matx33d(k.data()), d)
                         : CameraModel::from_opencv(w, h, cv::Matx33d(k.data()), d);
  } catch (const Error& e) {
    throw Error(e.code(), "camera model file '" + path + "': " + e.what());
  }
  for (const char* key : {"lens_model", "distortion_model"}) {
    if (!root[key].empty()) check_lens_model(path, root[key], key, file.model.lens_model());
  }
  std::string why;
  if (!file.model.is_valid(&why)) bad_file(path, why);
  file.extras = extras_from(path, root, file.model);
  return file;
}

cv::Mat row_matrix(const std::vector<double>& v, int rows) {
  return cv::Mat(rows, static_cast<int>(v.size()) / rows, CV_64F, const_cast<double*>(v.data()));
}

}  // namespace

ModelFile parse_opencv(const std::string& path, std::string_view bytes) {
  const std::string_view text = check_text(path, bytes);
  try {
    const cv::FileStorage fs(std::string(text), cv::FileStorage::READ | cv::FileStorage::MEMORY);
    if (!fs.isOpened()) bad_file(path, "OpenCV cannot read it");
    ModelFile file = model_from(path, fs.root());
    file.format = ModelFormat::kOpenCV;
    return file;
  } catch (const cv::Exception& e) {
    bad_file(path, "not valid OpenCV YAML/JSON/XML: " + e.msg);
  } catch (const Error&) {
    throw;
  } catch (const std::exception& e) {
    // OpenCV's parser also lets std::length_error and the like through on malformed text
    // (tests/fuzz/crashes/fuzz_model_file/length-error-escapes.yml).
    bad_file(path, std::string("not valid OpenCV YAML/JSON/XML: ") + e.what());
  }
}

namespace {

std::string space_separated(const std::vector<std::string>& words) {
  std::string out;
  for (const std::string& w : words) out += (out.empty() ? "" : " ") + w;
  return out;
}

}  // namespace

std::string compose_opencv(const std::string& path, const CameraModel& model,
                           const CalibrationFileExtras& extras) {
  const auto ends_with = [&](std::string_view e) {
    return path.size() >= e.size() && path.compare(path.size() - e.size(), e.size(), e) == 0;
  };
  const int format = ends_with(".json")  ? cv::FileStorage::FORMAT_JSON
                     : ends_with(".xml") ? cv::FileStorage::FORMAT_XML
                                         : cv::FileStorage::FORMAT_YAML;
  const int n = model.num_params();
  if ((!extras.param_std.empty() && static_cast<int>(extras.param_std.size()) != n) ||
      (!extras.covariance.empty() && static_cast<int>(extras.covariance.size()) != n * n) ||
      (!extras.held.empty() && static_cast<int>(extras.held_covariance.size()) != n * n)) {
    throw Error(ErrorCode::kInternal,
                "cannot compose '" + path + "': std or covariance sized for another model");
  }
  cv::FileStorage fs;
  try {
    fs.open("", cv::FileStorage::WRITE | cv::FileStorage::MEMORY | format);
  } catch (const cv::Exception& e) {
    throw Error(ErrorCode::kInternal, "cannot compose calibration file '" + path + "': " + e.msg);
  }
  fs << "calibration_time" << utc_now_iso8601();
  if (extras.nr_of_frames >= 0) fs << "nr_of_frames" << extras.nr_of_frames;
  fs << "image_width" << model.width();
  fs << "image_height" << model.height();
  fs << "lens_model" << std::string(lens_model_name(model.lens_model()));
  fs << "distortion_model" << std::string(lens_model_name(model.lens_model()));
  fs << "camera_matrix" << cv::Mat(model.camera_matrix());
  fs << "distortion_coefficients" << row_matrix(model.distortion_coefficients(), 1);
  if (extras.avg_reprojection_error >= 0) {
    fs << "avg_reprojection_error" << extras.avg_reprojection_error;
  }
  if (!extras.param_std.empty()) {
    fs << "intrinsic_names" << space_separated(model.param_names());
    fs << "std_deviations_intrinsics" << row_matrix(extras.param_std, 1);
  }
  if (!extras.covariance.empty()) {
    fs << "intrinsics_covariance" << row_matrix(extras.covariance, n);
  }
  if (!extras.held.empty()) {
    fs << "held_intrinsics" << space_separated(extras.held);
    fs << "held_intrinsics_covariance" << row_matrix(extras.held_covariance, n);
  }
  if (extras.expected_error_px >= 0) fs << "expected_error_px" << extras.expected_error_px;
  if (extras.converged) fs << "converged" << (*extras.converged ? 1 : 0);
  if (extras.interrupted) fs << "interrupted" << (*extras.interrupted ? 1 : 0);
  for (const auto& [key, value] : extras.strings) fs << key << value;
  fs << kModelFileEndKey << 1;  // the last key: the reader refuses a file cut short
  return fs.releaseAndGetString();
}

}  // namespace posecal::model_io
