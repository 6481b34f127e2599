// Pose generation rules (paper §3.3, §3.4), one test per rule.
#include <gtest/gtest.h>

#include <optional>
#include <random>

#include "board/views.hpp"
#include "common/error.hpp"
#include "lens/reference_models.hpp"
#include "select/pose_rules.hpp"

using namespace posecal;

namespace {

constexpr double kDeg = M_PI / 180.0;

// Undo the 22.5 degree roll and read the tilt: R = Rz(roll) * R_axis(tilt).
void roll_and_tilt(const Pose& p, double roll_deg, Eigen::Vector3d* axis, double* tilt_deg) {
  const Eigen::Matrix3d R = Eigen::AngleAxisd(-roll_deg * kDeg, Eigen::Vector3d::UnitZ()).toRotationMatrix() * p.R();
  const Eigen::AngleAxisd aa(R);
  *axis = aa.axis();
  *tilt_deg = aa.angle() / kDeg;
}

Eigen::Vector2d centre_pixel(const CameraModel& m, const Board& t, const Pose& p) {
  const cv::Size2d bs = t.board_size_m();
  Eigen::Vector2d uv;
  m.project(p.apply(Eigen::Vector3d(bs.width / 2, bs.height / 2, 0)), &uv);
  return uv;
}

}  // namespace

TEST(PoseGen, BinarySubdivisionSequence) {
  const double expected[] = {0.25, 0.75, 0.125, 0.375, 0.625, 0.875, 0.0625, 0.1875};
  for (int i = 0; i < 8; ++i) EXPECT_DOUBLE_EQ(binary_subdivision(i), expected[i]) << i;
  EXPECT_THROW(binary_subdivision(-1), Error);
}

TEST(PoseGen, PinholeTiltsFollowTheSequencePerAxisWithRoll) {
  const CameraModel cam = c525_reference_model();
  const Board t;
  PoseGenerator pg(t, cam.size());
  // fx: tilt about y; the first angles are -70 + 140 * (0.25, 0.75, 0.125, 0.375).
  const double fx_angles[] = {-35.0, 35.0, -52.5, -17.5};
  for (double want : fx_angles) {
    const TargetPose p = pg.next_pose(0, cam);
    EXPECT_EQ(p.kind, TargetKind::kPinhole);
    Eigen::Vector3d axis;
    double tilt;
    roll_and_tilt(p.T_cam_board, 22.5, &axis, &tilt);
    EXPECT_NEAR(std::abs(tilt), std::abs(want), 1e-6);
    EXPECT_NEAR(std::abs(axis.y()), 1.0, 1e-9);  // about y
    EXPECT_NEAR(axis.y() * tilt, want, 1e-6);    // signed angle
    EXPECT_NEAR(p.tilt_deg, want, 1e-9);
  }
  // fy starts its own sequence, about x.
  const TargetPose q = pg.next_pose(1, cam);
  Eigen::Vector3d axis;
  double tilt;
  roll_and_tilt(q.T_cam_board, 22.5, &axis, &tilt);
  EXPECT_NEAR(std::abs(axis.x()), 1.0, 1e-9);
  EXPECT_NEAR(axis.x() * tilt, -35.0, 1e-6);
  EXPECT_EQ(pg.pinhole_poses_generated(1), 4);
  EXPECT_EQ(pg.pinhole_poses_generated(0), 1);
}

TEST(PoseGen, PrincipalPointPosesShiftFivePercentWithAlternatingSign) {
  const CameraModel cam = CameraModel::opencv5(1280, 720, 1000, 1000, 639.5, 359.5, {0, 0, 0, 0, 0});
  const Board t;
  PoseGenerator pg(t, cam.size());
  double prev_sign = 0;
  for (int k = 0; k < 4; ++k) {
    const TargetPose p = pg.next_pose(2, cam);  // cx: shift along x by 5% of 1280 = 64 px
    const Eigen::Vector2d c = centre_pixel(cam, t, p.T_cam_board);
    EXPECT_NEAR(std::abs(c.x() - cam.cx()), 64.0, 1e-6);
    EXPECT_NEAR(c.y(), cam.cy(), 1e-6);
    const double sign = c.x() > cam.cx() ? 1 : -1;
    if (k > 0) {
      EXPECT_EQ(sign, -prev_sign);
    }
    prev_sign = sign;
  }
  const TargetPose py = pg.next_pose(3, cam);  // cy: along y by 5% of 720 = 36 px
  const Eigen::Vector2d c = centre_pixel(cam, t, py.T_cam_board);
  EXPECT_NEAR(std::abs(c.y() - cam.cy()), 36.0, 1e-6);
  EXPECT_NEAR(c.x(), cam.cx(), 1e-6);
}

TEST(PoseGen, EveryGeneratedPoseIsFullyVisible) {
  const Board t;
  const std::vector<CameraModel> cams = {
      c525_reference_model(),
      CameraModel::opencv5(2448, 2048, 2320, 2320, 1223.5, 1023.5, {-0.30, 0.12, 0.0005, -0.0004, -0.02}),
      CameraModel::opencv5(1600, 1200, 11300, 11300, 799.5, 599.5, {-0.02, 0.05, 0, 0, 0})};
  for (const auto& cam : cams) {
    PoseGenerator pg(t, cam.size());
    const double margin = PoseGenOptions{}.border_margin_fraction * std::min(cam.width(), cam.height());
    for (int k = 0; k < 2; ++k) EXPECT_TRUE(board_fully_visible(cam, t, pg.initial_pose(k, cam).T_cam_board, margin * 0.99));
    for (int i = 0; i < 30; ++i) {
      const TargetPose p = pg.next_pose(i % 9, cam);
      EXPECT_TRUE(board_fully_visible(cam, t, p.T_cam_board, margin * 0.99))
          << cam.width() << "x" << cam.height() << " param " << i % 9 << " " << target_kind_name(p.kind) << " " << p.note;
    }
  }
}

TEST(PoseGen, DistortionPosesVisitRegionsStrongestFirstAndMaskThem) {
  // Barrel distortion with the principal point right of centre: the left corners are the most
  // distorted, so the first region is on the left.
  const CameraModel cam = CameraModel::opencv5(1280, 720, 1000, 1000, 760, 359.5, {-0.25, 0.05, 0, 0, 0});
  const Board t;
  PoseGenerator pg(t, cam.size());
  const int step = PoseGenOptions{}.distortion_map_step_px;
  const cv::Mat dmap = cam.distortion_map(step);
  std::vector<double> strength;
  for (int k = 0; k < 4; ++k) {
    const TargetPose p = pg.next_pose(4, cam);
    ASSERT_EQ(p.kind, TargetKind::kDistortion) << k;
    // Mean displacement inside the region this pose samples.
    const cv::Rect cells(p.region.x / step, p.region.y / step, std::max(1, p.region.width / step),
                         std::max(1, p.region.height / step));
    double mx = 0;
    cv::minMaxLoc(dmap(cells & cv::Rect(0, 0, dmap.cols, dmap.rows)), nullptr, &mx);
    strength.push_back(mx);
    if (k == 0) {
      EXPECT_LT(p.region.x, 640) << "strongest distortion is on the left";
    }
    // The region is masked afterwards.
    EXPECT_GT(cv::countNonZero(pg.distortion_mask()(cells & cv::Rect(0, 0, dmap.cols, dmap.rows))), 0);
  }
  // The first region holds the strongest distortion of the whole map; later ones are weaker.
  double global = 0;
  cv::minMaxLoc(dmap, nullptr, &global);
  EXPECT_NEAR(strength[0], global, 1e-3);
  for (int k = 1; k < 4; ++k) EXPECT_LE(strength[k], strength[0]) << k;
}

TEST(PoseGen, DistortionBoardIsParallelAndCoversAThirdOfTheWidth) {
  const CameraModel cam = CameraModel::opencv5(1280, 720, 1000, 1000, 639.5, 359.5, {-0.2, 0.03, 0, 0, 0});
  const Board t;
  PoseGenOptions o;
  PoseGenerator pg(t, cam.size(), o);
  const TargetPose p = pg.next_pose(4, cam);
  ASSERT_EQ(p.kind, TargetKind::kDistortion);
  // Parallel to the image plane: the board normal is the optical axis (maybe rolled 90 deg).
  EXPECT_NEAR(p.T_cam_board.R().col(2).z(), 1.0, 1e-9);
  // Long side in pixels (pinhole part) = 33% of the width, unless the region is wider.
  const cv::Size2d bs = t.board_size_m();
  const double depth = p.T_cam_board.t.z();
  const double long_px = cam.fx() * std::max(bs.width, bs.height) / depth;
  EXPECT_NEAR(long_px, std::max<double>(0.33 * 1280, std::max(p.region.width, p.region.height)), 1.0);
}

TEST(PoseGen, TallRegionsGetARotatedBoard) {
  // Principal point far right: the whole left edge is strongly distorted, a tall region.
  const CameraModel cam = CameraModel::opencv5(1280, 720, 1000, 1000, 1150, 359.5, {-0.2, 0.03, 0, 0, 0});
  const Board t;
  PoseGenerator pg(t, cam.size());
  bool saw_rotated = false;
  for (int k = 0; k < 6; ++k) {
    const TargetPose p = pg.next_pose(4, cam);
    if (p.kind != TargetKind::kDistortion) break;
    if (p.region.height > p.region.width) {
      // Board x (its long side) runs along the image's y axis.
      EXPECT_NEAR(std::abs(p.T_cam_board.R()(1, 0)), 1.0, 1e-9);
      saw_rotated = true;
    }
  }
  EXPECT_TRUE(saw_rotated);
}

TEST(PoseGen, FallsBackToAPinholePoseWhenNoRegionIsLeft) {
  const CameraModel cam = CameraModel::opencv5(1280, 720, 1000, 1000, 639.5, 359.5, {-0.2, 0.03, 0, 0, 0});
  const Board t;
  PoseGenerator pg(t, cam.size());
  TargetPose p;
  int k = 0;
  for (; k < 200; ++k) {
    p = pg.next_pose(5, cam);
    if (p.kind != TargetKind::kDistortion) break;
  }
  ASSERT_LT(k, 200) << "the mask never filled";
  EXPECT_EQ(p.kind, TargetKind::kPinhole);
  EXPECT_NE(p.note.find("no distorted region left"), std::string::npos) << p.note;
}

TEST(PoseGen, InitialPoses) {
  const CameraModel cam = c525_reference_model();
  const Board t;
  PoseGenerator pg(t, cam.size());
  const TargetPose a = pg.initial_pose(0, cam);
  Eigen::Vector3d axis;
  double tilt;
  roll_and_tilt(a.T_cam_board, 22.5, &axis, &tilt);
  EXPECT_NEAR(tilt, 45.0, 1e-6);
  EXPECT_NEAR(std::abs(axis.x()), 1.0, 1e-9);
  const TargetPose b = pg.initial_pose(1, cam);
  EXPECT_NEAR(b.T_cam_board.R().col(2).z(), 1.0, 1e-12);  // parallel to the image plane
  // Covers the view along its limiting axis without overflowing the other (the reference
  // implementation overflowed vertically).
  const auto o = projected_outline(cam, t, b.T_cam_board, 8);
  double x0 = 1e9, x1 = -1e9, y0 = 1e9, y1 = -1e9;
  for (const auto& p : o) x0 = std::min(x0, p.x), x1 = std::max(x1, p.x), y0 = std::min(y0, p.y), y1 = std::max(y1, p.y);
  EXPECT_GT(x0, 0);
  EXPECT_GT(y0, 0);
  EXPECT_LT(x1, cam.width() - 1);
  EXPECT_LT(y1, cam.height() - 1);
  EXPECT_GT(std::max((x1 - x0) / cam.width(), (y1 - y0) / cam.height()), 0.85);
  EXPECT_THROW(pg.initial_pose(2, cam), Error);
  // Offered again after a timeout: 10 degrees less tilted each time, down to 25.
  EXPECT_DOUBLE_EQ(pg.initial_pose(0, cam, 1).tilt_deg, 35.0);
  EXPECT_DOUBLE_EQ(pg.initial_pose(0, cam, 2).tilt_deg, 25.0);
  EXPECT_DOUBLE_EQ(pg.initial_pose(0, cam, 7).tilt_deg, 25.0);
  EXPECT_EQ(pg.initial_pose(1, cam, 3).T_cam_board.t, b.T_cam_board.t);
  EXPECT_THROW(pg.initial_pose(0, cam, -1), Error);
}

TEST(PoseGen, JaccardIndex) {
  const CameraModel cam = c525_reference_model();
  const Board t;
  const Pose p = board_pose_at(t, Eigen::Vector3d(0, 0, 0.5), 0, 0.2, 0.1);
  EXPECT_NEAR(board_jaccard(cam, t, p, p), 1.0, 1e-9);
  Pose shifted = p;
  shifted.t.x() += 0.05;
  const double j = board_jaccard(cam, t, p, shifted);
  EXPECT_GT(j, 0.3);
  EXPECT_LT(j, 0.9);
  Pose far = p;
  far.t.x() += 1.0;
  EXPECT_EQ(board_jaccard(cam, t, p, far), 0.0);
  Pose behind = p;
  behind.t.z() = -1;
  EXPECT_EQ(board_jaccard(cam, t, p, behind), 0.0);
}

TEST(PoseGen, OptionsValidate) {
  PoseGenOptions o;
  std::string why;
  EXPECT_TRUE(o.is_valid(&why)) << why;
  o.max_tilt_deg = 95;
  EXPECT_FALSE(o.is_valid(&why));
  o = {};
  o.distortion_width_fraction = 0;
  EXPECT_FALSE(o.is_valid(&why));
  EXPECT_THROW(PoseGenerator(Board(), cv::Size(1280, 720), o), Error);
}

// A fisheye (185 degrees): every rule pose keeps the whole board in view, the distortion poses
// reach the rim, where the board faces the camera (a board parallel to the image plane is seen
// edge-on there), and random views reach beyond 90 degrees.
TEST(PoseGen, FisheyePosesReachTheRimFacingTheCamera) {
  const Board t;
  const double f = 512 / (92.5 * kDeg);
  const CameraModel cam(1280, 1024, LensModel::kFisheye,
                        {f, f * 1.002, 640.3, 511.2, 0.01, -0.002, 0.0003, -0.00002});
  PoseGenerator pg(t, cam.size());
  const double margin =
      PoseGenOptions{}.border_margin_fraction * std::min(cam.width(), cam.height());
  const cv::Size2d bs = t.board_size_m();
  for (int k = 0; k < 2; ++k)
    EXPECT_TRUE(board_fully_visible(cam, t, pg.initial_pose(k, cam).T_cam_board, margin * 0.99));
  double widest = 0;
  for (int i = 0; i < 24; ++i) {
    const int param = i % 8;
    const TargetPose p = pg.next_pose(param, cam);
    EXPECT_TRUE(board_fully_visible(cam, t, p.T_cam_board, margin * 0.99))
        << "param " << param << " " << target_kind_name(p.kind) << " " << p.note;
    if (p.kind != TargetKind::kDistortion) continue;
    const Eigen::Vector3d c = p.T_cam_board.apply(Eigen::Vector3d(bs.width / 2, bs.height / 2, 0));
    const double off_axis = std::atan2(c.head<2>().norm(), c.z()) / kDeg;
    widest = std::max(widest, off_axis);
    // Facing the camera: the board's normal along the line of sight.
    const Eigen::Vector3d normal = p.T_cam_board.R().col(2);
    EXPECT_GT(normal.dot(c.normalized()), std::cos(1 * kDeg)) << off_axis;
  }
  EXPECT_GT(widest, 60.0);
  std::printf("fisheye: distortion poses up to %.1f degrees from the axis\n", widest);

  std::mt19937_64 rng(5);
  ViewSampling vs;
  const ViewSampler sampler(cam, t, vs);
  int drawn = 0;
  double widest_view = 0;
  for (int i = 0; i < 400; ++i) {
    const std::optional<Pose> p = sampler.draw(rng);
    if (!p) continue;
    ++drawn;
    const Eigen::Vector3d c = p->apply(Eigen::Vector3d(bs.width / 2, bs.height / 2, 0));
    widest_view = std::max(widest_view, std::atan2(c.head<2>().norm(), c.z()) / kDeg);
  }
  EXPECT_GT(drawn, 300);
  EXPECT_GT(widest_view, 55.0);
  std::printf("fisheye: %d random views, centres up to %.1f degrees from the axis\n", drawn,
              widest_view);
}
