// A record's calibration recomputed from its stored keyframes, shared by the records' readers
// (records_abi.cpp) and the report (report_abi.cpp).
#pragma once

#include <memory>

#include "records/record_store.hpp"
#include "select/engine.hpp"

namespace posecal::abi {

// The run's calibration recomputed from its stored keyframes, as a journal's resume recomputes
// it: the engine of the recorded config and image size, every keyframe restored in order.
struct Resolved {
  std::unique_ptr<CalibrationEngine> engine;
  bool identical_to_last_keyframe = false;
};

// Throws Error(kState) for a run of fewer than two keyframes, Error(kDegenerate) if its
// keyframes give no calibration, Error(kInvalidArgument) for a recorded config it cannot read.
Resolved resolve(const RunRecord& r);

}  // namespace posecal::abi
