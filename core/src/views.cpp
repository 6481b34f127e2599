#include "posecal/views.hpp"

#include <cmath>

#include "posecal/error.hpp"

namespace posecal {

Pose board_pose_at(const Target& target, const Eigen::Vector3d& centre_cam, double tilt_axis_rad,
                   double tilt_rad, double roll_rad) {
  const Eigen::Vector3d axis(std::cos(tilt_axis_rad), std::sin(tilt_axis_rad), 0.0);
  const Eigen::Matrix3d R =
      Eigen::AngleAxisd(roll_rad, Eigen::Vector3d::UnitZ()).toRotationMatrix() *
      Eigen::AngleAxisd(tilt_rad, axis).toRotationMatrix();
  const cv::Size2d bs = target.board_size_m();
  const Eigen::Vector3d centre_board(bs.width / 2, bs.height / 2, 0.0);
  return Pose::from_rotation(R, centre_cam - R * centre_board);
}

bool board_fully_visible(const CameraModel& model, const Target& target, const Pose& T_cam_board,
                         double margin_px) {
  const auto outline = target.outline();
  auto inside = [&](const cv::Point2d& p) {
    return std::isfinite(p.x) && std::isfinite(p.y) && p.x >= margin_px && p.y >= margin_px &&
           p.x <= model.width() - 1 - margin_px && p.y <= model.height() - 1 - margin_px;
  };
  // The sheet's four corners are among the points checked below: a cheap early rejection.
  for (const cv::Point2d& p : project_points(model, T_cam_board, outline))
    if (!inside(p)) return false;
  std::vector<cv::Point3d> pts = target.corners();
  constexpr int kSteps = 16;
  for (int e = 0; e < 4; ++e) {
    const cv::Point3d& a = outline[e];
    const cv::Point3d& b = outline[(e + 1) % 4];
    for (int s = 0; s < kSteps; ++s) pts.push_back(a + (b - a) * (static_cast<double>(s) / kSteps));
  }
  const auto proj = project_points(model, T_cam_board, pts);
  for (const auto& p : proj)
    if (!inside(p)) return false;
  // A board seen almost edge-on, or folded by the distortion model, is no use either: the
  // projected outline must stay convex and counter-clockwise-consistent.
  const auto quad = project_points(model, T_cam_board, outline);
  double sign = 0;
  for (int i = 0; i < 4; ++i) {
    const cv::Point2d a = quad[(i + 1) % 4] - quad[i], b = quad[(i + 2) % 4] - quad[(i + 1) % 4];
    const double z = a.x * b.y - a.y * b.x;
    if (sign == 0) sign = z;
    if (z * sign <= 0) return false;
  }
  return true;
}

std::optional<Pose> random_board_view(std::mt19937_64& rng, const CameraModel& model,
                                      const Target& target, const ViewSampling& s, int* draws) {
  if (draws) *draws = 0;
  std::uniform_real_distribution<double> U(0.0, 1.0);
  const cv::Size2d bs = target.board_size_m();
  const double pi = 3.14159265358979323846;
  for (int attempt = 0; attempt < s.max_tries; ++attempt) {
    if (draws) *draws = attempt + 1;
    const double frac =
        s.min_width_fraction + (s.max_width_fraction - s.min_width_fraction) * U(rng);
    const double depth = model.fx() * bs.width / (frac * model.width());
    const Eigen::Vector2d px(U(rng) * (model.width() - 1), U(rng) * (model.height() - 1));
    Eigen::Vector2d xn;
    if (!model.unproject(px, &xn)) continue;
    const Eigen::Vector3d centre(xn.x() * depth, xn.y() * depth, depth);
    // Tilt magnitude uniform in [0, max]: spreads views over the angular range.
    const double tilt = s.max_tilt_deg * pi / 180.0 * U(rng);
    const double axis = 2 * pi * U(rng);
    const double roll = (U(rng) - 0.5) * pi / 2;  // +-45 deg
    const Pose pose = board_pose_at(target, centre, axis, tilt, roll);
    if (board_fully_visible(model, target, pose, s.margin_px)) return pose;
  }
  return std::nullopt;
}

std::vector<Pose> random_board_views(uint64_t seed, int count, const CameraModel& model,
                                     const Target& target, const ViewSampling& sampling) {
  std::mt19937_64 rng(seed);
  std::vector<Pose> out;
  for (int i = 0; i < count; ++i) {
    auto p = random_board_view(rng, model, target, sampling);
    if (!p) {
      throw Error(ErrorCode::kInternal,
                  "no fully visible board view found: is the board larger than the view?");
    }
    out.push_back(*p);
  }
  return out;
}

std::vector<Pose> test_set_views(const CameraModel& model, const Target& target, int count) {
  ViewSampling s;
  s.max_tilt_deg = 50;
  s.min_width_fraction = 0.2;
  s.max_width_fraction = 0.8;
  return random_board_views(0x7e57'5e7ull, count, model, target, s);
}

}  // namespace posecal
