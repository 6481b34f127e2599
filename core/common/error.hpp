// posecal core: error type shared by every part.
//
// Inside the C++ parts failures are exceptions of type posecal::Error carrying a code; the C ABI
// (plugin/) is the only place that turns them into a posecal_status, so the codes below map
// one-to-one onto the POSECAL_E_* values of plugin/include/posecal.h.
#pragma once

#include <stdexcept>
#include <string>

namespace posecal {

enum class ErrorCode {
  kInvalidArgument = 1,  // malformed input: bad spec, bad JSON, NaN, out-of-range value
  kNotFound = 2,         // camera, feature, file or key that does not exist
  kBufferTooSmall = 3,   // only used by the C ABI
  kTimeout = 4,          // a blocking call ran out of time
  kDevice = 5,           // the camera failed or disconnected
  kState = 6,            // the call is not allowed in the object's current state
  kIo = 7,               // file or stream could not be read or written
  kInternal = 8,         // a bug: an invariant did not hold
  kDegenerate = 9,       // data cannot determine the result (e.g. focal length unobservable)
  kUnsupported = 10,     // a valid request this build or device does not support
};

const char* error_code_name(ErrorCode code);

class Error : public std::runtime_error {
 public:
  Error(ErrorCode code, const std::string& message) : std::runtime_error(message), code_(code) {}
  ErrorCode code() const { return code_; }

 private:
  ErrorCode code_;
};

}  // namespace posecal
