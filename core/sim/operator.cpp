#include "sim/operator.hpp"

#include <cmath>
#include <opencv2/calib3d.hpp>

#include "board/views.hpp"
#include "calib/pose_estimation.hpp"
#include "common/error.hpp"
#include "lens/geometry.hpp"

namespace posecal {

namespace {
constexpr double kPi = 3.14159265358979323846;

Eigen::Matrix3d small_rotation(double ax, double ay, double az) {
  return (Eigen::AngleAxisd(az, Eigen::Vector3d::UnitZ()) * Eigen::AngleAxisd(ay, Eigen::Vector3d::UnitY()) *
          Eigen::AngleAxisd(ax, Eigen::Vector3d::UnitX()))
      .toRotationMatrix();
}

Eigen::Vector3d board_centre(const Board& t) {
  const cv::Size2d bs = t.board_size_m();
  return {bs.width / 2, bs.height / 2, 0};
}
}  // namespace

bool OperatorOptions::is_valid(std::string* error) const {
  auto fail = [&](const std::string& w) {
    if (error) *error = w;
    return false;
  };
  if (!(rotation_error_deg >= 0 && rotation_error_deg < 45)) return fail("rotation error must be in [0, 45) deg");
  if (!(translation_error_fraction >= 0 && translation_error_fraction < 0.5)) return fail("translation error in [0, 0.5)");
  if (move_frames < 0 || move_frames > 100) return fail("move_frames must be in [0, 100]");
  if (bootstrap != BootstrapBoards::kFollowsGuidance && bootstrap != BootstrapBoards::kFixedTilt &&
      bootstrap != BootstrapBoards::kAnyBoard)
    return fail("unknown bootstrap behaviour");
  if (hold_frames < 2 || hold_frames > 100) return fail("hold_frames must be in [2, 100]");
  if (move_frames + hold_frames < 3) return fail("an attempt needs at least 3 frames");
  if (!(jitter_px >= 0 && jitter_px < 1.5)) return fail("jitter must be in [0, 1.5) px");
  if (max_tries < 1 || max_tries > 1000) return fail("max_tries must be in [1, 1000]");
  return true;
}

SimulatedOperator::SimulatedOperator(const CameraModel& truth, const Board& board,
                                     const OperatorOptions& options, uint64_t seed)
    : truth_(truth), board_(board), opt_(options), rng_(seed) {
  std::string why;
  if (!options.is_valid(&why)) throw Error(ErrorCode::kInvalidArgument, "operator options: " + why);
}

Pose SimulatedOperator::perturb(const Pose& p) {
  std::normal_distribution<double> N(0.0, 1.0);
  const double sr = opt_.rotation_error_deg * kPi / 180.0;
  const Eigen::Vector3d c = p.apply(board_centre(board_));
  const Eigen::Matrix3d R = small_rotation(sr * N(rng_), sr * N(rng_), sr * N(rng_)) * p.R();
  // Translation error: N(0, 2% of the distance) per axis. For fields of view narrower than the
  // C525's (width / f = 1.2) the lateral part shrinks with the view, so the error stays the same
  // in the image: nobody misaligns an overlay by a fifth of a telephoto's view
  // (docs/pose-selection.md).
  const double st = opt_.translation_error_fraction * c.norm();
  const double fov = std::min(1.0, truth_.width() / truth_.fx() / 1.2);
  const Eigen::Vector3d c2 = c + Eigen::Vector3d(st * fov * N(rng_), st * fov * N(rng_), st * N(rng_));
  return Pose::from_rotation(R, c2 - R * board_centre(board_));
}

const char* const kOperatorPresetNames = "approach, hold-only, sloppy, careless, robot";

OperatorOptions operator_preset(const std::string& name) {
  OperatorOptions o;
  if (name == "approach") return o;
  if (name == "robot") {
    o.kind = OperatorKind::kRobot;
    return o;
  }
  if (name == "sloppy") {
    o.rotation_error_deg = 4.0;
    o.translation_error_fraction = 0.04;
    return o;
  }
  if (name == "hold-only" || name == "careless") {
    o.move_frames = 0;
    o.hold_frames = 3;
    o.bootstrap = name == "careless" ? BootstrapBoards::kAnyBoard : BootstrapBoards::kFixedTilt;
    return o;
  }
  throw Error(ErrorCode::kInvalidArgument,
              "unknown operator '" + name + "' (" + kOperatorPresetNames + ")");
}

// The board, rotated by R about its centre, with its width `width_fraction` of the image's and
// its centre seen at pixel centre_px.
Pose SimulatedOperator::board_at(double width_fraction, const Eigen::Vector2d& centre_px, const Eigen::Matrix3d& R) const {
  const double depth = truth_.fx() * board_.board_size_m().width / (width_fraction * truth_.width());
  // A ray model's (fisheye's) board faces the camera where it is (board_frame_at_pixel).
  Eigen::Vector3d c;
  Eigen::Matrix3d facing;
  if (!board_frame_at_pixel(truth_, centre_px, depth, &c, &facing)) {
    c = Eigen::Vector3d(0, 0, depth);
    facing.setIdentity();
  }
  const Eigen::Matrix3d Rf = facing * R;
  return Pose::from_rotation(Rf, c - Rf * board_centre(board_));
}

Pose SimulatedOperator::bootstrap_goal() {
  std::normal_distribution<double> N(0.0, 1.0);
  std::uniform_real_distribution<double> U(-1.0, 1.0);
  const Eigen::Vector2d centre(truth_.cx(), truth_.cy());
  const Eigen::Vector2d size(truth_.width(), truth_.height());
  auto tilt_axis = [&]() {
    const double a = kPi * U(rng_);
    return Eigen::Vector3d(std::cos(a), std::sin(a), 0);
  };
  if (opt_.bootstrap == BootstrapBoards::kFixedTilt) {
    const double tilt = (17.5 + 7.5 * U(rng_)) * kPi / 180.0;
    const Eigen::Vector3d axis = tilt_axis();
    const double dx = U(rng_), dy = U(rng_);
    return board_at(0.55, centre + 0.1 * Eigen::Vector2d(size.x() * dx, size.y() * dy),
                    Eigen::AngleAxisd(tilt, axis).toRotationMatrix());
  }
  if (opt_.bootstrap == BootstrapBoards::kAnyBoard) {
    // Drawn until every corner is in the view (the person looks at the screen that far).
    Pose p;
    for (int draw = 0; draw < 200; ++draw) {
      const double frac = 0.6 + 0.3 * U(rng_);
      const double tilt = 30.0 * (1 + U(rng_)) * kPi / 180.0;
      const Eigen::Vector3d axis = tilt_axis();
      const double roll = 15.0 * kPi / 180.0 * N(rng_);
      const double dx = U(rng_), dy = U(rng_);
      const Eigen::Matrix3d R = Eigen::AngleAxisd(tilt, axis).toRotationMatrix() * small_rotation(0, 0, roll);
      p = board_at(frac, centre + 0.5 * (1 - frac) * Eigen::Vector2d(size.x() * dx, size.y() * dy), R);
      bool in_view = true;
      for (const auto& q : project_points(truth_, p, board_.corners()))
        in_view = in_view && q.x >= 0 && q.y >= 0 && q.x <= truth_.width() - 1 && q.y <= truth_.height() - 1;
      if (in_view) return p;
    }
    return p;
  }
  // A person first shows the board roughly fronto-parallel near the centre (paper §3.4); each
  // further attempt follows the guidance "tilt the board" a little more (10 degrees more per
  // attempt, up to 50), about a random in-plane axis.
  const double frac = 0.5 + 0.1 * U(rng_);
  const Eigen::Vector2d px(truth_.cx() + 0.1 * truth_.width() * U(rng_), truth_.cy() + 0.1 * truth_.height() * U(rng_));
  const double tilt = std::min(50.0, 10.0 * (1 + tries_)) * kPi / 180.0 * std::abs(N(rng_));
  const Eigen::Vector3d axis = tilt_axis();
  const Eigen::Matrix3d R = Eigen::AngleAxisd(tilt, axis).toRotationMatrix() *
                            small_rotation(0, 0, 5.0 * kPi / 180.0 * N(rng_));
  return board_at(frac, px, R);
}

Pose SimulatedOperator::attempt_goal(const GuidanceInfo& g) {
  if (!g.has_target) return bootstrap_goal();
  if (g.robot) return perturb(g.T_cam_board_target);
  // A person makes the board's image match the overlay, which is drawn with the engine's
  // current (imperfect) intrinsics: the pose that the TRUE camera sees as the overlay.
  std::vector<cv::Point3d> pts = board_.corners();
  for (const auto& o : board_.outline()) pts.push_back(o);
  const auto overlay = project_points(g.estimate, g.T_cam_board_target, pts);
  Pose aligned = g.T_cam_board_target;
  std::vector<cv::Point3d> obj;
  std::vector<cv::Point2d> img;
  for (size_t i = 0; i < pts.size(); ++i) {
    if (std::isfinite(overlay[i].x)) {
      obj.push_back(pts[i]);
      img.push_back(overlay[i]);
    }
  }
  if (is_ray_model(truth_.lens_model())) {
    // Rays, not the plane Z = 1: the overlay may lie beyond 90 degrees from the axis.
    std::vector<cv::Point3d> seen;
    std::vector<Eigen::Vector3d> rays;
    for (size_t i = 0; i < obj.size(); ++i) {
      Eigen::Vector3d ray;
      if (!truth_.unproject_ray(Eigen::Vector2d(img[i].x, img[i].y), &ray)) continue;
      seen.push_back(obj[i]);
      rays.push_back(ray);
    }
    Pose p;
    if (seen.size() >= 6 && pose_from_rays(seen, rays, &p)) aligned = p;
    return perturb(aligned);
  }
  const PnPInput in = pnp_input(truth_, obj, img);
  if (in.object.size() >= 6) {
    cv::Mat rvec = (cv::Mat_<double>(3, 1) << aligned.r.x(), aligned.r.y(), aligned.r.z());
    cv::Mat tvec = (cv::Mat_<double>(3, 1) << aligned.t.x(), aligned.t.y(), aligned.t.z());
    try {
      if (cv::solvePnP(in.object, in.image, in.K, in.dist, rvec, tvec, true)) {
        Pose p;
        p.r << rvec.at<double>(0), rvec.at<double>(1), rvec.at<double>(2);
        p.t << tvec.at<double>(0), tvec.at<double>(1), tvec.at<double>(2);
        if (p.is_finite() && p.t.z() > 0) aligned = p;
      }
    } catch (const cv::Exception&) {
    }
  }
  return perturb(aligned);
}

Pose SimulatedOperator::next_pose(const GuidanceInfo& g) {
  const int cycle = opt_.move_frames + opt_.hold_frames;
  auto start_attempt = [&]() {
    from_ = have_current_ ? current_ : attempt_goal(g);
    goal_ = attempt_goal(g);
    phase_frame_ = 0;
    in_attempt_ = true;
    ++stats_[kind_].attempts;
  };
  if (!g.finished) {
    if (g.target_serial != serial_) {
      // A target was reached when it gave a keyframe; the bootstrap, when a target appeared.
      if (in_attempt_ && (g.keyframes > keyframes_seen_ || (kind_ == "bootstrap" && g.has_target))) ++stats_[kind_].reached;
      serial_ = g.target_serial;
      kind_ = g.has_target ? target_kind_name(g.target_kind) : "bootstrap";
      tries_ = 0;
      gave_up_ = false;
      start_attempt();
    } else if (phase_frame_ >= cycle && !gave_up_) {
      // While bootstrapping the engine keeps asking; a person keeps trying.
      if (++tries_ < opt_.max_tries || !g.has_target) {
        start_attempt();
      } else {
        gave_up_ = true;
      }
    }
  } else if (in_attempt_ && g.keyframes > keyframes_seen_) {
    ++stats_[kind_].reached;
    in_attempt_ = false;
  }
  keyframes_seen_ = g.keyframes;

  Pose p;
  if (phase_frame_ < opt_.move_frames && in_attempt_) {
    // Moving: interpolate rotation (slerp) and translation towards the goal.
    const double a = (phase_frame_ + 1.0) / opt_.move_frames;
    const Eigen::Quaterniond q0(from_.R()), q1(goal_.R());
    const Eigen::Vector3d c0 = from_.apply(board_centre(board_)), c1 = goal_.apply(board_centre(board_));
    const Eigen::Matrix3d R = q0.slerp(a, q1).toRotationMatrix();
    p = Pose::from_rotation(R, (1 - a) * c0 + a * c1 - R * board_centre(board_));
  } else {
    // Holding: sub-pixel tremor.
    std::normal_distribution<double> N(0.0, 1.0);
    const double depth = std::max(0.05, goal_.apply(board_centre(board_)).z());
    const double s = opt_.jitter_px * depth / truth_.fx();
    p = goal_;
    p.t += Eigen::Vector3d(s * N(rng_), s * N(rng_), 0.0);
    if (phase_frame_ == opt_.move_frames && g.robot && g.has_target) reached_signal_ = true;
  }
  ++phase_frame_;
  current_ = p;
  have_current_ = true;
  return p;
}

bool SimulatedOperator::take_pose_reached() {
  const bool r = reached_signal_;
  reached_signal_ = false;
  return r;
}

CameraModel sample_camera(const CameraModel& reference, double rel_std, uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::normal_distribution<double> N(0.0, 1.0);
  for (int attempt = 0; attempt < 1000; ++attempt) {
    std::vector<double> p = reference.params();
    for (double& v : p) v += rel_std * v * N(rng);
    CameraModel m(reference.width(), reference.height(), reference.lens_model(), p);
    if (!m.is_valid()) continue;
    // The lens model must be one-to-one over the whole image (a fisheye's: wherever the
    // reference's is; the corners beyond its image circle see nothing).
    const int step = std::max(8, reference.width() / 64);
    const cv::Mat dm = m.distortion_map(step), ref = reference.distortion_map(step);
    bool ok = true;
    for (int i = 0; i < dm.rows && ok; ++i)
      for (int j = 0; j < dm.cols && ok; ++j)
        ok = std::isfinite(dm.at<float>(i, j)) || !std::isfinite(ref.at<float>(i, j));
    if (ok) return m;
  }
  throw Error(ErrorCode::kInternal, "could not sample a valid camera around the reference");
}

}  // namespace posecal
