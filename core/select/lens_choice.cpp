// The automatic lens model (EngineOptions::auto_lens_model): after each keyframe's calibration
// every model of the lens table is fitted to the keyframes, and the engine moves to the one the
// Bayesian information criterion prefers once it leads the current one by kLensSwitchMargin
// (docs/pose-selection.md, "Automatic lens model").
#include <cmath>
#include <cstdio>
#include <optional>
#include <string>
#include <vector>

#include "common/error.hpp"
#include "select/engine_internal.hpp"

namespace posecal {

namespace {

LensCandidate evidence_of(const CalibrationResult& r) {
  LensCandidate c;
  c.model = r.model.lens_model();
  c.fitted = true;
  c.rms_px = r.rms_px;
  for (int i = 0; i < r.model.num_params(); ++i) c.free_intrinsics += r.fixed[i] ? 0 : 1;
  c.residuals = 2 * r.num_points;
  const double n = c.residuals;
  const double ssr = r.rms_px * r.rms_px * r.num_points;
  c.bic = n * std::log(std::max(ssr, 1e-300) / n) + c.free_intrinsics * std::log(n);
  c.expected_error_px = expected_error(r).rms_px;
  c.held = r.held;
  return c;
}

// The coefficients of `to` that mean what they mean in `from`: the pinhole four always, the
// distortion coefficients of the same name within a family (OpenCV's models, or the fisheye);
// -1 for the rest.
int carried_index(LensModel from, LensModel to, int i) {
  if (i < 0) return -1;
  if (i < kNumPinholeParams) return i;
  if (is_ray_model(from) != is_ray_model(to)) return -1;
  const std::vector<std::string>& names = intrinsic_names(to);
  const std::string& name = intrinsic_names(from)[static_cast<size_t>(i)];
  for (size_t j = kNumPinholeParams; j < names.size(); ++j)
    if (names[j] == name) return static_cast<int>(j);
  return -1;
}

// A start for `to` from another model's fit: its carried coefficients (the rest 0) and board
// poses. None for a ray model from a pinhole one: its own equidistant start is better.
std::optional<WarmStart> converted_start(const CalibrationResult& from, LensModel to) {
  const LensModel f = from.model.lens_model();
  if (is_ray_model(to) && !is_ray_model(f)) return std::nullopt;
  std::vector<double> p(static_cast<size_t>(num_intrinsics(to)), 0.0);
  for (int i = 0; i < from.model.num_params(); ++i) {
    const int j = carried_index(f, to, i);
    if (j >= 0) p[static_cast<size_t>(j)] = from.model.params()[static_cast<size_t>(i)];
  }
  return WarmStart{CameraModel(from.model.width(), from.model.height(), to, p), from.poses};
}

// The largest angle between a keyframe corner's direction (under the fit's board poses) and the
// optical axis, degrees.
double widest_corner_deg(const CalibrationResult& fit, const std::vector<Observation>& frames) {
  double widest = 0;
  for (size_t f = 0; f < frames.size() && f < fit.poses.size(); ++f) {
    const Eigen::Matrix3d R = fit.poses[f].R();
    for (const cv::Point3d& b : frames[f].board_points) {
      const Eigen::Vector3d p = R * Eigen::Vector3d(b.x, b.y, b.z) + fit.poses[f].t;
      widest = std::max(widest, std::atan2(std::hypot(p.x(), p.y()), p.z()) * 180 / M_PI);
    }
  }
  return widest;
}
// A pinhole model is not fitted to corners further from the axis than this: its projection
// diverges at 90 degrees, and the bundle adjustment would fail on them.
constexpr double kPinholeLimitDeg = 80;

}  // namespace

// The per-parameter state follows the parameters that carry over (by name, within a family);
// the others start unconverged and untargeted. The estimate is the caller's to replace.
void CalibrationEngine::Impl::move_to_lens_model(LensModel to) {
  const LensModel from = opt.calibration.lens_model;
  const int n = num_intrinsics(to);
  std::vector<bool> converged(static_cast<size_t>(n), false);
  std::vector<int> targeted(static_cast<size_t>(n), 0);
  for (int i = 0; i < num_intrinsics(from); ++i) {
    const int j = carried_index(from, to, i);
    if (j < 0 || static_cast<size_t>(i) >= param_converged.size()) continue;
    converged[static_cast<size_t>(j)] = param_converged[static_cast<size_t>(i)];
    targeted[static_cast<size_t>(j)] = param_targeted[static_cast<size_t>(i)];
  }
  param_converged = converged;
  param_targeted = targeted;
  for (int& t : keyframe_target) t = carried_index(from, to, t);
  target_param = carried_index(from, to, target_param);
  opt.calibration.lens_model = to;
}

std::string CalibrationEngine::Impl::choose_lens_model(CalibrationResult* now) {
  const LensModel current = now->model.lens_model();
  const std::vector<LensModel>& models = lens_models();
  lens_fits.resize(models.size());
  lens_evidence.clear();
  size_t cur = 0;
  const double widest = widest_corner_deg(*now, keyframes);
  for (size_t m = 0; m < models.size(); ++m) {
    if (models[m] == current) {
      lens_fits[m] = *now;
      lens_evidence.push_back(evidence_of(*now));
      cur = m;
      continue;
    }
    LensCandidate c;
    c.model = models[m];
    if (!is_ray_model(models[m]) && widest > kPinholeLimitDeg) {
      char why[160];
      std::snprintf(why, sizeof why,
                    "corners %.0f degrees from the optical axis: beyond what a pinhole model "
                    "projects (%.0f)",
                    widest, kPinholeLimitDeg);
      lens_fits[m].reset();
      c.failure = why;
      lens_evidence.push_back(c);
      continue;
    }
    try {
      CalibrationOptions co = opt.calibration;
      co.lens_model = models[m];
      co.hold_if_undetermined = extension_parameters(models[m]);
      // From this model's own last fit (the keyframes before this one), else from the current.
      std::optional<WarmStart> ws;
      if (lens_fits[m] && lens_fits[m]->poses.size() <= keyframes.size()) {
        ws = WarmStart{lens_fits[m]->model, lens_fits[m]->poses};
      } else {
        ws = converted_start(*now, models[m]);
      }
      lens_fits[m] = calibrate(keyframes, size, co, ws ? &*ws : nullptr);
      c = evidence_of(*lens_fits[m]);
    } catch (const Error& e) {
      lens_fits[m].reset();
      c.failure = e.what();
    }
    lens_evidence.push_back(c);
  }
  // The lead a model needs: kLensSwitchMargin within the family, kFamilySwitchMargin across (the
  // bootstrap chose the family; where the keyframes lie within some 80 degrees of the axis a
  // rich pinhole model and the fisheye both explain them, and the targets of the other family
  // would be ones the operator cannot reach).
  auto margin = [&](size_t m) {
    return is_ray_model(models[m]) == is_ray_model(current) ? kLensSwitchMargin
                                                            : kFamilySwitchMargin;
  };
  size_t best = cur;
  double best_lead = 0;
  for (size_t m = 0; m < models.size(); ++m) {
    if (!lens_evidence[m].fitted || m == cur) continue;
    const double lead = lens_evidence[cur].bic - lens_evidence[m].bic;
    if (lead > margin(m) && lead - margin(m) > best_lead) {
      best = m;
      best_lead = lead - margin(m);
    }
  }
  if (best == cur) return "";
  const double lead = lens_evidence[cur].bic - lens_evidence[best].bic;

  const LensModel to = models[best];
  move_to_lens_model(to);
  *now = *lens_fits[best];
  char text[160];
  std::snprintf(text, sizeof text, "; lens model %s -> %s (BIC lower by %.1f)",
                lens_model_name(current), lens_model_name(to), lead);
  return text;
}

}  // namespace posecal
