#include "select/pose_rules.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <opencv2/imgproc.hpp>
#include <sstream>

#include "common/error.hpp"
#include "board/views.hpp"

namespace posecal {

namespace {
constexpr double kPi = 3.14159265358979323846;
double rad(double deg) { return deg * kPi / 180.0; }

std::string fmt(double v, int prec = 3) {
  std::ostringstream os;
  os.setf(std::ios::fixed);
  os.precision(prec);
  os << v;
  return os.str();
}
}  // namespace


double binary_subdivision(int n) {
  if (n < 0) throw Error(ErrorCode::kInvalidArgument, "binary_subdivision: n < 0");
  // Level L holds 2^L midpoints (2k + 1) / 2^(L + 1), k = 0 .. 2^L - 1, starting at L = 1.
  int level = 1;
  int count = 2;
  while (n >= count) {
    n -= count;
    ++level;
    count *= 2;
  }
  return (2.0 * n + 1.0) / std::pow(2.0, level + 1);
}

bool PoseGenOptions::is_valid(std::string* error) const {
  auto fail = [&](const std::string& w) {
    if (error) *error = w;
    return false;
  };
  if (!(max_tilt_deg > 0 && max_tilt_deg < 89)) return fail("max_tilt_deg must be in (0, 89)");
  if (!(std::abs(roll_deg) < 90)) return fail("roll_deg must be in (-90, 90)");
  if (!(shift_fraction >= 0 && shift_fraction < 0.4)) return fail("shift_fraction must be in [0, 0.4)");
  if (!(init_tilt_deg > 0 && init_tilt_deg < 89)) return fail("init_tilt_deg must be in (0, 89)");
  if (!(distortion_width_fraction > 0.05 && distortion_width_fraction <= 1)) {
    return fail("distortion_width_fraction must be in (0.05, 1]");
  }
  if (!(distortion_threshold_step > 0 && distortion_threshold_step < 0.5)) return fail("bad threshold step");
  if (!(mask_max_overlap > 0 && mask_max_overlap <= 1)) return fail("mask_max_overlap must be in (0, 1]");
  if (distortion_map_step_px < 1 || distortion_map_step_px > 100) return fail("distortion map step 1..100");
  if (!(border_margin_fraction >= 0 && border_margin_fraction < 0.2)) return fail("border margin in [0, 0.2)");
  if (!(fullscreen_fill > 0.3 && fullscreen_fill <= 1)) return fail("fullscreen_fill must be in (0.3, 1]");
  if (!(pinhole_fill > 0.1 && pinhole_fill <= 1)) return fail("pinhole_fill must be in (0.1, 1]");
  if (!(std::abs(distortion_tilt_deg) < 80)) return fail("distortion_tilt_deg must be in (-80, 80)");
  return true;
}

PoseGenerator::PoseGenerator(const Board& board, cv::Size image_size, const PoseGenOptions& options)
    : board_(board), size_(image_size), options_(options) {
  std::string why;
  if (!options.is_valid(&why)) throw Error(ErrorCode::kInvalidArgument, "pose generation options: " + why);
  if (image_size.width <= 0 || image_size.height <= 0) {
    throw Error(ErrorCode::kInvalidArgument, "pose generation: image size must be positive");
  }
  const int s = options.distortion_map_step_px;
  mask_ = cv::Mat::zeros((image_size.height + s - 1) / s, (image_size.width + s - 1) / s, CV_8U);
}

bool PoseGenerator::keep_in_view(const CameraModel& estimate, Pose* pose, std::string* note) const {
  const double margin = options_.border_margin_fraction * std::min(size_.width, size_.height);
  if (board_fully_visible(estimate, board_, *pose, margin)) return true;
  // Move back along the line of sight through the board's centre until it fits.
  const cv::Size2d bs = board_.board_size_m();
  const Eigen::Vector3d centre = pose->apply(Eigen::Vector3d(bs.width / 2, bs.height / 2, 0));
  const Eigen::Vector3d offset = pose->t - centre;
  const double d0 = centre.norm();
  double lo = 1.0, hi = 1.0;
  for (int i = 0; i < 40; ++i) {
    hi *= 1.25;
    Pose p = *pose;
    p.t = centre * hi + offset;
    if (board_fully_visible(estimate, board_, p, margin)) break;
    if (i == 39) return false;
  }
  for (int i = 0; i < 20; ++i) {
    const double mid = 0.5 * (lo + hi);
    Pose p = *pose;
    p.t = centre * mid + offset;
    (board_fully_visible(estimate, board_, p, margin) ? hi : lo) = mid;
  }
  pose->t = centre * hi + offset;
  if (note) {
    *note += (note->empty() ? "" : "; ");
    *note += "moved back from " + fmt(d0) + " m to " + fmt(d0 * hi) + " m to keep the whole board in view";
  }
  return true;
}

TargetPose PoseGenerator::pinhole_pose(int axis, double tilt_deg, double shift_px,
                                       const CameraModel& estimate) const {
  TargetPose out;
  out.kind = TargetKind::kPinhole;
  out.tilt_deg = tilt_deg;
  const cv::Size2d bs = board_.board_size_m();
  // Paper §3.3 steps 2-3: tilt about the parameter's axis, then roll about the optical axis.
  const Eigen::Vector3d tilt_axis = axis == 0 ? Eigen::Vector3d::UnitX() : Eigen::Vector3d::UnitY();
  const Eigen::Matrix3d R = Eigen::AngleAxisd(rad(options_.roll_deg), Eigen::Vector3d::UnitZ()).toRotationMatrix() *
                            Eigen::AngleAxisd(rad(tilt_deg), tilt_axis).toRotationMatrix();
  // Step 1: distance such that the whole board is visible; nominally the untilted board covers
  // 60% of the limiting image dimension, moved back if the tilted board would leave the view.
  const double d_nominal = std::max(estimate.fx() * bs.width / (options_.pinhole_fill * size_.width),
                                    estimate.fy() * bs.height / (options_.pinhole_fill * size_.height));
  // Step 4: shift the board's centre along the image axis (cx: x, cy: y).
  Eigen::Vector2d px(estimate.cx(), estimate.cy());
  px[axis == 0 ? 1 : 0] += shift_px;
  // A ray model's board faces the camera (board_frame_at_pixel), the tilt is about its own axes.
  Eigen::Vector3d centre;
  Eigen::Matrix3d facing;
  if (!board_frame_at_pixel(estimate, px, d_nominal, &centre, &facing)) {
    centre = Eigen::Vector3d((px.x() - estimate.cx()) / estimate.fx(),
                             (px.y() - estimate.cy()) / estimate.fy(), 1.0) *
             d_nominal;
    facing.setIdentity();
  }
  const Eigen::Matrix3d Rf = facing * R;
  out.T_cam_board =
      Pose::from_rotation(Rf, centre - Rf * Eigen::Vector3d(bs.width / 2, bs.height / 2, 0));
  if (!keep_in_view(estimate, &out.T_cam_board, &out.note)) {
    out.note += (out.note.empty() ? "" : "; ");
    out.note += "board cannot be fully visible at this tilt";
  }
  return out;
}

TargetPose PoseGenerator::initial_pose(int index, const CameraModel& estimate, int retry) const {
  if (retry < 0) throw Error(ErrorCode::kInvalidArgument, "initial_pose: retry must be >= 0");
  if (index == 0) {
    const double tilt = retry == 0 ? options_.init_tilt_deg : std::max(std::min(25.0, options_.init_tilt_deg),
                                                                       options_.init_tilt_deg - 10.0 * retry);
    TargetPose p = pinhole_pose(0, tilt, 0.0, estimate);
    p.kind = TargetKind::kInitTilted;
    return p;
  }
  if (index != 1) throw Error(ErrorCode::kInvalidArgument, "initial_pose: index must be 0 or 1");
  // Board parallel to the image plane covering the view: the depth must fit BOTH image axes
  // (the reference implementation fitted only one, so the board overflowed vertically).
  TargetPose out;
  out.kind = TargetKind::kInitFrontoParallel;
  const cv::Size2d bs = board_.board_size_m();
  const double fill = options_.fullscreen_fill * (1.0 - 2.0 * options_.border_margin_fraction);
  const double Z = std::max(estimate.fx() * bs.width / (fill * size_.width),
                            estimate.fy() * bs.height / (fill * size_.height));
  Eigen::Vector2d xn;
  if (!estimate.unproject(Eigen::Vector2d(estimate.cx(), estimate.cy()), &xn)) xn.setZero();
  const Eigen::Vector3d centre(xn.x() * Z, xn.y() * Z, Z);
  out.T_cam_board = Pose::from_rotation(Eigen::Matrix3d::Identity(),
                                        centre - Eigen::Vector3d(bs.width / 2, bs.height / 2, 0));
  keep_in_view(estimate, &out.T_cam_board, &out.note);
  return out;
}

std::vector<TargetPose> PoseGenerator::distortion_candidates(const CameraModel& estimate, int count) const {
  const int step = options_.distortion_map_step_px;
  const cv::Mat dmap = estimate.distortion_map(step);
  // Normalise the finite displacements to 0..255; cells without a preimage stay 0 (never a
  // target: no board can be seen there).
  double mn = 1e300, mx = -1e300;
  for (int i = 0; i < dmap.rows; ++i)
    for (int j = 0; j < dmap.cols; ++j) {
      const float v = dmap.at<float>(i, j);
      if (std::isfinite(v)) mn = std::min(mn, static_cast<double>(v)), mx = std::max(mx, static_cast<double>(v));
    }
  if (!(mx > mn)) return {};
  cv::Mat norm(dmap.size(), CV_8U);
  for (int i = 0; i < dmap.rows; ++i)
    for (int j = 0; j < dmap.cols; ++j) {
      const float v = dmap.at<float>(i, j);
      norm.at<uchar>(i, j) = std::isfinite(v) ? static_cast<uchar>(std::lround(255.0 * (v - mn) / (mx - mn))) : 0;
    }
  // Paper §3.3 (C_Delta) steps 1-3: lower the threshold until a region appears whose box is not
  // already visited; the strongest distortion is found first. Further candidates are the next
  // distinct regions found as the threshold keeps falling.
  std::vector<cv::Rect> boxes;
  cv::Mat claimed = mask_.clone();
  for (double t = 1.0 - options_.distortion_threshold_step; t >= 0 && static_cast<int>(boxes.size()) < count;
       t -= options_.distortion_threshold_step) {
    cv::Mat bin;
    cv::threshold(norm, bin, t * 255.0, 255, cv::THRESH_BINARY);
    std::vector<std::vector<cv::Point>> contours;
    cv::findContours(bin, contours, cv::RETR_EXTERNAL, cv::CHAIN_APPROX_NONE);
    std::sort(contours.begin(), contours.end(), [](const auto& a, const auto& b) {
      return cv::contourArea(a) + a.size() > cv::contourArea(b) + b.size();
    });
    for (const auto& c : contours) {
      const cv::Rect r = cv::boundingRect(c);
      if (r.area() == 0) continue;
      if (cv::countNonZero(mask_(r)) / static_cast<double>(r.area()) > options_.mask_max_overlap) continue;
      if (cv::countNonZero(claimed(r)) / static_cast<double>(r.area()) > options_.mask_max_overlap) continue;
      boxes.push_back(r);
      claimed(r).setTo(1);  // later candidates must be other regions
      if (static_cast<int>(boxes.size()) >= count) break;
    }
  }
  std::vector<TargetPose> out;
  for (const auto& b : boxes) out.push_back(distortion_pose_for(estimate, b));
  return out;
}

TargetPose PoseGenerator::distortion_pose_for(const CameraModel& estimate, const cv::Rect& box) const {
  const int step = options_.distortion_map_step_px;
  const cv::Rect region(box.x * step, box.y * step, box.width * step, box.height * step);
  // Step 4: a board parallel to the image plane, its top-left corner at the box's top-left, at a
  // depth where it covers distortion_width_fraction of the image width (rotated 90 degrees for
  // tall boxes), clipped to the image.
  const cv::Size2d bs = board_.board_size_m();
  const bool rot90 = region.height > region.width;
  const double long_m = std::max(bs.width, bs.height), short_m = std::min(bs.width, bs.height);
  const double long_px = std::max<double>(rot90 ? region.height : region.width,
                                          options_.distortion_width_fraction * size_.width);
  const double short_px = long_px * short_m / long_m;
  const double Z = (rot90 ? estimate.fy() : estimate.fx()) * long_m / long_px;
  const double w_px = rot90 ? short_px : long_px, h_px = rot90 ? long_px : short_px;
  const double margin = options_.border_margin_fraction * std::min(size_.width, size_.height);
  const double x0 = std::clamp<double>(region.x, margin, std::max(margin, size_.width - 1 - margin - w_px));
  const double y0 = std::clamp<double>(region.y, margin, std::max(margin, size_.height - 1 - margin - h_px));
  // Board x along the long side: R = I (x right) or a 90 degree roll (x down, y left, so the
  // board's origin sits at the footprint's top-right).
  const Eigen::Matrix3d R = rot90 ? Eigen::AngleAxisd(kPi / 2, Eigen::Vector3d::UnitZ()).toRotationMatrix()
                                  : Eigen::Matrix3d::Identity();
  TargetPose out;
  out.kind = TargetKind::kDistortion;
  out.region = region;
  Pose pose;
  bool placed = false;
  const double cxi = 0.5 * size_.width, cyi = 0.5 * size_.height;
  const bool ray_model = is_ray_model(estimate.lens_model());
  for (int k = 0; k <= 20 && !placed && ray_model; ++k) {
    // A ray model (the fisheye): the board faces the camera, centred on the footprint's centre at
    // the distance where it spans long_px (equidistant: image size = f x angle), and steps
    // towards the image centre until it fits.
    const double f = k / 20.0;
    const Eigen::Vector2d c0(x0 + w_px / 2, y0 + h_px / 2);
    const Eigen::Vector2d c = c0 + f * (Eigen::Vector2d(cxi, cyi) - c0);
    Eigen::Vector3d centre;
    Eigen::Matrix3d facing;
    if (!board_frame_at_pixel(estimate, c, Z, &centre, &facing)) continue;
    const Eigen::Matrix3d Rf = facing * R;
    pose = Pose::from_rotation(Rf, centre - Rf * Eigen::Vector3d(bs.width / 2, bs.height / 2, 0));
    if (board_fully_visible(estimate, board_, pose, margin)) {
      placed = true;
      if (k > 0)
        out.note = "shifted " + std::to_string(k * 5) + "% towards the centre to stay in view";
    }
  }
  for (int k = 0; k <= 20 && !placed && !ray_model; ++k) {
    // Distortion bends the footprint; step towards the image centre until the board fits.
    const double f = k / 20.0;
    const double ox = x0 + f * (cxi - (x0 + w_px / 2)), oy = y0 + f * (cyi - (y0 + h_px / 2));
    const Eigen::Vector2d origin_px(rot90 ? ox + w_px : ox, oy);
    Eigen::Vector2d xn;
    if (!estimate.unproject(origin_px, &xn)) continue;
    pose = Pose::from_rotation(R, Eigen::Vector3d(xn.x(), xn.y(), 1.0) * Z);
    if (board_fully_visible(estimate, board_, pose, margin)) {
      placed = true;
      if (k > 0) out.note = "shifted " + std::to_string(k * 5) + "% towards the centre to stay in view";
    }
  }
  if (!placed) keep_in_view(estimate, &pose, &out.note);
  if (options_.distortion_tilt_deg != 0.0) {
    // Tilt about the board's centre, about the axis perpendicular to the direction from the
    // image centre, so the pose also carries perspective (pinhole) information.
    const Eigen::Vector3d c = pose.apply(Eigen::Vector3d(bs.width / 2, bs.height / 2, 0));
    Eigen::Vector3d radial(c.x(), c.y(), 0.0);  // towards the centre's ray (also beyond 90 degrees)
    if (radial.norm() < 1e-6 * c.norm()) radial = Eigen::Vector3d::UnitX();
    const Eigen::Vector3d axis = Eigen::Vector3d::UnitZ().cross(radial.normalized());
    const Eigen::Matrix3d Rt = Eigen::AngleAxisd(options_.distortion_tilt_deg * kPi / 180.0, axis).toRotationMatrix();
    const Eigen::Matrix3d Rn = Rt * pose.R();
    pose = Pose::from_rotation(Rn, c - Rn * Eigen::Vector3d(bs.width / 2, bs.height / 2, 0));
    keep_in_view(estimate, &pose, &out.note);
  }
  out.T_cam_board = pose;
  // The cells this visit masks (paper §3.3, step 3): the region plus the board's footprint,
  // grown by the border margin (the strip between the board and the image border belongs to
  // this visit, or the search would find the same corner again and again).
  cv::Rect covered = box;
  const auto outline = projected_outline(estimate, board_, pose, 4);
  if (!outline.empty()) {
    std::vector<cv::Point> cells;
    const int grow = static_cast<int>(std::ceil(margin / step)) + 1;
    for (const auto& p : outline) cells.emplace_back(static_cast<int>(p.x / step), static_cast<int>(p.y / step));
    cv::Rect fp = cv::boundingRect(cells);
    fp = cv::Rect(fp.x - grow, fp.y - grow, fp.width + 2 * grow, fp.height + 2 * grow);
    covered |= fp;
  }
  out.mask_cells = covered & cv::Rect(0, 0, mask_.cols, mask_.rows);
  return out;
}

int PoseGenerator::pinhole_poses_generated(int axis) const {
  return static_cast<int>(std::count(used_[axis].begin(), used_[axis].end(), true));
}

std::vector<TargetPose> PoseGenerator::candidates(int param_index, const CameraModel& estimate, int count) {
  if (param_index < 0 || param_index >= estimate.num_params()) {
    throw Error(ErrorCode::kInvalidArgument, "pose generation: no parameter " + std::to_string(param_index));
  }
  if (count < 1) throw Error(ErrorCode::kInvalidArgument, "pose generation: need at least one candidate");
  if (param_group(param_index) == ParamGroup::kDistortion) {
    auto c = distortion_candidates(estimate, count);
    if (!c.empty()) return c;
    // No distorted region left: fall back to C_K poses on the axis used least so far.
    const int axis = pinhole_poses_generated(0) <= pinhole_poses_generated(1) ? 0 : 1;
    auto p = candidates(axis == 0 ? 1 : 0, estimate, count);
    for (auto& t : p) t.note = "no distorted region left to visit: pinhole pose instead" + (t.note.empty() ? "" : "; " + t.note);
    return p;
  }
  // fx, cx: tilt about y; fy, cy: tilt about x (paper §3.3 step 2: x for fy).
  const int axis = (param_index == 0 || param_index == 2) ? 1 : 0;
  const bool shifted = param_index >= 2;
  std::vector<TargetPose> out;
  constexpr int kSequenceLength = 1 << 12;  // angles closer than 0.03 deg apart: start over
  if (pinhole_poses_generated(axis) >= kSequenceLength) used_[axis].clear();
  for (int n = 0; static_cast<int>(out.size()) < count && n < kSequenceLength; ++n) {
    if (n < static_cast<int>(used_[axis].size()) && used_[axis][n]) continue;
    const double tilt = -options_.max_tilt_deg + 2.0 * options_.max_tilt_deg * binary_subdivision(n);
    const double size = axis == 1 ? size_.width : size_.height;
    // Step 4 alternates the shift sign; the alternative sign is a further candidate.
    for (int sign : shifted ? std::vector<int>{shift_sign_[axis], -shift_sign_[axis]} : std::vector<int>{0}) {
      if (static_cast<int>(out.size()) >= count) break;
      TargetPose t = pinhole_pose(axis, tilt, options_.shift_fraction * size * sign, estimate);
      t.axis = axis;
      t.sequence_index = n;
      t.shift_sign = sign;
      out.push_back(t);
    }
  }
  return out;
}

void PoseGenerator::commit(const TargetPose& t) {
  if (t.kind == TargetKind::kPinhole && t.axis >= 0 && t.sequence_index >= 0) {
    auto& used = used_[t.axis];
    if (static_cast<int>(used.size()) <= t.sequence_index) used.resize(t.sequence_index + 1, false);
    used[t.sequence_index] = true;
    if (t.shift_sign != 0) shift_sign_[t.axis] = -t.shift_sign;
  } else if (t.kind == TargetKind::kDistortion) {
    mask_(t.mask_cells & cv::Rect(0, 0, mask_.cols, mask_.rows)).setTo(1);
  }
}

TargetPose PoseGenerator::next_pose(int param_index, const CameraModel& estimate, const PoseScorer& scorer,
                                    int count) {
  auto c = candidates(param_index, estimate, scorer ? count : 1);
  if (c.empty()) throw Error(ErrorCode::kInternal, "pose generation produced no candidate");
  size_t best = 0;
  if (scorer && c.size() > 1) {
    double best_score = std::numeric_limits<double>::infinity();
    for (size_t i = 0; i < c.size(); ++i) {
      const double sc = scorer(c[i]);
      if (sc < best_score) best_score = sc, best = i;
    }
  }
  commit(c[best]);
  return c[best];
}

std::vector<cv::Point2d> projected_outline(const CameraModel& model, const Board& board,
                                           const Pose& pose, int points_per_edge) {
  const auto o = board.outline();
  std::vector<cv::Point3d> pts;
  for (int e = 0; e < 4; ++e)
    for (int k = 0; k < points_per_edge; ++k)
      pts.push_back(o[e] + (o[(e + 1) % 4] - o[e]) * (static_cast<double>(k) / points_per_edge));
  auto proj = project_points(model, pose, pts);
  for (const auto& p : proj)
    if (!std::isfinite(p.x) || !std::isfinite(p.y)) return {};
  return proj;
}

double board_jaccard(const CameraModel& model, const Board& board, const Pose& a, const Pose& b,
                     int raster_scale) {
  const auto pa = projected_outline(model, board, a), pb = projected_outline(model, board, b);
  if (pa.empty() || pb.empty()) return 0.0;
  const cv::Size sz((model.width() + raster_scale - 1) / raster_scale,
                    (model.height() + raster_scale - 1) / raster_scale);
  auto raster = [&](const std::vector<cv::Point2d>& poly) {
    cv::Mat m = cv::Mat::zeros(sz, CV_8U);
    std::vector<cv::Point> q;
    // Fixed-point vertices (4 fractional bits) for sub-cell precision.
    for (const auto& p : poly) {
      q.emplace_back(static_cast<int>(std::lround((p.x + 0.5) / raster_scale * 16.0)),
                     static_cast<int>(std::lround((p.y + 0.5) / raster_scale * 16.0)));
    }
    cv::fillPoly(m, std::vector<std::vector<cv::Point>>{q}, cv::Scalar(1), cv::LINE_8, 4);
    return m;
  };
  const cv::Mat ma = raster(pa), mb = raster(pb);
  const int inter = cv::countNonZero(ma & mb), uni = cv::countNonZero(ma | mb);
  return uni > 0 ? static_cast<double>(inter) / uni : 0.0;
}

}  // namespace posecal
