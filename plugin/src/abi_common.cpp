#include "abi_common.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstring>

namespace posecal::abi {

namespace {
thread_local std::string t_last_error;

[[noreturn]] void bad_option(const char* what, const char* key, const std::string& expected) {
  throw Error(ErrorCode::kInvalidArgument,
              std::string(what) + ": '" + key + "' must be " + expected);
}

std::string range_text(double lo, double hi) {
  char buf[64];
  std::snprintf(buf, sizeof buf, "[%g, %g]", lo, hi);
  return buf;
}
}  // namespace

void set_error(const std::string& message) { t_last_error = message; }
void clear_error() { t_last_error.clear(); }
const char* last_error() { return t_last_error.c_str(); }

posecal_status status_of(ErrorCode code) {
  switch (code) {
    case ErrorCode::kInvalidArgument:
      return POSECAL_E_INVALID_ARGUMENT;
    case ErrorCode::kNotFound:
      return POSECAL_E_NOT_FOUND;
    case ErrorCode::kBufferTooSmall:
      return POSECAL_E_BUFFER_TOO_SMALL;
    case ErrorCode::kTimeout:
      return POSECAL_E_TIMEOUT;
    case ErrorCode::kDevice:
      return POSECAL_E_DEVICE;
    case ErrorCode::kState:
      return POSECAL_E_STATE;
    case ErrorCode::kIo:
      return POSECAL_E_IO;
    case ErrorCode::kInternal:
      return POSECAL_E_INTERNAL;
    case ErrorCode::kDegenerate:
      return POSECAL_E_DEGENERATE;
    case ErrorCode::kUnsupported:
      return POSECAL_E_UNSUPPORTED;
  }
  return POSECAL_E_INTERNAL;
}

void require(const void* p, const char* name) {
  if (p == nullptr) throw Error(ErrorCode::kInvalidArgument, std::string(name) + " is NULL");
}

posecal_status copy_out(const std::string& text, char* buf, size_t* size) {
  require(size, "size");
  const size_t needed = text.size() + 1;
  if (buf == nullptr || *size < needed) {
    const size_t given = *size;
    *size = needed;
    set_error("buffer too small: " + std::to_string(needed) + " bytes needed, " +
              (buf == nullptr ? std::string("buffer is NULL") : std::to_string(given) + " given"));
    return POSECAL_E_BUFFER_TOO_SMALL;
  }
  std::memcpy(buf, text.c_str(), needed);
  *size = needed;
  return POSECAL_OK;
}

nlohmann::json parse_options(const char* json_text, const std::vector<std::string>& allowed,
                             const char* what) {
  if (json_text == nullptr || json_text[0] == '\0') return nlohmann::json::object();
  nlohmann::json j;
  try {
    j = nlohmann::json::parse(json_text);
  } catch (const nlohmann::json::parse_error& e) {
    throw Error(ErrorCode::kInvalidArgument, std::string(what) + " is not valid JSON: " + e.what());
  }
  if (!j.is_object())
    throw Error(ErrorCode::kInvalidArgument, std::string(what) + " must be a JSON object");
  for (const auto& item : j.items()) {
    if (std::find(allowed.begin(), allowed.end(), item.key()) == allowed.end()) {
      std::string list;
      for (const auto& a : allowed) list += (list.empty() ? "" : ", ") + a;
      throw Error(ErrorCode::kInvalidArgument,
                  std::string(what) + ": unknown key '" + item.key() + "' (known: " + list + ")");
    }
  }
  return j;
}

bool get_bool(const nlohmann::json& j, const char* key, bool def, const char* what) {
  if (!j.contains(key)) return def;
  const auto& v = j.at(key);
  if (!v.is_boolean()) bad_option(what, key, "true or false");
  return v.get<bool>();
}

int get_int(const nlohmann::json& j, const char* key, int def, int lo, int hi, const char* what) {
  if (!j.contains(key)) return def;
  const auto& v = j.at(key);
  const std::string expected = "an integer in " + range_text(lo, hi);
  if (!v.is_number_integer()) bad_option(what, key, expected);
  const long long x = v.get<long long>();
  if (x < lo || x > hi) bad_option(what, key, expected);
  return static_cast<int>(x);
}

double get_double(const nlohmann::json& j, const char* key, double def, double lo, double hi,
                  const char* what) {
  if (!j.contains(key)) return def;
  const auto& v = j.at(key);
  const std::string expected = "a number in " + range_text(lo, hi);
  if (!v.is_number()) bad_option(what, key, expected);
  const double x = v.get<double>();
  if (!(x >= lo && x <= hi)) bad_option(what, key, expected);
  return x;
}

std::string get_string(const nlohmann::json& j, const char* key, const std::string& def,
                       const char* what) {
  if (!j.contains(key)) return def;
  const auto& v = j.at(key);
  if (!v.is_string()) bad_option(what, key, "a string");
  return v.get<std::string>();
}

std::vector<std::string> get_strings(const nlohmann::json& j, const char* key, const char* what) {
  std::vector<std::string> out;
  if (!j.contains(key)) return out;
  const auto& v = j.at(key);
  if (!v.is_array()) bad_option(what, key, "an array of strings");
  for (const auto& e : v) {
    if (!e.is_string()) bad_option(what, key, "an array of strings");
    out.push_back(e.get<std::string>());
  }
  return out;
}

std::string to_text(const nlohmann::json& j) {
  return j.dump(-1, ' ', false, nlohmann::json::error_handler_t::replace);
}

nlohmann::json number(double v) {
  return std::isfinite(v) ? nlohmann::json(v) : nlohmann::json(nullptr);
}

}  // namespace posecal::abi
