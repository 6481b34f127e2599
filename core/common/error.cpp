#include "common/error.hpp"

namespace posecal {

const char* error_code_name(ErrorCode code) {
  switch (code) {
    case ErrorCode::kInvalidArgument:
      return "invalid argument";
    case ErrorCode::kNotFound:
      return "not found";
    case ErrorCode::kBufferTooSmall:
      return "buffer too small";
    case ErrorCode::kTimeout:
      return "timeout";
    case ErrorCode::kDevice:
      return "device error";
    case ErrorCode::kState:
      return "wrong state";
    case ErrorCode::kIo:
      return "I/O error";
    case ErrorCode::kInternal:
      return "internal error";
    case ErrorCode::kDegenerate:
      return "degenerate data";
    case ErrorCode::kUnsupported:
      return "unsupported";
  }
  return "unknown error";
}

}  // namespace posecal
