// What the operator is told (FrameReport::guidance) and what a guided camera is given.
#include <algorithm>
#include <cmath>
#include <opencv2/imgproc.hpp>

#include "select/engine_internal.hpp"

namespace posecal {

std::string CalibrationEngine::Impl::guidance_text(const FrameReport& r, const std::optional<Pose>& current) const {
  switch (state) {
    case EngineState::kConverged: return "calibration converged";
    case EngineState::kFailed: return "calibration stopped: " + failure;
    case EngineState::kWaitingForBoard: return "show the calibration board to the camera";
    case EngineState::kBootstrapping:
      if (r.corners < bootstrap_min_corners()) return "show more of the board";
      return bootstrap_hint.empty() ? "tilt the board slightly so the focal length can be estimated" : bootstrap_hint;
    default: break;
  }
  if (r.captured) return "captured keyframe " + std::to_string(keyframes.size());
  if (!r.board_visible) return "show the calibration board to the camera";
  if (r.corners < r.corners_required) {
    return "show the whole board (" + std::to_string(r.corners) + " of " + std::to_string(r.corners_required) +
           " corners needed)";
  }
  if (r.pose_reached) return "hold still";
  if (opt.robot) return "waiting for the robot to reach the target pose";
  if (!current || !target) return "align the board with the overlay";
  return alignment_hint(*current);
}

// What to change so the board matches the target: position first, then size, tilt, rotation.
std::string CalibrationEngine::Impl::alignment_hint(const Pose& current) const {
  const auto a = projected_outline(estimate, board, target->T_cam_board, 4);
  const auto b = projected_outline(estimate, board, current, 4);
  if (a.empty() || b.empty()) return "align the board with the overlay";
  const double area_a = std::abs(cv::contourArea(std::vector<cv::Point2f>(a.begin(), a.end())));
  const double area_b = std::abs(cv::contourArea(std::vector<cv::Point2f>(b.begin(), b.end())));
  cv::Point2d ca(0, 0), cb(0, 0);
  for (const auto& p : a) ca += p;
  for (const auto& p : b) cb += p;
  ca /= static_cast<double>(a.size());
  cb /= static_cast<double>(b.size());
  const cv::Point2d d = ca - cb;
  const double tol = 0.04 * std::max(size.width, size.height);
  if (std::abs(d.x) > tol || std::abs(d.y) > tol) {
    if (std::abs(d.x) >= std::abs(d.y)) return d.x > 0 ? "move right" : "move left";
    return d.y > 0 ? "move down" : "move up";
  }
  if (area_a > 1.15 * area_b) return "move closer";
  if (area_a < 0.87 * area_b) return "move further away";
  const Eigen::Vector3d n_t = target->T_cam_board.R().col(2), n_c = current.R().col(2);
  const double tilt_t = std::acos(std::clamp(n_t.z(), -1.0, 1.0)), tilt_c = std::acos(std::clamp(n_c.z(), -1.0, 1.0));
  if (tilt_t > tilt_c + 0.09) return "tilt the board further";
  if (tilt_t < tilt_c - 0.09) return "tilt the board back towards the camera";
  if (rotation_angle_between(target->T_cam_board.R(), current.R()) > 0.09) return "rotate the board to match the overlay";
  return "align the board with the overlay";
}

GuidanceInfo CalibrationEngine::guidance_info() const {
  const Impl& s = *impl_;
  GuidanceInfo g;
  g.has_target = s.target.has_value();
  g.bootstrapping = !s.have_bootstrap && s.keyframes.empty();
  g.robot = s.opt.robot;
  if (s.target) g.T_cam_board_target = s.target->T_cam_board;
  g.estimate = s.estimate;
  g.target_serial = s.target_serial;
  if (s.target) g.target_kind = s.target->kind;
  g.keyframes = static_cast<int>(s.keyframes.size());
  g.finished = s.state == EngineState::kConverged || s.state == EngineState::kFailed;
  return g;
}

}  // namespace posecal
