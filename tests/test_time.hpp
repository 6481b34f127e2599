// How much slower than a normal build the tests run: POSECAL_TEST_TIME_FACTOR, which ctest sets
// for every test from the CMake cache variable POSECAL_TEST_TIMEOUT_FACTOR (1 normally, 3 under
// ASan + UBSan, 10 under ThreadSanitizer; tests/CMakeLists.txt). A test scales its own waits by
// it, and a test that counts what arrives within a real-time window (frames from a simulated
// camera that renders them on the same slowed cores) lowers its expectation by it.
#pragma once

#include <cstdlib>

namespace posecal::test {

inline int time_factor() {
  const char* v = std::getenv("POSECAL_TEST_TIME_FACTOR");
  const int f = v != nullptr ? std::atoi(v) : 1;
  return f >= 1 && f <= 100 ? f : 1;
}

// A wait of `ms` milliseconds in a normal build, scaled for a sanitized one.
inline int scaled_ms(int ms) { return ms * time_factor(); }

}  // namespace posecal::test
