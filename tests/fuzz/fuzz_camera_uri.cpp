// libFuzzer target: camera URIs (core/device/uri.cpp), the sim:// options (core/sim/sim_camera.cpp)
// and the one percent-encoder (core/common/percent_encoding.cpp).
//
// Properties checked besides "no crash, no sanitizer report, only posecal::Error thrown":
//  - percent_decode(percent_encode(x)) == x for any bytes, and the encoding holds only the
//    characters percent_encoding.hpp promises;
//  - a parsed URI built again with percent_encode (path, and query values of keys without '=')
//    parses to the same scheme, path and query (the backends build their URIs that way).
#include <cctype>
#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <string>

#include "board/board.hpp"
#include "common/error.hpp"
#include "common/percent_encoding.hpp"
#include "device/camera.hpp"
#include "sim/sim_camera.hpp"

namespace {

void check_percent_round_trip(const std::string& text) {
  const std::string enc = posecal::percent_encode(text);
  for (char c : enc) {
    if (!std::isalnum(static_cast<unsigned char>(c)) && std::strchr("-._~:@+,=/%", c) == nullptr) {
      std::abort();
    }
  }
  const auto dec = posecal::percent_decode(enc);
  if (!dec || *dec != text) std::abort();
}

void check_uri_round_trip(const posecal::Uri& u) {
  if (u.text.find("://") == std::string::npos) return;  // scheme-only ("external")
  std::string text = u.scheme + "://" + posecal::percent_encode(u.path);
  char sep = '?';
  for (const auto& [k, v] : u.query) {
    if (k.find('=') != std::string::npos) return;  // percent_encode keeps '=' (a value's rule)
    text += sep + posecal::percent_encode(k) + "=" + posecal::percent_encode(v);
    sep = '&';
  }
  const posecal::Uri again = posecal::Uri::parse(text);  // must not throw
  if (again.scheme != u.scheme || again.path != u.path || again.query != u.query) std::abort();
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string text(reinterpret_cast<const char*>(data), size);
  check_percent_round_trip(text);
  (void)posecal::percent_decode(text);
  try {
    posecal::Uri u = posecal::Uri::parse(text);
    check_uri_round_trip(u);
    if (u.scheme == "sim") {
      // model=FILE reads a file of the machine: the model-file target fuzzes that reader.
      u.query.erase("model");
      (void)posecal::sim_options_from_uri(u, posecal::BoardSpec{});
    }
  } catch (const posecal::Error&) {
  }
  return 0;
}
