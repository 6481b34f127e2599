// The clocks posecal reads: the host's monotonic clock for frame timestamps, UTC wall time for
// records and files.
#pragma once

#include <cstdint>
#include <string>

namespace posecal {

// std::chrono::steady_clock in nanoseconds (CLOCK_MONOTONIC on Linux, as V4L2 timestamps).
int64_t monotonic_ns();

// The current UTC time as ISO 8601, "2026-12-01T20:35:54Z".
std::string utc_now_iso8601();

}  // namespace posecal
