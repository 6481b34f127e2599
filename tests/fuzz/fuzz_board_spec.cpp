// libFuzzer target: board specs, BoardSpec::parse (core/board/board.cpp), as a session config's
// "target" and posecal_write_target pass them.
//
// Besides "no crash, no sanitizer report, only posecal::Error thrown": a spec that parses is
// valid, builds a Board, and its to_string() parses again to the same board (it is written into
// result files and read back).
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <string>

#include "board/board.hpp"
#include "common/error.hpp"

namespace {

bool close(double a, double b) {
  return std::abs(a - b) <= 1e-9 * std::max(std::abs(a), std::abs(b));
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string text(reinterpret_cast<const char*>(data), size);
  posecal::BoardSpec spec;
  try {
    spec = posecal::BoardSpec::parse(text);
  } catch (const posecal::Error&) {
    return 0;
  }
  spec.validate();  // must not throw: parse validated it
  const posecal::Board board(spec);
  if (board.num_corners() <= 0) std::abort();
  const posecal::BoardSpec again = posecal::BoardSpec::parse(spec.to_string());  // must not throw
  if (again.type != spec.type || again.cols != spec.cols || again.rows != spec.rows ||
      again.dictionary != spec.dictionary || !close(again.square_length_m, spec.square_length_m) ||
      !close(again.marker_length_m, spec.marker_length_m)) {
    std::abort();
  }
  return 0;
}
