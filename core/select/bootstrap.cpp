// The bootstrap (paper §3.4): before any keyframe, a single-view fit of the focal lengths gives the
// estimate the first target is placed with.
#include <cmath>

#include "common/error.hpp"
#include "select/engine_internal.hpp"

namespace posecal {

int CalibrationEngine::Impl::bootstrap_min_corners() const {
  return opt.bootstrap_min_corners > 0 ? opt.bootstrap_min_corners : std::max(6, board.num_corners() / 2);
}

// Paper §3.4: a single-frame calibration of the focal length only (principal point at the
// centre, no distortion); the best by residual is kept.
bool CalibrationEngine::Impl::try_bootstrap(const Detection& det) {
  if (static_cast<int>(det.size()) < bootstrap_min_corners()) return false;
  CalibrationOptions co = opt.calibration;
  // Focal lengths only: fx and fy both free. The paper's sampling protocol varies them
  // independently by 10%; forcing fx = fy turns the aspect ratio into a false tilt seen from
  // far away (seen: f 4.5x too large), which sends a robot to an invisible target.
  co.fix_principal_point = true;
  co.fix_aspect_ratio = false;
  co.zero_distortion = true;
  co.fixed.clear();
  try {
    const CalibrationResult r = calibrate({Observation::from(det)}, size, co);
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
      const CalibrationResult rs = calibrate({Observation::from(det)}, size, co, &ws);
      if (std::abs(rs.model.fx() - r.model.fx()) > opt.bootstrap_max_pp_sensitivity * r.model.fx()) return false;
    }
    // Deviation from the paper (which keeps the best by residual): keep the view that
    // determines f best. A weak view fits any f with a low residual (docs/pose-selection.md).
    if (rel_std < best_bootstrap_rms) {
      best_bootstrap_rms = rel_std;
      estimate = r.model;
      have_bootstrap = true;
      return true;
    }
  } catch (const Error&) {
    // Degenerate view (e.g. fronto-parallel): the focal length is unobservable from it.
  }
  return false;
}

}  // namespace posecal
