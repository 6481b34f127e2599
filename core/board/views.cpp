#include "board/views.hpp"

#include <cmath>

#include "common/error.hpp"

namespace posecal {

Pose board_pose_at(const Board& board, const Eigen::Vector3d& centre_cam, double tilt_axis_rad,
                   double tilt_rad, double roll_rad, const Eigen::Matrix3d& facing) {
  const Eigen::Vector3d axis(std::cos(tilt_axis_rad), std::sin(tilt_axis_rad), 0.0);
  const Eigen::Matrix3d R =
      facing * Eigen::AngleAxisd(roll_rad, Eigen::Vector3d::UnitZ()).toRotationMatrix() *
      Eigen::AngleAxisd(tilt_rad, axis).toRotationMatrix();
  const cv::Size2d bs = board.board_size_m();
  const Eigen::Vector3d centre_board(bs.width / 2, bs.height / 2, 0.0);
  return Pose::from_rotation(R, centre_cam - R * centre_board);
}

bool board_frame_at_pixel(const CameraModel& model, const Eigen::Vector2d& px, double depth,
                          Eigen::Vector3d* centre_cam, Eigen::Matrix3d* facing,
                          double fold_free_r) {
  if (!is_ray_model(model.lens_model())) {
    Eigen::Vector2d xn;
    if (!model.unproject(px, &xn, fold_free_r)) return false;
    *centre_cam = Eigen::Vector3d(xn.x(), xn.y(), 1.0) * depth;
    facing->setIdentity();
    return true;
  }
  Eigen::Vector3d ray;
  if (!model.unproject_ray(px, &ray)) return false;
  *centre_cam = ray * depth;
  // The least rotation taking z onto the ray: about z x ray by the angle between them (about x
  // for a ray straight behind the camera, which no model reaches).
  const Eigen::Vector3d axis = Eigen::Vector3d::UnitZ().cross(ray);
  const double s = axis.norm();
  const double angle = std::atan2(s, ray.z());
  *facing =
      s > 1e-12
          ? Eigen::AngleAxisd(angle, axis / s).toRotationMatrix()
          : (ray.z() > 0 ? Eigen::Matrix3d::Identity()
                         : Eigen::AngleAxisd(M_PI, Eigen::Vector3d::UnitX()).toRotationMatrix());
  return true;
}

bool board_fully_visible(const CameraModel& model, const Board& board, const Pose& T_cam_board,
                         double margin_px) {
  // The same points and arithmetic as project_points(), without its allocations: this runs in
  // every distance search of the pose generator and for every view candidate.
  const Eigen::Matrix3d R = T_cam_board.R();
  auto project_inside = [&](const cv::Point3d& P, Eigen::Vector2d* uv) {
    const Eigen::Vector3d pc = R * Eigen::Vector3d(P.x, P.y, P.z) + T_cam_board.t;
    if (!model.project(pc, uv)) return false;
    return std::isfinite(uv->x()) && std::isfinite(uv->y()) && uv->x() >= margin_px && uv->y() >= margin_px &&
           uv->x() <= model.width() - 1 - margin_px && uv->y() <= model.height() - 1 - margin_px;
  };
  const std::vector<cv::Point3d> outline = board.outline();
  // The sheet's four corners and a convex outline first: a cheap early rejection. A board seen
  // almost edge-on, or folded by the distortion model, is no use either.
  if (!board_outline_in_view(model, outline, R, T_cam_board.t, margin_px)) return false;
  Eigen::Vector2d uv;
  for (const cv::Point3d& c : board.corners())
    if (!project_inside(c, &uv)) return false;
  constexpr int kSteps = 16;
  for (int e = 0; e < 4; ++e) {
    const cv::Point3d& a = outline[e];
    const cv::Point3d& b = outline[(e + 1) % 4];
    for (int st = 0; st < kSteps; ++st)
      if (!project_inside(a + (b - a) * (static_cast<double>(st) / kSteps), &uv)) return false;
  }
  return true;
}

std::optional<Pose> random_board_view(std::mt19937_64& rng, const CameraModel& model,
                                      const Board& board, const ViewSampling& s, int* draws) {
  if (draws) *draws = 0;
  std::uniform_real_distribution<double> U(0.0, 1.0);
  const cv::Size2d bs = board.board_size_m();
  const double pi = 3.14159265358979323846;
  for (int attempt = 0; attempt < s.max_tries; ++attempt) {
    if (draws) *draws = attempt + 1;
    const double frac =
        s.min_width_fraction + (s.max_width_fraction - s.min_width_fraction) * U(rng);
    const double depth = model.fx() * bs.width / (frac * model.width());
    const Eigen::Vector2d px(U(rng) * (model.width() - 1), U(rng) * (model.height() - 1));
    Eigen::Vector3d centre;
    Eigen::Matrix3d facing;
    if (!board_frame_at_pixel(model, px, depth, &centre, &facing)) continue;
    // Tilt magnitude uniform in [0, max]: spreads views over the angular range.
    const double tilt = s.max_tilt_deg * pi / 180.0 * U(rng);
    const double axis = 2 * pi * U(rng);
    const double roll = (U(rng) - 0.5) * pi / 2;  // +-45 deg
    const Pose pose = board_pose_at(board, centre, axis, tilt, roll, facing);
    if (board_fully_visible(model, board, pose, s.margin_px)) return pose;
  }
  return std::nullopt;
}

ViewSampler::ViewSampler(const CameraModel& model, const Board& board, const ViewSampling& sampling)
    : model_(model), s_(sampling), outline_(board.outline()) {
  const cv::Size2d bs = board.board_size_m();
  centre_board_ = Eigen::Vector3d(bs.width / 2, bs.height / 2, 0.0);
  board_width_m_ = bs.width;
  fold_free_r_ = model.fold_free_radius();
  ray_model_ = is_ray_model(model.lens_model());
  // Any centre range lies within the image less the margins.
  reference_area_ = std::max(0.0, model.width() - 1 - 2 * s_.margin_px) * std::max(0.0, model.height() - 1 - 2 * s_.margin_px);
}

std::optional<Pose> ViewSampler::draw(std::mt19937_64& rng, int* draws, int max_tries) const {
  Eigen::Matrix3d R;
  Eigen::Vector3d t;
  if (!draw(rng, &R, &t, draws, max_tries)) return std::nullopt;
  return Pose::from_rotation(R, t);
}

namespace {

Eigen::Matrix3d view_rotation(const ViewDraw& v) {
  const Eigen::Vector3d ax(std::cos(v.tilt_axis_rad), std::sin(v.tilt_axis_rad), 0.0);
  return Eigen::AngleAxisd(v.roll_rad, Eigen::Vector3d::UnitZ()).toRotationMatrix() *
         Eigen::AngleAxisd(v.tilt_rad, ax).toRotationMatrix();
}

}  // namespace

bool ViewSampler::draw(std::mt19937_64& rng, Eigen::Matrix3d* R_out, Eigen::Vector3d* t_out, int* draws,
                       int max_tries) const {
  const int tries = max_tries < 0 ? s_.max_tries : max_tries;
  int used = 0;
  if (draws) *draws = 0;
  while (used < tries) {
    ViewDraw v;
    int d = 0;
    const bool fit = draw_view(rng, &v, &d, tries - used);
    used += d;
    if (draws) *draws = used;
    if (!fit) return false;
    if (realise(v, R_out, t_out)) return true;
  }
  return false;
}

bool ViewSampler::draw_view(std::mt19937_64& rng, ViewDraw* out, int* draws, int max_tries) const {
  if (draws) *draws = 0;
  std::uniform_real_distribution<double> U(0.0, 1.0);
  const double pi = 3.14159265358979323846;
  const double W = model_.width(), H = model_.height(), m = s_.margin_px;
  const int tries = max_tries < 0 ? s_.max_tries : max_tries;
  for (int attempt = 0; attempt < tries; ++attempt) {
    if (draws) *draws = attempt + 1;
    ViewDraw v;
    v.width_fraction = s_.min_width_fraction + (s_.max_width_fraction - s_.min_width_fraction) * U(rng);
    const double depth = model_.fx() * board_width_m_ / (v.width_fraction * W);
    v.tilt_rad = s_.max_tilt_deg * pi / 180.0 * U(rng);
    v.tilt_axis_rad = 2 * pi * U(rng);
    v.roll_rad = (U(rng) - 0.5) * pi / 2;
    const Eigen::Matrix3d R = view_rotation(v);
    // Pinhole extent of the outline around the projection of its centre, centre on the axis.
    double u0 = 1e300, u1 = -1e300, v0 = 1e300, v1 = -1e300;
    bool behind = false;
    for (const cv::Point3d& o : outline_) {
      const Eigen::Vector3d q = R * (Eigen::Vector3d(o.x, o.y, o.z) - centre_board_);
      const double z = depth + q.z();
      if (!(z > 1e-9)) {
        behind = true;
        break;
      }
      const double du = model_.fx() * q.x() / z, dv = model_.fy() * q.y() / z;
      u0 = std::min(u0, du), u1 = std::max(u1, du), v0 = std::min(v0, dv), v1 = std::max(v1, dv);
    }
    if (behind) continue;
    const double lo_u = m - u0, hi_u = W - 1 - m - u1, lo_v = m - v0, hi_v = H - 1 - m - v1;
    if (!(hi_u > lo_u && hi_v > lo_v)) continue;
    // Kept with probability proportional to the area its centre may take: the distribution of
    // drawing the centre anywhere in the image and rejecting.
    const double area = (hi_u - lo_u) * (hi_v - lo_v);
    if (!(U(rng) * reference_area_ < area)) continue;
    v.centre_px = Eigen::Vector2d(lo_u + (hi_u - lo_u) * U(rng), lo_v + (hi_v - lo_v) * U(rng));
    *out = v;
    return true;
  }
  return false;
}

bool board_outline_in_view(const CameraModel& model, const std::vector<cv::Point3d>& outline, const Eigen::Matrix3d& R,
                           const Eigen::Vector3d& t, double m) {
  if (outline.size() != 4) throw Error(ErrorCode::kInvalidArgument, "board_outline_in_view: the outline has 4 corners");
  const double W = model.width(), H = model.height();
  Eigen::Vector2d quad[4];
  for (int i = 0; i < 4; ++i) {
    const cv::Point3d& o = outline[i];
    if (!(model.project(R * Eigen::Vector3d(o.x, o.y, o.z) + t, &quad[i]) && quad[i].x() >= m && quad[i].y() >= m &&
          quad[i].x() <= W - 1 - m && quad[i].y() <= H - 1 - m)) {
      return false;
    }
  }
  double sign = 0;
  for (int i = 0; i < 4; ++i) {
    const Eigen::Vector2d a = quad[(i + 1) % 4] - quad[i], b = quad[(i + 2) % 4] - quad[(i + 1) % 4];
    const double z = a.x() * b.y() - a.y() * b.x();
    if (sign == 0) sign = z;
    if (!(z * sign > 0)) return false;
  }
  return true;
}

bool ViewSampler::realise(const ViewDraw& view, Eigen::Matrix3d* R_out, Eigen::Vector3d* t_out) const {
  if (!(view.width_fraction > 0)) return false;
  const double depth = model_.fx() * board_width_m_ / (view.width_fraction * model_.width());
  Eigen::Vector3d centre;
  Eigen::Matrix3d facing;
  if (!board_frame_at_pixel(model_, view.centre_px, depth, &centre, &facing, fold_free_r_))
    return false;
  const Eigen::Matrix3d R =
      ray_model_ ? Eigen::Matrix3d(facing * view_rotation(view)) : view_rotation(view);
  const Eigen::Vector3d t = centre - R * centre_board_;
  if (!board_outline_in_view(model_, outline_, R, t, s_.margin_px)) return false;
  *R_out = R;
  *t_out = t;
  return true;
}

std::vector<Pose> random_board_views(uint64_t seed, int count, const CameraModel& model,
                                     const Board& board, const ViewSampling& sampling) {
  std::mt19937_64 rng(seed);
  std::vector<Pose> out;
  for (int i = 0; i < count; ++i) {
    auto p = random_board_view(rng, model, board, sampling);
    if (!p) {
      // The camera (e.g. a model file's) and the board admit no view: an input, not a bug.
      throw Error(ErrorCode::kInvalidArgument,
                  "no fully visible view of the board in a " + std::to_string(model.width()) + "x" +
                      std::to_string(model.height()) + " camera with fx " +
                      std::to_string(model.fx()) +
                      ": is the board larger than the view, or the field of view too wide?");
    }
    out.push_back(*p);
  }
  return out;
}

std::vector<Pose> test_set_views(const CameraModel& model, const Board& board, int count) {
  ViewSampling s;
  s.max_tilt_deg = 50;
  s.min_width_fraction = 0.2;
  s.max_width_fraction = 0.8;
  return random_board_views(0x7e57'5e7ull, count, model, board, s);
}

}  // namespace posecal
