// Frozen layouts of the C ABI (ONNX Runtime style): a change here is an incompatible change of
// POSECAL_ABI_VERSION 1 and must not compile silently. posecal_image may only grow at its end
// (hosts set struct_size, the library checks it).
#include <cstddef>
#include <type_traits>

#include "posecal.h"

static_assert(POSECAL_ABI_VERSION == 1u, "layouts below are those of ABI version 1");

static_assert(std::is_standard_layout_v<posecal_image>, "posecal_image must stay a C struct");
static_assert(offsetof(posecal_image, struct_size) == 0, "posecal_image layout changed");
static_assert(offsetof(posecal_image, width) == 4, "posecal_image layout changed");
static_assert(offsetof(posecal_image, height) == 8, "posecal_image layout changed");
static_assert(offsetof(posecal_image, stride_bytes) == 12, "posecal_image layout changed");
static_assert(offsetof(posecal_image, format) == 16, "posecal_image layout changed");
#if UINTPTR_MAX > 0xFFFFFFFFu
static_assert(offsetof(posecal_image, data) == 24, "posecal_image layout changed (LP64)");
static_assert(sizeof(posecal_image) == 32, "posecal_image layout changed (LP64)");
#else
static_assert(offsetof(posecal_image, data) == 20, "posecal_image layout changed (ILP32)");
static_assert(sizeof(posecal_image) == 24, "posecal_image layout changed (ILP32)");
#endif

// Enumerations travel as int32_t / int; their values are part of the ABI.
static_assert(sizeof(posecal_status) == sizeof(int), "posecal_status must be int-sized");
static_assert(POSECAL_OK == 0 && POSECAL_E_INVALID_ARGUMENT == 1 && POSECAL_E_NOT_FOUND == 2 &&
                  POSECAL_E_BUFFER_TOO_SMALL == 3 && POSECAL_E_TIMEOUT == 4 &&
                  POSECAL_E_DEVICE == 5 && POSECAL_E_STATE == 6 && POSECAL_E_IO == 7 &&
                  POSECAL_E_INTERNAL == 8 && POSECAL_E_DEGENERATE == 9 &&
                  POSECAL_E_UNSUPPORTED == 10,
              "posecal_status values are frozen");
static_assert(POSECAL_PIXEL_MONO8 == 0 && POSECAL_PIXEL_BGR8 == 1 && POSECAL_PIXEL_RGB8 == 2,
              "posecal_pixel_format values are frozen");

// The statuses are core's error codes one-to-one (common/error.hpp), so abi::status_of is a
// table, not a policy.
#include "common/error.hpp"
static_assert(static_cast<int>(posecal::ErrorCode::kInvalidArgument) ==
                      POSECAL_E_INVALID_ARGUMENT &&
                  static_cast<int>(posecal::ErrorCode::kNotFound) == POSECAL_E_NOT_FOUND &&
                  static_cast<int>(posecal::ErrorCode::kBufferTooSmall) ==
                      POSECAL_E_BUFFER_TOO_SMALL &&
                  static_cast<int>(posecal::ErrorCode::kTimeout) == POSECAL_E_TIMEOUT &&
                  static_cast<int>(posecal::ErrorCode::kDevice) == POSECAL_E_DEVICE &&
                  static_cast<int>(posecal::ErrorCode::kState) == POSECAL_E_STATE &&
                  static_cast<int>(posecal::ErrorCode::kIo) == POSECAL_E_IO &&
                  static_cast<int>(posecal::ErrorCode::kInternal) == POSECAL_E_INTERNAL &&
                  static_cast<int>(posecal::ErrorCode::kDegenerate) == POSECAL_E_DEGENERATE &&
                  static_cast<int>(posecal::ErrorCode::kUnsupported) == POSECAL_E_UNSUPPORTED,
              "core error codes and posecal_status must match");
