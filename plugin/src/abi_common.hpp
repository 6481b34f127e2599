// Internal helpers of the C ABI: the one place that turns C++ exceptions into statuses, the
// per-thread error message, and the JSON buffer protocol.
#pragma once

#include <nlohmann/json.hpp>
#include <string>

#include "posecal.h"
#include "posecal/error.hpp"

namespace posecal::abi {

void set_error(const std::string& message);
void clear_error();
posecal_status status_of(ErrorCode code);

// Runs `body` and converts every exception into a status plus a per-thread message. Every
// exported function goes through this (ONNX Runtime's API_IMPL_BEGIN/END, as one helper).
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

// Fails with POSECAL_E_INVALID_ARGUMENT naming the argument if p is NULL.
void require(const void* p, const char* name);

// JSON buffer protocol: *size = capacity on entry; needed length (incl. NUL) on return.
posecal_status copy_out(const std::string& text, char* buf, size_t* size);

// Parses a JSON object (NULL or "" = empty object); throws Error(kInvalidArgument) if it is not
// an object or has a key outside `allowed`.
nlohmann::json parse_options(const char* json_text, const std::vector<std::string>& allowed,
                             const char* what);

}  // namespace posecal::abi
