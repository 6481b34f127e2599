// The strict parser of the YAML subset ROS and Kalibr files use and of mrcal's Python literal
// (model_file_internal.hpp), and typed access to what it parsed. Recursive descent with the
// depth checked on every level: no input can take it deeper than kMaxModelFileDepth frames, and
// every step consumes input, so it ends.
#include <algorithm>
#include <cctype>
#include <charconv>
#include <cmath>
#include <set>

#include "common/error.hpp"
#include "io/model_file_internal.hpp"

namespace posecal::model_io {

namespace {

bool is_key_char(char c) {
  return std::isalnum(static_cast<unsigned char>(c)) || c == '_' || c == '-' || c == '.' ||
         c == '/';
}

class TreeParser {
 public:
  TreeParser(const std::string& path, std::string_view text, bool python)
      : path_(path), python_(python) {
    if (text.substr(0, 3) == "\xEF\xBB\xBF") text.remove_prefix(3);
    t_.reserve(text.size());
    for (size_t i = 0; i < text.size(); ++i) {
      const char c = text[i];
      const auto u = static_cast<unsigned char>(c);
      if (c == '\r' && i + 1 < text.size() && text[i + 1] == '\n') continue;
      if (c == '\t' && python_) {
        t_.push_back(' ');
        continue;
      }
      if (u < 0x20 && c != '\n') {
        line_cache_pos_ = 0, line_cache_ = 1;
        p_ = t_.size();
        fail(c == '\t' ? "a tab (YAML indents with spaces)" : "a control character");
      }
      t_.push_back(c);
    }
  }

  TextNode yaml_document() {
    int indent = next_content_line();
    if (indent == 0 && at(p_) == '%') {
      if (t_.compare(p_, 5, "%YAML") != 0) fail("a directive other than %YAML");
      next_line();
      indent = next_content_line();
      if (indent != 0 || !document_start(p_)) fail("'---' after the %YAML directive");
    }
    if (indent == 0 && document_start(p_)) {
      next_line();
      indent = next_content_line();
    }
    if (indent < 0) fail("no keys");
    if (indent > 0) fail("the top level is indented");
    if (!map_entry(p_)) fail("the top level is not a map of 'key: value' lines");
    TextNode root = block_map(0, 1, p_);
    if (next_content_line() >= 0) {
      fail(document_start(p_) || t_.compare(p_, 3, "...") == 0 ? "more than one document"
                                                               : "text after the document");
    }
    return root;
  }

  TextNode python_document() {
    skip_flow_space();
    if (at(p_) != '{') fail("not a Python dict (mrcal's .cameramodel starts with '{')");
    TextNode root = flow_value(1);
    skip_flow_space();
    if (p_ < t_.size()) fail("text after the dict's closing '}'");
    return root;
  }

 private:
  [[noreturn]] void fail(const std::string& why) {
    bad_file(path_, std::string(python_ ? "not an mrcal .cameramodel" : "not YAML as read here") +
                        " (line " + std::to_string(line_at(p_)) + ": " + why + ")");
  }
  // Lines are counted incrementally: positions only grow while parsing.
  int line_at(size_t pos) {
    if (pos < line_cache_pos_) line_cache_pos_ = 0, line_cache_ = 1;
    pos = std::min(pos, t_.size());
    line_cache_ += static_cast<int>(std::count(t_.begin() + static_cast<long>(line_cache_pos_),
                                               t_.begin() + static_cast<long>(pos), '\n'));
    line_cache_pos_ = pos;
    return line_cache_;
  }
  void enter(int depth) {
    if (depth > kMaxModelFileDepth) {
      fail("nesting deeper than the limit of " + std::to_string(kMaxModelFileDepth) + " levels");
    }
  }
  char at(size_t i) const { return i < t_.size() ? t_[i] : '\0'; }
  bool line_end(size_t i) const { return at(i) == '\n' || at(i) == '\0'; }
  // A comment starts at '#' at a line's start or after a space (YAML); anywhere in Python.
  bool comment(size_t i) const {
    return at(i) == '#' && (python_ || i == 0 || t_[i - 1] == ' ' || t_[i - 1] == '\n');
  }
  bool document_start(size_t i) const {
    return t_.compare(i, 3, "---") == 0 && (line_end(i + 3) || at(i + 3) == ' ');
  }
  void next_line() {
    while (!line_end(p_)) ++p_;
    if (p_ < t_.size()) ++p_;
  }
  // From a line's start: skips blank and comment lines; p_ at the next content line's start.
  // Returns its indentation, or -1 at the end of the text.
  int next_content_line() {
    while (p_ < t_.size()) {
      size_t i = p_;
      while (at(i) == ' ') ++i;
      if (!line_end(i) && !comment(i)) return static_cast<int>(i - p_);
      p_ = i;
      next_line();
    }
    return -1;
  }
  // The rest of a line after a value: spaces and a comment only; p_ at the next line's start.
  void finish_line() {
    while (at(p_) == ' ') ++p_;
    if (!line_end(p_) && !comment(p_)) fail("text after a value");
    next_line();
  }
  bool seq_entry(size_t i) const { return at(i) == '-' && (at(i + 1) == ' ' || line_end(i + 1)); }
  bool map_entry(size_t i) const {
    size_t j = i;
    while (is_key_char(at(j))) ++j;
    return j > i && at(j) == ':' && (at(j + 1) == ' ' || line_end(j + 1));
  }
  // Adds an entry to a map being parsed; `keys` are its keys so far (a set: a map of many keys
  // must not take quadratic time).
  void add_entry(TextNode* map, std::set<std::string>* keys, std::string key, TextNode value) {
    if (!keys->insert(key).second) fail("key '" + key + "' appears twice");
    map->entries.push_back(TextEntry{std::move(key), std::move(value)});
  }

  // ---- YAML block structure -----------------------------------------------------------------
  TextNode collection(TextNode::Kind kind, int depth, size_t first) {
    enter(depth);
    TextNode node;
    node.kind = kind;
    node.line = line_at(first);
    return node;
  }

  // After an entry of a block collection at `indent`: true with *i at the next entry's start,
  // false when the collection ended (a line indented less, or the text's end).
  bool next_entry(int indent, size_t* i) {
    const int next = next_content_line();
    if (next < indent) return false;
    if (next > indent) fail("unexpected indentation (a value on more than one line?)");
    *i = p_ + static_cast<size_t>(next);
    return true;
  }

  // Entries "key: value" at `indent`, the first one's key at `first`.
  TextNode block_map(int indent, int depth, size_t first) {
    TextNode node = collection(TextNode::Kind::kMap, depth, first);
    std::set<std::string> keys;
    size_t i = first;
    while (true) {
      size_t j = i;
      while (is_key_char(at(j))) ++j;
      std::string key = t_.substr(i, j - i);
      p_ = j + 1;
      TextNode value = block_value(indent, depth + 1, /*map_value=*/true);
      add_entry(&node, &keys, std::move(key), std::move(value));
      if (!next_entry(indent, &i)) break;
      if (indent == 0 && (document_start(i) || t_.compare(i, 3, "...") == 0)) break;
      if (!map_entry(i)) {
        fail(seq_entry(i) ? "a '- ' entry among the keys" : "expected 'key:' (keys are plain)");
      }
    }
    return node;
  }

  // Entries "- value" at `indent`, the first one's '-' at `first`; a line at `indent` that is not
  // an entry ends it (the key after a sequence written at its key's indentation).
  TextNode block_seq(int indent, int depth, size_t first) {
    TextNode node = collection(TextNode::Kind::kSeq, depth, first);
    size_t i = first;
    do {
      p_ = i + 1;
      node.items.push_back(block_value(indent, depth + 1, /*map_value=*/false));
    } while (next_entry(indent, &i) && seq_entry(i));
    return node;
  }

  // The value after "key:" or "- " (p_ just after the ':' or '-'): on this line, or on the
  // following lines when the line ends here. Leaves p_ at the start of the next line.
  TextNode block_value(int parent_indent, int depth, bool map_value) {
    enter(depth);
    while (at(p_) == ' ') ++p_;
    size_t line_start = p_;
    while (line_start > 0 && t_[line_start - 1] != '\n') --line_start;
    if (line_end(p_) || comment(p_)) {
      const int line = line_at(p_);
      next_line();
      const int next = next_content_line();
      if (next > parent_indent) {
        const size_t i = p_ + static_cast<size_t>(next);
        if (seq_entry(i)) return block_seq(next, depth, i);
        if (map_entry(i)) return block_map(next, depth, i);
        fail("expected 'key:' or '- ' (a value on a line of its own?)");
      }
      if (map_value && next == parent_indent && seq_entry(p_ + static_cast<size_t>(next))) {
        return block_seq(next, depth, p_ + static_cast<size_t>(next));
      }
      TextNode empty;
      empty.empty = true;
      empty.line = line;
      return empty;
    }
    const char c = at(p_);
    if (c == '[' || c == '{' || c == '"' || c == '\'') {
      TextNode v = flow_value(depth);
      finish_line();
      return v;
    }
    if (std::string_view("&*!|>?%@`").find(c) != std::string_view::npos) {
      fail(std::string("a value starting with '") + c +
           "' (anchors, aliases, tags, block scalars and complex keys are not read)");
    }
    const int column = static_cast<int>(p_ - line_start);
    if (!map_value && map_entry(p_)) return block_map(column, depth, p_);
    if (!map_value && seq_entry(p_)) return block_seq(column, depth, p_);
    TextNode v;
    v.line = line_at(p_);
    const size_t start = p_;
    while (!line_end(p_) && !comment(p_)) ++p_;
    size_t end = p_;
    while (end > start && t_[end - 1] == ' ') --end;
    v.scalar = t_.substr(start, end - start);
    if (v.scalar.find(": ") != std::string::npos || v.scalar.back() == ':') {
      fail("a ':' inside a plain value (quote it)");
    }
    next_line();
    return v;
  }

  // ---- Flow collections (YAML [..] {..}) and Python literals --------------------------------
  void skip_flow_space() {
    while (true) {
      const char c = at(p_);
      if (c == ' ' || c == '\n') {
        ++p_;
      } else if (comment(p_)) {
        while (!line_end(p_)) ++p_;
      } else {
        return;
      }
    }
  }

  TextNode flow_value(int depth) {
    enter(depth);
    skip_flow_space();
    TextNode node;
    node.line = line_at(p_);
    const char c = at(p_);
    if (c == '\0') fail("the text ends inside a value (truncated?)");
    if (c == '[' || (python_ && c == '(')) {
      node.kind = TextNode::Kind::kSeq;
      const char close = c == '[' ? ']' : ')';
      ++p_;
      while (true) {
        skip_flow_space();
        if (at(p_) == close) break;
        node.items.push_back(flow_value(depth + 1));
        if (!separator(close)) break;
      }
      ++p_;
      return node;
    }
    if (c == '{') {
      node.kind = TextNode::Kind::kMap;
      std::set<std::string> keys;
      ++p_;
      while (true) {
        skip_flow_space();
        if (at(p_) == '}') break;
        std::string key = flow_key();
        skip_flow_space();
        if (at(p_) != ':') fail("expected ':' after the key '" + key + "'");
        ++p_;
        TextNode value = flow_value(depth + 1);
        add_entry(&node, &keys, std::move(key), std::move(value));
        if (!separator('}')) break;
      }
      ++p_;
      return node;
    }
    if (c == '"' || c == '\'' ||
        (python_ && (c == 'b' || c == 'B') && (at(p_ + 1) == '\'' || at(p_ + 1) == '"'))) {
      if (c == 'b' || c == 'B') ++p_;
      node.scalar = quoted();
      node.quoted = true;
      return node;
    }
    const size_t start = p_;
    while (!line_end(p_) && std::string_view(",]})").find(at(p_)) == std::string_view::npos &&
           !comment(p_) && !(python_ && at(p_) == ' ')) {
      ++p_;
    }
    size_t end = p_;
    while (end > start && t_[end - 1] == ' ') --end;
    if (end == start) fail(std::string("expected a value, found '") + at(p_) + "'");
    node.scalar = t_.substr(start, end - start);
    return node;
  }

  // After an element: ',' (true; a trailing one before `close` is allowed) or `close` (false).
  bool separator(char close) {
    skip_flow_space();
    if (at(p_) == ',') {
      ++p_;
      return true;
    }
    if (at(p_) == close) return false;
    if (at(p_) == '\0') fail(std::string("the text ends before '") + close + "' (truncated?)");
    fail(std::string("expected ',' or '") + close + "'");
  }

  std::string flow_key() {
    if (at(p_) == '"' || at(p_) == '\'') return quoted();
    if (python_) fail("a dict key that is not a string");
    const size_t start = p_;
    while (is_key_char(at(p_))) ++p_;
    if (p_ == start) fail("expected a key");
    return t_.substr(start, p_ - start);
  }

  // A quoted string at p_; p_ after its closing quote. Python and YAML double quotes take the
  // common backslash escapes; YAML single quotes double a quote.
  std::string quoted() {
    const char q = at(p_++);
    std::string out;
    while (true) {
      const char c = at(p_);
      if (line_end(p_)) fail("a string runs over the line's end");
      ++p_;
      if (c == q) {
        if (!python_ && q == '\'' && at(p_) == '\'') {
          out.push_back(q);
          ++p_;
          continue;
        }
        return out;
      }
      if (c == '\\' && (python_ || q == '"')) {
        const char e = at(p_++);
        if (e == 'n') {
          out.push_back('\n');
        } else if (e == 't') {
          out.push_back('\t');
        } else if (e == '\\' || e == '\'' || e == '"' || e == '/') {
          out.push_back(e);
        } else {
          fail(std::string("an escape '\\") + e + "' not read here");
        }
        continue;
      }
      out.push_back(c);
    }
  }

  const std::string& path_;
  bool python_;
  std::string t_;
  size_t p_ = 0;
  size_t line_cache_pos_ = 0;
  int line_cache_ = 1;
};

}  // namespace

TextNode parse_yaml_subset(const std::string& path, std::string_view text) {
  return TreeParser(path, text, false).yaml_document();
}

TextNode parse_python_literal(const std::string& path, std::string_view text) {
  return TreeParser(path, text, true).python_document();
}

// ---- Fields ---------------------------------------------------------------------------------

void Fields::fail(const TextNode& n, const std::string& what, const std::string& why) const {
  bad_file(path_, what + " (line " + std::to_string(n.line) + ") " + why);
}

void Fields::only_keys(const TextNode& map, const std::vector<std::string>& known,
                       const std::string& where) const {
  for (const auto& [key, value] : map.entries) {
    if (std::find(known.begin(), known.end(), key) == known.end()) {
      fail(value, "unknown key '" + where + key + "'", "");
    }
  }
}

const TextNode* Fields::find(const TextNode& map, const std::string& key) const {
  for (const auto& [k, v] : map.entries) {
    if (k == key) return &v;
  }
  return nullptr;
}

const TextNode& Fields::need(const TextNode& map, const std::string& key,
                             const std::string& where) const {
  const TextNode* n = find(map, key);
  if (n == nullptr) bad_file(path_, "has no field '" + where + key + "'");
  return *n;
}

double Fields::number(const TextNode& n, const std::string& what) const {
  if (n.kind != TextNode::Kind::kScalar || n.quoted || n.empty) fail(n, what, "is not a number");
  std::string_view s = n.scalar;
  if (!s.empty() && s[0] == '+') s.remove_prefix(1);
  double v = 0;
  const auto [end, ec] = std::from_chars(s.data(), s.data() + s.size(), v);
  if (s.empty() || ec != std::errc() || end != s.data() + s.size()) {
    fail(n, what, "'" + n.scalar + "' is not a number");
  }
  if (!std::isfinite(v)) fail(n, what, "is not finite");
  return v;
}

int Fields::integer(const TextNode& n, const std::string& what, int lo, int hi) const {
  const double v = number(n, what);
  if (!(v >= lo && v <= hi && v == std::floor(v))) {
    fail(n, what,
         "must be an integer within [" + std::to_string(lo) + ", " + std::to_string(hi) + "]");
  }
  return static_cast<int>(v);
}

std::string Fields::string(const TextNode& n, const std::string& what) const {
  if (n.kind != TextNode::Kind::kScalar || n.empty) fail(n, what, "is not a string");
  return n.scalar;
}

std::vector<double> Fields::numbers(const TextNode& n, const std::string& what, size_t count_lo,
                                    size_t count_hi) const {
  if (n.kind != TextNode::Kind::kSeq) fail(n, what, "is not a list of numbers");
  if (n.items.size() < count_lo || n.items.size() > count_hi) {
    fail(n, what,
         "has " + std::to_string(n.items.size()) + " values; expected " +
             (count_lo == count_hi ? std::to_string(count_lo)
                                   : std::to_string(count_lo) + " to " + std::to_string(count_hi)));
  }
  std::vector<double> v;
  for (const TextNode& x : n.items) v.push_back(number(x, what));
  return v;
}

std::string number_text(double v) {
  char buf[32];
  const auto [end, ec] = std::to_chars(buf, buf + sizeof buf, v);  // the shortest that reads back
  return ec == std::errc() ? std::string(buf, end) : std::string("nan");
}

std::string number_list(const std::vector<double>& v) {
  std::string s = "[";
  for (size_t i = 0; i < v.size(); ++i) s += (i ? ", " : "") + number_text(v[i]);
  return s + "]";
}

}  // namespace posecal::model_io
