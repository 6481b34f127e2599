// libFuzzer target: camera URIs (core/device/uri.cpp), the sim:// options (core/sim/sim_camera.cpp)
// and the one percent-encoder (core/common/percent_encoding.cpp).
//
// Properties checked besides "no crash, no sanitizer report, only posecal::Error thrown":
//  - percent_decode(percent_encode(x)) == x for any bytes, and the encoding holds only the
//    characters percent_encoding.hpp promises;
//  - a parsed URI built again with percent_encode (path, and query values of keys without '=')
//    parses to the same scheme, path and query (the backends build their URIs that way).
#include <unistd.h>

#include <cctype>
#include <cstddef>
#include <cstdint>
#include <cstdio>
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

// sim://?model=FILE reads a file of the machine (the model-file target fuzzes that reader): the
// value is replaced by this valid model, which also spares the sampling of a random camera (tens
// of milliseconds under the sanitizers) that a URI without a model costs.
const std::string& model_path() {
  static const std::string path = [] {
    const char* dir = std::getenv("TMPDIR");
    const std::string p = std::string(dir && *dir ? dir : "/tmp") + "/posecal_fuzz_uri_" +
                          std::to_string(::getpid()) + ".yml";
    FILE* f = std::fopen(p.c_str(), "w");
    if (f == nullptr) std::abort();
    std::fputs(
        "%YAML:1.0\n---\nimage_width: 640\nimage_height: 480\n"
        "camera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n"
        "   data: [ 610., 0., 322., 0., 612., 238.5, 0., 0., 1. ]\n"
        "distortion_coefficients: !!opencv-matrix\n   rows: 1\n   cols: 5\n   dt: d\n"
        "   data: [ 0.12, -0.25, 0.001, -0.0015, 0.1 ]\n",
        f);
    std::fclose(f);
    std::atexit([] { std::remove(model_path().c_str()); });
    return p;
  }();
  return path;
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
      u.query["model"] = model_path();
      (void)posecal::sim_options_from_uri(u, posecal::BoardSpec{});
    }
  } catch (const posecal::Error&) {
  }
  return 0;
}
