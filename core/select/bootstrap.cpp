// The bootstrap (paper §3.4): before any keyframe, a single-view fit of the focal lengths gives the
// estimate the first target is placed with.
#include <algorithm>
#include <cmath>
#include <map>

#include "calib/pose_estimation.hpp"
#include "common/error.hpp"
#include "select/engine_internal.hpp"

namespace posecal {

int CalibrationEngine::Impl::bootstrap_min_corners() const {
  return opt.bootstrap_min_corners > 0 ? opt.bootstrap_min_corners : std::max(6, board.num_corners() / 2);
}

namespace {
constexpr size_t kMaxBootstrapViews = 6;
constexpr double kPi = 3.14159265358979323846;
}  // namespace

// Paper §3.4: a single-frame calibration of the focal length only (principal point at the
// centre, no distortion); the best by residual is kept. Departure: when no single view
// determines f (a person who shows the board tilted 10-25 degrees and never more), the distinct
// views seen so far are fitted together, which two tilts about different axes do
// (docs/pose-selection.md, "The bootstrap").
bool CalibrationEngine::Impl::try_bootstrap(const Detection& det) {
  if (static_cast<int>(det.size()) < bootstrap_min_corners()) {
    bootstrap_hint = "show more of the board (" + std::to_string(det.size()) + " of " +
                     std::to_string(bootstrap_min_corners()) + " corners needed)";
    return false;
  }
  const Observation view = Observation::from(det);
  if (fit_bootstrap({view})) return true;
  if (have_bootstrap) return false;
  // The board's tilt under the current guess of f (good enough to say "more").
  double tilt = -1;
  Pose p;
  if (estimate_pose(estimate, view, &p)) tilt = std::acos(std::min(1.0, std::abs(p.R()(2, 2)))) * 180.0 / kPi;
  // "About 30 degrees": what a single view needs in the benchmark's cameras; the joint fit of
  // several views below may get there first.
  double x0 = size.width, x1 = 0;
  for (const cv::Point2d& p : view.image_points) x0 = std::min(x0, p.x), x1 = std::max(x1, p.x);
  if (x1 - x0 < 0.3 * size.width) {
    bootstrap_hint = "bring the board closer, to about half the width of the view";
  } else if (tilt >= 0 && tilt < 30) {
    const int more = std::max(10, static_cast<int>(std::lround((35 - tilt) / 5)) * 5);
    bootstrap_hint = "tilt the board about " + std::to_string(more) + " degrees more (it is tilted " +
                     std::to_string(static_cast<int>(std::lround(tilt))) + " degrees)";
  } else {
    bootstrap_hint = "tilt the board differently, about 30 degrees away from the camera";
  }
  if (!remember_bootstrap_view(view) || bootstrap_views.size() < 2) return false;
  return fit_bootstrap(bootstrap_views);
}

// Keeps a view that differs from every kept one (corners moved by more than 1.5% of the image
// width on average, or a different set of corners; a board held still moves < 1 px); false if it adds
// nothing.
bool CalibrationEngine::Impl::remember_bootstrap_view(const Observation& view) {
  for (const Observation& kept : bootstrap_views) {
    std::map<int, cv::Point2d> at;
    for (size_t j = 0; j < kept.ids.size(); ++j) at.emplace(kept.ids[j], kept.image_points[j]);
    double sum = 0;
    int common = 0;
    for (size_t i = 0; i < view.ids.size(); ++i) {
      const auto it = at.find(view.ids[i]);
      if (it == at.end()) continue;
      sum += cv::norm(view.image_points[i] - it->second);
      ++common;
    }
    if (common >= static_cast<int>(view.ids.size()) / 2 && sum / common < 0.015 * size.width) return false;
  }
  bootstrap_views.push_back(view);
  if (bootstrap_views.size() > kMaxBootstrapViews) bootstrap_views.erase(bootstrap_views.begin());
  return true;
}

bool CalibrationEngine::Impl::fit_bootstrap(const std::vector<Observation>& views) {
  CalibrationOptions co = opt.calibration;
  // Focal lengths only: fx and fy both free. The paper's sampling protocol varies them
  // independently by 10%; forcing fx = fy turns the aspect ratio into a false tilt seen from
  // far away (seen: f 4.5x too large), which sends a robot to an invisible target.
  co.fix_principal_point = true;
  co.fix_aspect_ratio = false;
  co.zero_distortion = true;
  co.fixed.clear();
  try {
    CalibrationResult r = calibrate(views, size, co);
    if (opt.auto_lens_model) {
      // The automatic lens model's family is chosen here, where the first target is drawn with
      // it: the pinhole or the equidistant projection, whichever explains the views better (a
      // board seen through a fisheye is far from any pinhole image, and back).
      CalibrationOptions other = co;
      other.lens_model = is_ray_model(co.lens_model) ? LensModel::kOpenCV5 : LensModel::kFisheye;
      try {
        CalibrationResult ro = calibrate(views, size, other);
        if (ro.rms_px < r.rms_px) {
          r = std::move(ro);
          co = other;
        }
      } catch (const Error&) {
        // (that projection cannot explain them)
      }
    }
    // Uncertainty at the measured noise level, floored at 0.1 px so that a perfect fit of a
    // weak view cannot pass: telephoto lenses see little perspective, so at 1 px noise even a
    // 60 degree tilt leaves f 5% uncertain, while their real corner noise is ~0.05 px.
    const double sigma = std::max(0.1, std::sqrt(r.residual_variance));
    const double rel_std = r.std_unit[0] * sigma / r.model.fx();
    if (rel_std > opt.bootstrap_max_relative_std) return false;
    // Bias: the principal point is assumed at the centre. A weak view lets that assumption
    // move f a lot (seen: f 5x too large from a 10 degree view of a camera whose principal
    // point was 100 px off); a robot sent to a target computed with such an f sees nothing.
    // Refit with the principal point moved by 5% of the image; f must stay within 10%.
    for (const cv::Point2d d : {cv::Point2d(0.05, 0), cv::Point2d(-0.05, 0), cv::Point2d(0, 0.05), cv::Point2d(0, -0.05)}) {
      CameraModel shifted = r.model;
      shifted.params()[2] += d.x * size.width;
      shifted.params()[3] += d.y * size.height;
      const WarmStart ws{shifted, r.poses};
      const CalibrationResult rs = calibrate(views, size, co, &ws);
      if (std::abs(rs.model.fx() - r.model.fx()) > opt.bootstrap_max_pp_sensitivity * r.model.fx()) return false;
    }
    // Deviation from the paper (which keeps the best by residual): keep the view that
    // determines f best. A weak view fits any f with a low residual (docs/pose-selection.md).
    if (rel_std < best_bootstrap_rms) {
      best_bootstrap_rms = rel_std;
      if (co.lens_model != opt.calibration.lens_model) move_to_lens_model(co.lens_model);
      estimate = r.model;
      have_bootstrap = true;
      bootstrap_hint.clear();
      return true;
    }
  } catch (const Error&) {
    // Degenerate view (e.g. fronto-parallel): the focal length is unobservable from it.
  }
  return false;
}

}  // namespace posecal
