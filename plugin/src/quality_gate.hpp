// The quality gate (docs/c-api.md, "Quality gate"): a product specification, read from a JSON
// file, and the verdict of a calibration against it: pass or fail, with every reason.
#pragma once

#include <map>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <vector>

namespace posecal::abi {

// One intrinsic's allowed range: |value - nominal| <= tolerance * |nominal| (relative) and/or
// <= tolerance_abs (each given one is checked).
struct ParameterLimit {
  double nominal = 0;
  std::optional<double> tolerance, tolerance_abs;
};

struct QualitySpec {
  std::string path;  // the file it was read from
  std::optional<double> max_expected_error_px, max_eps_res_px, max_seconds;
  std::optional<int> max_keyframes;
  std::map<std::string, ParameterLimit> parameters;
  bool require_converged = true;
};

// The largest specification file read (bytes): a specification is a few hundred bytes.
inline constexpr long long kMaxSpecFileBytes = 64 * 1024;

// Reads and checks a specification file. Error(kInvalidArgument) naming the file and the key for
// an unknown key, a value of the wrong type or range, a parameter that `parameter_names` (the
// session's lens model) does not have, invalid JSON or a file above kMaxSpecFileBytes;
// Error(kNotFound) / kIo when it cannot be read.
QualitySpec read_quality_spec(const std::string& path,
                              const std::vector<std::string>& parameter_names);
// The same from the file's text (`path` only names it in errors; fuzz_quality_spec).
QualitySpec parse_quality_spec(const std::string& text, const std::string& path,
                               const std::vector<std::string>& parameter_names);

// The verdict of a calibration result (the JSON of posecal_session_result or
// posecal_calibration_json: "converged", "interrupted", "expected_error_px", "eps_res" and the
// intrinsics by name) that took `seconds` and `keyframes`: {"verdict": "pass" | "fail",
// "verdict_reasons": [...], "spec": path}. Each reason names the limit and the figure.
nlohmann::json quality_verdict(const QualitySpec& spec, const nlohmann::json& result,
                               int keyframes, double seconds);

}  // namespace posecal::abi
