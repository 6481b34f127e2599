// What the C ABI benchmarks (bench_abi.cpp, bench_station_load.cpp) share: clocks, the status
// JSON's fields they read, quantiles, and the exit on a failed call. Header-only, C ABI only.
#pragma once

#include <time.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <string>
#include <vector>

#include "posecal.h"

namespace posecal_bench {

using Clock = std::chrono::steady_clock;

// A clock's reading in seconds (CLOCK_PROCESS_CPUTIME_ID, CLOCK_THREAD_CPUTIME_ID, ...).
inline double clock_s(clockid_t id) {
  timespec ts{};
  clock_gettime(id, &ts);
  return static_cast<double>(ts.tv_sec) + 1e-9 * static_cast<double>(ts.tv_nsec);
}

inline double since_s(Clock::time_point t0) {
  return std::chrono::duration<double>(Clock::now() - t0).count();
}

// Ends the benchmark (exit 2) naming the failed call and the ABI's last error.
[[noreturn]] inline void die(const char* what) {
  std::fprintf(stderr, "%s: %s\n", what, posecal_last_error());
  std::exit(2);
}

inline std::string status_json(posecal_session* s) {
  std::vector<char> buf(1 << 16);
  size_t size = buf.size();
  if (posecal_session_status(s, buf.data(), &size) != POSECAL_OK) die("status");
  return std::string(buf.data());
}

inline bool converged(posecal_session* s) {
  return status_json(s).find("\"state\":\"converged\"") != std::string::npos;
}

// The value after option argv[*i] (advancing *i to it); exits 1 naming the option if none follows.
inline const char* option_value(int argc, char** argv, int* i) {
  if (*i + 1 >= argc) {
    std::fprintf(stderr, "%s needs a value\n", argv[*i]);
    std::exit(1);
  }
  return argv[++*i];
}

// The q-quantile (0..1) of v, linear between neighbours; 0 for an empty v.
inline double quantile(std::vector<double> v, double q) {
  if (v.empty()) return 0;
  std::sort(v.begin(), v.end());
  const double at = q * static_cast<double>(v.size() - 1);
  const auto lo = static_cast<size_t>(at);
  const size_t hi = std::min(lo + 1, v.size() - 1);
  return v[lo] + (at - static_cast<double>(lo)) * (v[hi] - v[lo]);
}

}  // namespace posecal_bench
