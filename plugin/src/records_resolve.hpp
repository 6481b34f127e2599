// A record's calibration recomputed from its stored keyframes, shared by the records' readers
// (records_abi.cpp) and the report (report_abi.cpp).
#pragma once

#include <memory>
#include <nlohmann/json.hpp>
#include <optional>

#include "records/record_store.hpp"
#include "select/engine.hpp"

namespace posecal::abi {

// The run's calibration recomputed from its stored keyframes, as a journal's resume recomputes
// it: the engine of the recorded config and image size, every keyframe restored in order.
struct Resolved {
  std::unique_ptr<CalibrationEngine> engine;
  bool identical_to_last_keyframe = false;
};

// The fleet prior a session used, as its result's "prior" keeps it ({"used": true, "names",
// "mean": {param: value}, "covariance": rows over names, "noise_px", "image_width",
// "image_height", "accuracy_px", ...}): written by session_abi.cpp, read back by resolve() so
// that a run calibrated with a prior re-solves bit for bit whatever the fleet is now.
nlohmann::json prior_json(const IntrinsicsPrior& prior,
                          const std::vector<std::string>& param_names);
// The prior of a result's "prior" (nullopt if it has none or did not use one);
// Error(kInvalidArgument) naming what is malformed.
std::optional<IntrinsicsPrior> prior_from_json(const nlohmann::json& result, LensModel lens);

// Throws Error(kState) for a run of fewer than two keyframes (one with a prior), Error(kDegenerate)
// if its keyframes give no calibration, Error(kInvalidArgument) for a recorded config it cannot
// read.
Resolved resolve(const RunRecord& r);

}  // namespace posecal::abi
