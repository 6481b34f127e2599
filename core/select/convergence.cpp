// When a parameter has converged (paper §4.1): the ratio test on the keyframe just captured, and
// the prospective test on the keyframe about to be requested (docs/pose-selection.md).
#include <algorithm>
#include <cmath>
#include <cstdio>

#include "common/error.hpp"
#include "select/engine_internal.hpp"

namespace posecal {

double variance_reduction(double var_before, double var_after, EngineOptions::ConvergenceMeasure measure) {
  return measure == EngineOptions::ConvergenceMeasure::kStd ? 1.0 - std::sqrt(std::max(0.0, var_after) / var_before)
                                                            : 1.0 - var_after / var_before;
}

std::string percent_text(double fraction) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "%.1f%%", fraction * 100.0);
  return buf;
}

std::vector<int> ratio_test(const std::vector<double>& var_before, const std::vector<double>& var_after,
                            int targeted, const std::vector<bool>& converged, const int group_keyframes[2],
                            double threshold, EngineOptions::ConvergenceMeasure measure) {
  const size_t n = var_before.size();
  if (var_after.size() != n || converged.size() != n || targeted < 0 || targeted >= static_cast<int>(n)) {
    throw Error(ErrorCode::kInvalidArgument, "ratio_test: inconsistent sizes");
  }
  std::vector<int> out;
  const ParamGroup g = param_group(targeted);
  for (size_t i = 0; i < n; ++i) {
    if (converged[i] || param_group(static_cast<int>(i)) != g) continue;  // only the targeted group
    const double v0 = var_before[i], v1 = var_after[i];
    if (!(v0 > 0) || !std::isfinite(v1)) continue;
    const double red = variance_reduction(v0, v1, measure);
    // Deviation from the reference implementation: the comparison must be between two
    // keyframes of the group's own strategy, so the first keyframe of a group after
    // initialisation cannot converge parameters it did not target (otherwise p1 and p2
    // "converge" at the first distortion keyframe whatever it taught about them).
    const bool evidence = static_cast<int>(i) == targeted || group_keyframes[static_cast<int>(g)] >= 2;
    if (red >= 0 && red < threshold && evidence) out.push_back(static_cast<int>(i));
  }
  return out;
}

double CalibrationEngine::Impl::reduction(double var_before, double var_after) const {
  if (!(var_before > 0)) return 0.0;
  return variance_reduction(var_before, var_after, opt.convergence_measure);
}

void CalibrationEngine::Impl::mark_converged(int i, const std::string& why) {
  param_converged[i] = true;
  EngineEvent e{EngineEvent::Kind::kParameterConverged};
  e.parameter = estimate.param_names()[i];
  e.message = why;
  emit(e);
}

bool CalibrationEngine::Impl::all_converged() const {
  return std::all_of(param_converged.begin(), param_converged.end(), [](bool b) { return b; });
}

// Ratio test (paper §4.1) on the parameters of the targeted parameter's group.
void CalibrationEngine::Impl::update_convergence(const CalibrationResult& prev, const CalibrationResult& now, int tgt) {
  if (tgt < 0 || !opt.measured_convergence) return;
  std::vector<double> v0, v1;
  std::vector<bool> skip = param_converged;
  for (int i = 0; i < estimate.num_params(); ++i) {
    v0.push_back(prev.std_unit[i] * prev.std_unit[i]);
    v1.push_back(now.std_unit[i] * now.std_unit[i]);
    if (now.fixed[i]) skip[i] = true;
  }
  for (int i : ratio_test(v0, v1, tgt, skip, group_keyframes, opt.convergence_threshold, opt.convergence_measure)) {
    mark_converged(i, "variance reduced by only " + percent_text(reduction(v0[i], v1[i])) + " by the last keyframe");
  }
}

bool CalibrationEngine::Impl::converges_prospectively(int param, double predicted_variance) {
  // Started from a prior: nothing converges before the first keyframe (a tight prior would
  // otherwise end the run without a calibration).
  if (!result) return false;
  const double now = result->std_unit[param] * result->std_unit[param];
  const double red = reduction(now, predicted_variance);
  if (red >= opt.convergence_threshold) return false;
  mark_converged(param, "best pose would reduce its variance by only " + percent_text(red) +
                            ": converged without capturing it");
  return true;
}

namespace {

std::string px_text(double px) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "%.3f px", px);
  return buf;
}

// "X px (90th percentile; RMS Y px)": the expected error as every message about it names it.
std::string expected_text(const ExpectedError& e) {
  return px_text(e.p90_px) + " (90th percentile; RMS " + px_text(e.rms_px) + ")";
}

}  // namespace

// Why an estimate that folds inside the image cannot stop, as every message about it says it.
std::string fold_text(const ExpectedError& e) {
  return "the estimate folds inside the image (" + std::to_string(e.grid_points - e.points) +
         " of the " + std::to_string(e.grid_points) +
         " grid points the expected error is taken over have no ray under it; the keyframes do "
         "not reach far enough towards the image corners to determine the distortion there)";
}

void CalibrationEngine::Impl::continue_towards_accuracy() {
  // The stop figure is the predicted 90th percentile of the realised eps_gt, not the RMS: the
  // realised error of one calibration scatters around the RMS (p90 about 1.4x it), so stopping on
  // the RMS left the realised error above 1.2 x accuracy_px in about one run in five
  // (docs/pose-selection.md, deviation 15).
  const double goal = *opt.accuracy_px;
  // (Not while a parameter is held: the expected error does not see a held guess.)
  // (Nor while the estimate folds inside the image: the figure leaves that part out.)
  if (expected->p90_px <= goal && held_pending() < 0 &&
      expected->covers_image()) {  // false for NaN
    const std::string why =
        "expected error " + expected_text(*expected) + " <= accuracy_px " + px_text(goal);
    for (int i = 0; i < estimate.num_params(); ++i)
      if (!param_converged[i]) mark_converged(i, why);
    target.reset();
    target_param = -1;
    set_state(EngineState::kConverged, why);
    return;
  }
  if (static_cast<int>(keyframes.size()) >= opt.max_keyframes) return fail(accuracy_shortfall());
  set_state(EngineState::kRefining);
  choose_accuracy_target();
}

bool CalibrationEngine::Impl::reopen_above_ceiling() {
  if (!expected) return false;
  const double ceiling = opt.ratio_stop_max_p90_px;
  const bool above = ceiling > 0 && !(expected->p90_px <= ceiling);  // NaN: above
  // (An estimate that folds inside the image: not in the paper's presets, which stay the paper's.)
  const bool folded = opt.method == EngineOptions::Method::kPosecal && !expected->covers_image();
  if (!above && !folded) return false;
  if (static_cast<int>(keyframes.size()) >= opt.max_keyframes)
    return true;  // the cap's failure says why
  const int param = expected->limiting_param;
  if (param < 0) return false;  // every intrinsic fixed: nothing to target
  param_converged[param] = false;
  EngineEvent e{EngineEvent::Kind::kParameterReopened};
  e.parameter = estimate.param_names()[param];
  e.message = "every parameter passed the ratio test, but " +
              (folded ? fold_text(*expected) + "; the expected error is " + expected_text(*expected)
                      : "the expected error is " + expected_text(*expected) +
                            ", above ratio_stop_max_p90_px " + px_text(ceiling)) +
              "; " + e.parameter + " holds it back (" + percent_text(expected->limiting_share) +
              " of the squared error)";
  emit(e);
  set_state(EngineState::kRefining);
  choose_accuracy_target();
  return true;
}

std::string CalibrationEngine::Impl::ceiling_shortfall() const {
  return "keyframe cap (" + std::to_string(opt.max_keyframes) +
         ") reached: every parameter passed the ratio test, but " +
         (expected->covers_image()
              ? "the expected error is " + expected_text(*expected) +
                    ", above ratio_stop_max_p90_px " + px_text(opt.ratio_stop_max_p90_px)
              : fold_text(*expected));
}

std::string CalibrationEngine::Impl::accuracy_shortfall() const {
  std::string why = "keyframe cap (" + std::to_string(opt.max_keyframes) +
                    ") reached with an expected error of " + expected_text(*expected) +
                    ", above accuracy_px " + px_text(*opt.accuracy_px);
  if (expected->limiting_param >= 0) {
    why += "; " + estimate.param_names()[expected->limiting_param] +
           " holds it back (knowing it exactly would remove " + percent_text(expected->limiting_share) +
           " of the squared error)";
  }
  if (!expected->covers_image()) why += "; " + fold_text(*expected);
  if (!result->solver_converged()) {
    why += "; the last bundle adjustment stopped at its iteration limit (" + result->termination_message + ")";
  }
  return why;
}

}  // namespace posecal
