// libFuzzer target: the session config JSON of posecal_session_open (plugin/src/session_config.cpp
// through the C ABI, as a host passes it), and the context options JSON of posecal_context_create.
//
// The input is the JSON text (up to its first NUL byte, as a C host would pass it). Fails on a
// crash, a sanitizer report, or an ABI contract breach: POSECAL_E_INTERNAL (by posecal.h a bug),
// a session handed out on failure, or a failure without a message.
#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <string>
#include <vector>

#include "posecal.h"

namespace {

posecal_context* external_context() {
  static posecal_context* const ctx = [] {
    posecal_context* c = nullptr;
    if (posecal_context_create("{\"backends\": [\"external\"]}", &c) != POSECAL_OK) std::abort();
    return c;
  }();
  return ctx;
}

void check_failure(posecal_status st) {
  if (st == POSECAL_E_INTERNAL) std::abort();
  if (st != POSECAL_OK && std::strlen(posecal_last_error()) == 0) std::abort();
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string text(reinterpret_cast<const char*>(data), size);

  posecal_session* s = nullptr;
  const posecal_status st = posecal_session_open(external_context(), "external", text.c_str(), &s);
  check_failure(st);
  if (st == POSECAL_OK) {
    if (s == nullptr) std::abort();
    std::vector<char> buf(1 << 16);
    size_t n = buf.size();
    if (posecal_session_status(s, buf.data(), &n) != POSECAL_OK) std::abort();
    posecal_session_close(s);
  } else if (s != nullptr) {
    std::abort();
  }

  // The same text as context options (keys "backends"); only the built-in, hardware-free
  // backends are ever enabled by a valid input of the corpus, and creating a context does not
  // touch hardware (posecal.h).
  posecal_context* ctx = nullptr;
  const posecal_status cs = posecal_context_create(text.c_str(), &ctx);
  check_failure(cs);
  if (cs == POSECAL_OK) {
    if (ctx == nullptr) std::abort();
    posecal_context_destroy(ctx);
  } else if (ctx != nullptr) {
    std::abort();
  }
  return 0;
}
