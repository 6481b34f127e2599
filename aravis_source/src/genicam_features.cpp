#include "genicam_features.hpp"

#include <algorithm>
#include <cctype>
#include <cerrno>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <set>

#include "aravis_util.hpp"
#include "common/error.hpp"

namespace posecal::aravis {

namespace {

std::string format_double(double v) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "%.10g", v);
  return buf;
}

std::string lower(std::string s) {
  for (char& c : s) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
  return s;
}

std::string feature_prefix(const std::string& camera, const std::string& name) {
  return camera + ": feature '" + name + "'";
}

[[noreturn]] void throw_gerror(const GErr& err, const std::string& what) {
  throw Error(err.is_genicam_error() ? ErrorCode::kInvalidArgument : ErrorCode::kDevice,
              what + ": " + err.message());
}

bool parse_int64(const std::string& text, int64_t* out) {
  if (text.empty()) return false;
  const bool hex = text.size() > 2 && text[0] == '0' && (text[1] == 'x' || text[1] == 'X');
  errno = 0;
  char* end = nullptr;
  const long long v = std::strtoll(text.c_str(), &end, hex ? 16 : 10);
  if (errno != 0 || end == text.c_str() || *end != '\0') return false;
  *out = v;
  return true;
}

bool parse_double(const std::string& text, double* out) {
  if (text.empty()) return false;
  errno = 0;
  char* end = nullptr;
  const double v = std::strtod(text.c_str(), &end);
  if (errno != 0 || end == text.c_str() || *end != '\0' || !std::isfinite(v)) return false;
  *out = v;
  return true;
}

// Nodes that are values in their own right (the SFNC's <Integer>, <Float>, ...), as opposed to
// the registers and formulas behind them.
bool is_front_node(ArvGcFeatureNode* node) {
  return ARV_IS_GC_INTEGER_NODE(node) || ARV_IS_GC_FLOAT_NODE(node) || ARV_IS_GC_BOOLEAN(node) ||
         ARV_IS_GC_ENUMERATION(node) || ARV_IS_GC_COMMAND(node) || ARV_IS_GC_STRING(node);
}

bool is_visible(ArvGcFeatureNode* node) {
  return arv_gc_feature_node_get_visibility(node) != ARV_GC_VISIBILITY_INVISIBLE;
}

void walk_category(ArvGc* genicam, const char* name, std::set<std::string>* seen,
                   std::vector<std::string>* out, int depth) {
  if (depth > 32) return;  // a malformed XML could make categories cyclic
  ArvGcNode* node = arv_gc_get_node(genicam, name);
  if (node == nullptr || !ARV_IS_GC_CATEGORY(node)) return;
  for (const GSList* it = arv_gc_category_get_features(ARV_GC_CATEGORY(node)); it != nullptr;
       it = it->next) {
    const char* child_name = static_cast<const char*>(it->data);
    ArvGcNode* child = arv_gc_get_node(genicam, child_name);
    if (child == nullptr) continue;
    if (ARV_IS_GC_CATEGORY(child)) {
      if (seen->insert(std::string("category:") + child_name).second) {
        walk_category(genicam, child_name, seen, out, depth + 1);
      }
    } else if (seen->insert(child_name).second) {
      out->push_back(child_name);
    }
  }
}

}  // namespace

ArvGcFeatureNode* find_feature(ArvDevice* device, const std::string& name) {
  if (name.empty()) return nullptr;
  ArvGcNode* node = arv_device_get_feature(device, name.c_str());
  if (node == nullptr || !ARV_IS_GC_FEATURE_NODE(node)) return nullptr;
  ArvGcFeatureNode* feature = ARV_GC_FEATURE_NODE(node);
  GErr err;
  const gboolean implemented = arv_gc_feature_node_is_implemented(feature, err.out());
  if (!err && !implemented) return nullptr;
  return feature;
}

std::optional<FeatureType> feature_type(ArvGcFeatureNode* node) {
  if (ARV_IS_GC_CATEGORY(node)) return std::nullopt;
  if (ARV_IS_GC_ENUMERATION(node)) return FeatureType::kEnumeration;
  if (ARV_IS_GC_BOOLEAN(node)) return FeatureType::kBoolean;
  if (ARV_IS_GC_COMMAND(node)) return FeatureType::kCommand;
  if (ARV_IS_GC_STRING(node)) return FeatureType::kString;
  if (ARV_IS_GC_FLOAT(node)) return FeatureType::kFloat;
  if (ARV_IS_GC_INTEGER(node)) return FeatureType::kInteger;
  return std::nullopt;
}

std::vector<std::string> enumeration_options(ArvGcFeatureNode* node) {
  std::vector<std::string> out;
  if (!ARV_IS_GC_ENUMERATION(node)) return out;
  GErr err;
  guint n = 0;
  const char** values =
      arv_gc_enumeration_dup_available_string_values(ARV_GC_ENUMERATION(node), &n, err.out());
  if (values == nullptr) return out;
  for (guint i = 0; i < n; ++i) {
    if (values[i] != nullptr && values[i][0] != '\0') out.emplace_back(values[i]);
  }
  g_free(values);  // (transfer container): the strings belong to the node tree
  return out;
}

FeatureInfo describe_feature(ArvGcFeatureNode* node) {
  FeatureInfo info;
  info.name = arv_gc_feature_node_get_name(node);
  info.type = feature_type(node).value_or(FeatureType::kString);
  const ArvGcAccessMode access = arv_gc_feature_node_get_actual_access_mode(node);
  GErr err;
  const gboolean available = arv_gc_feature_node_is_available(node, err.out());
  const bool usable = err || available;
  err.reset();
  const gboolean locked = arv_gc_feature_node_is_locked(node, err.out());
  const bool is_command = info.type == FeatureType::kCommand;
  info.readable =
      usable && !is_command && (access == ARV_GC_ACCESS_MODE_RO || access == ARV_GC_ACCESS_MODE_RW);
  info.writable = usable && !(locked && !err) &&
                  (access == ARV_GC_ACCESS_MODE_WO || access == ARV_GC_ACCESS_MODE_RW);
  if (info.readable) {
    err.reset();
    const char* value = arv_gc_feature_node_get_value_as_string(node, err.out());
    if (!err && value != nullptr) info.value = value;
  }
  if (ARV_IS_GC_FLOAT(node)) {
    ArvGcFloat* f = ARV_GC_FLOAT(node);
    if (const char* unit = arv_gc_float_get_unit(f)) info.unit = unit;
    err.reset();
    const double mn = arv_gc_float_get_min(f, err.out());
    if (!err) info.min = format_double(mn);
    err.reset();
    const double mx = arv_gc_float_get_max(f, err.out());
    if (!err) info.max = format_double(mx);
  } else if (ARV_IS_GC_INTEGER(node) && !ARV_IS_GC_ENUMERATION(node) && !ARV_IS_GC_BOOLEAN(node)) {
    ArvGcInteger* i = ARV_GC_INTEGER(node);
    if (const char* unit = arv_gc_integer_get_unit(i)) info.unit = unit;
    err.reset();
    const gint64 mn = arv_gc_integer_get_min(i, err.out());
    if (!err) info.min = std::to_string(mn);
    err.reset();
    const gint64 mx = arv_gc_integer_get_max(i, err.out());
    if (!err) info.max = std::to_string(mx);
  }
  info.options = enumeration_options(node);
  return info;
}

std::vector<FeatureInfo> list_features(ArvDevice* device) {
  ArvGc* genicam = arv_device_get_genicam(device);
  std::vector<std::string> names;
  std::set<std::string> seen;
  if (genicam == nullptr) return {};
  walk_category(genicam, "Root", &seen, &names, 0);
  // Features no category lists (vendors forget some; the fake camera's AnalogControl is not
  // under Root).
  ArvDomElement* root = arv_dom_document_get_document_element(ARV_DOM_DOCUMENT(genicam));
  for (ArvDomNode* n = root != nullptr ? arv_dom_node_get_first_child(ARV_DOM_NODE(root)) : nullptr;
       n != nullptr; n = arv_dom_node_get_next_sibling(n)) {
    if (!ARV_IS_GC_FEATURE_NODE(n)) continue;
    ArvGcFeatureNode* f = ARV_GC_FEATURE_NODE(n);
    if (!is_front_node(f)) continue;
    const char* name = arv_gc_feature_node_get_name(f);
    if (name != nullptr && seen.insert(name).second) names.emplace_back(name);
  }
  std::vector<FeatureInfo> out;
  for (const std::string& name : names) {
    ArvGcFeatureNode* f = find_feature(device, name);
    if (f == nullptr || !feature_type(f) || !is_visible(f)) continue;
    GErr err;
    const gboolean available = arv_gc_feature_node_is_available(f, err.out());
    if (!err && !available) continue;
    out.push_back(describe_feature(f));
  }
  return out;
}

std::string read_feature(ArvDevice* device, const std::string& camera, const std::string& name) {
  ArvGcFeatureNode* f = find_feature(device, name);
  if (f == nullptr) throw Error(ErrorCode::kNotFound, camera + " has no feature '" + name + "'");
  const std::optional<FeatureType> type = feature_type(f);
  if (!type || *type == FeatureType::kCommand) {
    throw Error(ErrorCode::kInvalidArgument,
                feature_prefix(camera, name) + " has no value (it is a " +
                    (type ? feature_type_name(*type) : "category or register node") + ")");
  }
  if (arv_gc_feature_node_get_actual_access_mode(f) == ARV_GC_ACCESS_MODE_WO) {
    throw Error(ErrorCode::kInvalidArgument, feature_prefix(camera, name) + " is write-only");
  }
  GErr err;
  const char* value = arv_gc_feature_node_get_value_as_string(f, err.out());
  if (err) throw_gerror(err, "reading " + feature_prefix(camera, name) + " failed");
  return value != nullptr ? value : "";
}

namespace {

// A command is executed by "" or "execute".
void write_command(ArvGcFeatureNode* f, const std::string& value, const std::string& bad, GErr* errp) {
  GErr& err = *errp;
  const std::string v = lower(value);
  if (!(v.empty() || v == "execute" || v == "1" || v == "true")) {
    throw Error(ErrorCode::kInvalidArgument, bad + " (a command takes \"\" or \"execute\")");
  }
  arv_gc_command_execute(ARV_GC_COMMAND(f), err.out());
}

// true/false, 1/0 or on/off.
void write_boolean(ArvGcFeatureNode* f, const std::string& value, const std::string& bad, GErr* errp) {
  GErr& err = *errp;
  const std::string v = lower(value);
  bool b;
  if (v == "1" || v == "true" || v == "on") {
    b = true;
  } else if (v == "0" || v == "false" || v == "off") {
    b = false;
  } else {
    throw Error(ErrorCode::kInvalidArgument, bad + " (expected true or false)");
  }
  arv_gc_boolean_set_value(ARV_GC_BOOLEAN(f), b ? TRUE : FALSE, err.out());
}

// One of the entries available now.
void write_enumeration(ArvGcFeatureNode* f, const std::string& value, const std::string& bad, GErr* errp) {
  GErr& err = *errp;
  const std::vector<std::string> options = enumeration_options(f);
  if (std::find(options.begin(), options.end(), value) == options.end()) {
    std::string list;
    for (const auto& o : options) list += (list.empty() ? "" : ", ") + o;
    throw Error(ErrorCode::kInvalidArgument, bad + " (available: " + list + ")");
  }
  arv_gc_enumeration_set_string_value(ARV_GC_ENUMERATION(f), value.c_str(), err.out());
}

// At most the node's maximum length.
void write_string(ArvGcFeatureNode* f, const std::string& value, const std::string& bad, GErr* errp) {
  GErr& err = *errp;
  GErr len_err;
  const gint64 max_length = arv_gc_string_get_max_length(ARV_GC_STRING(f), len_err.out());
  if (!len_err && max_length > 0 && static_cast<gint64>(value.size()) > max_length) {
    throw Error(ErrorCode::kInvalidArgument,
                bad + " (longer than " + std::to_string(max_length) + " characters)");
  }
  arv_gc_string_set_value(ARV_GC_STRING(f), value.c_str(), err.out());
}

// A number in the node's range.
void write_float(ArvGcFeatureNode* f, const std::string& value, const std::string& bad, GErr* errp) {
  GErr& err = *errp;
  double v;
  if (!parse_double(value, &v))
    throw Error(ErrorCode::kInvalidArgument, bad + " (expected a number)");
  ArvGcFloat* fl = ARV_GC_FLOAT(f);
  GErr e1, e2;
  const double mn = arv_gc_float_get_min(fl, e1.out());
  const double mx = arv_gc_float_get_max(fl, e2.out());
  if (!e1 && !e2 && (v < mn || v > mx)) {
    throw Error(ErrorCode::kInvalidArgument,
                bad + " (out of range [" + format_double(mn) + ", " + format_double(mx) + "])");
  }
  arv_gc_float_set_value(fl, v, err.out());
}

// An integer in the node's range, on its increment.
void write_integer(ArvGcFeatureNode* f, const std::string& value, const std::string& bad, GErr* errp) {
  GErr& err = *errp;
  int64_t v;
  if (!parse_int64(value, &v))
    throw Error(ErrorCode::kInvalidArgument, bad + " (expected an integer)");
  ArvGcInteger* in = ARV_GC_INTEGER(f);
  GErr e1, e2, e3;
  const gint64 mn = arv_gc_integer_get_min(in, e1.out());
  const gint64 mx = arv_gc_integer_get_max(in, e2.out());
  const gint64 inc = arv_gc_integer_get_inc(in, e3.out());
  if (!e1 && !e2 && (v < mn || v > mx)) {
    throw Error(ErrorCode::kInvalidArgument,
                bad + " (out of range [" + std::to_string(mn) + ", " + std::to_string(mx) + "])");
  }
  if (!e1 && !e3 && inc > 1 && (v - mn) % inc != 0) {
    throw Error(ErrorCode::kInvalidArgument, bad + " (must be " + std::to_string(mn) +
                                                 " plus a multiple of " + std::to_string(inc) +
                                                 ")");
  }
  arv_gc_integer_set_value(in, v, err.out());

}

}  // namespace

void write_feature(ArvDevice* device, const std::string& camera, const std::string& name,
                   const std::string& value) {
  ArvGcFeatureNode* f = find_feature(device, name);
  if (f == nullptr) throw Error(ErrorCode::kNotFound, camera + " has no feature '" + name + "'");
  const std::string prefix = feature_prefix(camera, name);
  const std::optional<FeatureType> type_or = feature_type(f);
  if (!type_or) {
    throw Error(ErrorCode::kInvalidArgument,
                prefix + " is not a value (category or register node)");
  }
  const FeatureType type = *type_or;
  if (arv_gc_feature_node_get_actual_access_mode(f) == ARV_GC_ACCESS_MODE_RO) {
    throw Error(ErrorCode::kInvalidArgument, prefix + " is read-only");
  }
  GErr err;
  const gboolean available = arv_gc_feature_node_is_available(f, err.out());
  if (!err && !available) {
    throw Error(ErrorCode::kInvalidArgument,
                prefix + " is not available in the camera's current mode");
  }
  err.reset();
  const gboolean locked = arv_gc_feature_node_is_locked(f, err.out());
  if (!err && locked) throw Error(ErrorCode::kInvalidArgument, prefix + " is locked");
  const std::string bad = prefix + ": invalid value '" + value + "'";
  err.reset();
  switch (type) {
    case FeatureType::kCommand: write_command(f, value, bad, &err); break;
    case FeatureType::kBoolean: write_boolean(f, value, bad, &err); break;
    case FeatureType::kEnumeration: write_enumeration(f, value, bad, &err); break;
    case FeatureType::kString: write_string(f, value, bad, &err); break;
    case FeatureType::kFloat: write_float(f, value, bad, &err); break;
    case FeatureType::kInteger: write_integer(f, value, bad, &err); break;
  }
  if (err) throw_gerror(err, "setting " + prefix + " to '" + value + "' failed");
}

}  // namespace posecal::aravis
