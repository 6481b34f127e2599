// Internal helpers of the C ABI: the one place that turns C++ exceptions into statuses, the
// per-thread error message, the JSON buffer protocol and typed access to JSON options.
#pragma once

#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "posecal.h"
#include "common/error.hpp"

namespace posecal::abi {

void set_error(const std::string& message);
void clear_error();
const char* last_error();
posecal_status status_of(ErrorCode code);

// Runs `body` and converts every exception into a status plus a per-thread message. Every
// exported function goes through this (ONNX Runtime's API_IMPL_BEGIN/END, as one helper).
// A body that returns a failure status itself has set the message already (copy_out does).
template <class Body>
posecal_status guarded(const char* function, Body&& body) noexcept {
  try {
    const posecal_status s = body();
    if (s == POSECAL_OK) clear_error();
    return s;
  } catch (const Error& e) {
    set_error(std::string(function) + ": " + e.what());
    return status_of(e.code());
  } catch (const nlohmann::json::exception& e) {
    set_error(std::string(function) + ": malformed JSON: " + e.what());
    return POSECAL_E_INVALID_ARGUMENT;
  } catch (const std::bad_alloc&) {
    set_error(std::string(function) + ": out of memory");
    return POSECAL_E_INTERNAL;
  } catch (const std::exception& e) {
    set_error(std::string(function) + ": internal error: " + e.what());
    return POSECAL_E_INTERNAL;
  } catch (...) {
    set_error(std::string(function) + ": internal error: unknown exception");
    return POSECAL_E_INTERNAL;
  }
}

// For the void functions (destroy/close): same conversion, the status is dropped but the
// message stays readable through posecal_last_error().
template <class Body>
void guarded_void(const char* function, Body&& body) noexcept {
  (void)guarded(function, [&] {
    body();
    return POSECAL_OK;
  });
}

// Fails with POSECAL_E_INVALID_ARGUMENT naming the argument if p is NULL.
void require(const void* p, const char* name);

// JSON buffer protocol: *size = capacity on entry; needed length (incl. NUL) on return. A NULL
// or too small buffer gives POSECAL_E_BUFFER_TOO_SMALL with *size set and the buffer untouched.
posecal_status copy_out(const std::string& text, char* buf, size_t* size);

// Parses a JSON object (NULL or "" = empty object); throws Error(kInvalidArgument) if it is not
// an object or has a key outside `allowed`.
nlohmann::json parse_options(const char* json_text, const std::vector<std::string>& allowed,
                             const char* what);

// Typed, range-checked access to an option of a parsed object: the default when the key is
// absent, Error(kInvalidArgument) naming `what` and the key for a wrong type or range.
bool get_bool(const nlohmann::json& j, const char* key, bool def, const char* what);
int get_int(const nlohmann::json& j, const char* key, int def, int lo, int hi, const char* what);
double get_double(const nlohmann::json& j, const char* key, double def, double lo, double hi,
                  const char* what);
std::string get_string(const nlohmann::json& j, const char* key, const std::string& def,
                       const char* what);
// An array of strings (absent: empty).
std::vector<std::string> get_strings(const nlohmann::json& j, const char* key, const char* what);

// Compact JSON text; invalid UTF-8 (a device name, a path) is replaced by U+FFFD rather than
// failing the call.
std::string to_text(const nlohmann::json& j);

// A JSON number, or null for NaN/Inf (JSON has neither; never a valid-looking value).
nlohmann::json number(double v);

}  // namespace posecal::abi
