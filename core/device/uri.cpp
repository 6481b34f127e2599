#include <cctype>

#include "common/error.hpp"
#include "common/percent_encoding.hpp"
#include "device/camera.hpp"

namespace posecal {

namespace {

std::string decode(const std::string& in, const std::string& uri) {
  std::optional<std::string> out = percent_decode(in);
  if (!out) throw Error(ErrorCode::kInvalidArgument, "camera URI '" + uri + "': bad percent escape");
  return *out;
}

}  // namespace

Uri Uri::parse(const std::string& text) {
  Uri u;
  u.text = text;
  if (text.empty()) throw Error(ErrorCode::kInvalidArgument, "camera URI is empty");
  for (char c : text) {
    if (static_cast<unsigned char>(c) < 0x20) {
      throw Error(ErrorCode::kInvalidArgument, "camera URI contains a control character");
    }
  }
  const size_t sep = text.find("://");
  std::string rest;
  if (sep == std::string::npos) {
    // Scheme-only URIs ("external").
    if (text.find_first_of(":/?") != std::string::npos) {
      throw Error(ErrorCode::kInvalidArgument,
                  "camera URI '" + text + "' is malformed (expected scheme://...)");
    }
    u.scheme = text;
    return u;
  }
  u.scheme = text.substr(0, sep);
  if (u.scheme.empty())
    throw Error(ErrorCode::kInvalidArgument, "camera URI '" + text + "' has no scheme");
  for (char c : u.scheme) {
    if (!std::isalnum(static_cast<unsigned char>(c)) && c != '+' && c != '-' && c != '.') {
      throw Error(ErrorCode::kInvalidArgument, "camera URI '" + text + "' has an invalid scheme");
    }
  }
  rest = text.substr(sep + 3);
  const size_t q = rest.find('?');
  u.path = decode(rest.substr(0, q), text);
  if (q != std::string::npos) {
    std::string query = rest.substr(q + 1);
    size_t start = 0;
    while (start <= query.size()) {
      size_t amp = query.find('&', start);
      if (amp == std::string::npos) amp = query.size();
      const std::string pair = query.substr(start, amp - start);
      if (!pair.empty()) {
        const size_t eq = pair.find('=');
        const std::string key = decode(pair.substr(0, eq), text);
        const std::string value =
            eq == std::string::npos ? "" : decode(pair.substr(eq + 1), text);
        if (key.empty())
          throw Error(ErrorCode::kInvalidArgument,
                      "camera URI '" + text + "' has an empty query key");
        if (u.query.count(key)) {
          throw Error(ErrorCode::kInvalidArgument,
                      "camera URI '" + text + "' repeats '" + key + "'");
        }
        u.query[key] = value;
      }
      start = amp + 1;
    }
  }
  return u;
}

}  // namespace posecal
