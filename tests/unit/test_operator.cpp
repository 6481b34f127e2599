// The simulated operators of the benchmark's worlds (sim/operator.hpp).
#include <gtest/gtest.h>

#include <cmath>

#include "common/error.hpp"
#include "lens/geometry.hpp"
#include "lens/reference_models.hpp"
#include "sim/operator.hpp"

using namespace posecal;

namespace {

double tilt_deg(const Pose& p) {
  // Angle between the board's normal and the camera's optical axis.
  return std::acos(std::min(1.0, std::abs(p.R()(2, 2)))) * 180.0 / M_PI;
}

// The board's held poses while bootstrapping: one per attempt (the last frame of each).
std::vector<Pose> bootstrap_boards(const OperatorOptions& o, int attempts, uint64_t seed) {
  const CameraModel cam = c525_reference_model();
  SimulatedOperator op(cam, Board(), o, seed);
  GuidanceInfo g;  // no target: bootstrapping
  g.bootstrapping = true;
  g.estimate = cam;
  std::vector<Pose> out;
  const int cycle = o.move_frames + o.hold_frames;
  for (int f = 0; f < attempts * cycle; ++f) {
    const Pose p = op.next_pose(g);
    if (f % cycle == cycle - 1) out.push_back(p);
  }
  return out;
}

}  // namespace

TEST(Operator, PresetsByName) {
  const OperatorOptions hold = operator_preset("hold-only");
  EXPECT_EQ(hold.move_frames, 0);
  EXPECT_EQ(hold.hold_frames, 3);
  EXPECT_EQ(hold.bootstrap, BootstrapBoards::kFixedTilt);
  EXPECT_EQ(operator_preset("careless").bootstrap, BootstrapBoards::kAnyBoard);
  EXPECT_EQ(operator_preset("sloppy").rotation_error_deg, 4.0);
  EXPECT_EQ(operator_preset("sloppy").translation_error_fraction, 0.04);
  EXPECT_EQ(operator_preset("robot").kind, OperatorKind::kRobot);
  EXPECT_EQ(operator_preset("approach").move_frames, OperatorOptions{}.move_frames);
  for (const char* name : {"approach", "hold-only", "sloppy", "careless", "robot"}) {
    std::string why;
    EXPECT_TRUE(operator_preset(name).is_valid(&why)) << name << ": " << why;
  }
  try {
    operator_preset("drunk");
    FAIL() << "an unknown operator must throw";
  } catch (const Error& e) {
    EXPECT_EQ(e.code(), ErrorCode::kInvalidArgument);
    EXPECT_NE(std::string(e.what()).find("hold-only"), std::string::npos) << e.what();
  }
  OperatorOptions bad;
  bad.move_frames = 0;
  bad.hold_frames = 2;
  EXPECT_FALSE(bad.is_valid(nullptr));  // an attempt of two frames cannot be still
}

// The hold-only person (the independent harness's): every attempt a centred board, 55% of the
// width, tilted 10-25 degrees, whatever the guidance says, held for exactly 3 frames.
TEST(Operator, HoldOnlyBootstrapsWithAFixedTilt) {
  const CameraModel cam = c525_reference_model();
  const OperatorOptions o = operator_preset("hold-only");
  const std::vector<Pose> boards = bootstrap_boards(o, 40, 3);
  ASSERT_EQ(boards.size(), 40u);
  const Board board;
  for (const Pose& p : boards) {
    EXPECT_GE(tilt_deg(p), 9.0);  // the tremor moves the board, not its tilt
    EXPECT_LE(tilt_deg(p), 26.0);
    const cv::Point2d c = project_points(cam, p, {cv::Point3d(board.board_size_m().width / 2, board.board_size_m().height / 2, 0)})[0];
    EXPECT_LT(std::abs(c.x - cam.cx()), 0.12 * cam.width());
    EXPECT_LT(std::abs(c.y - cam.cy()), 0.12 * cam.height());
  }
  // Three frames per attempt: the board jumps between frames 3 and 4, not within an attempt.
  SimulatedOperator op(cam, board, o, 5);
  GuidanceInfo g;
  g.bootstrapping = true;
  g.estimate = cam;
  std::vector<Pose> f;
  for (int i = 0; i < 9; ++i) f.push_back(op.next_pose(g));
  auto moved = [](const Pose& a, const Pose& b) { return (a.t - b.t).norm() > 0.005 || (a.r - b.r).norm() > 0.01; };
  EXPECT_FALSE(moved(f[0], f[1]));
  EXPECT_FALSE(moved(f[1], f[2]));
  EXPECT_TRUE(moved(f[2], f[3]));
  EXPECT_FALSE(moved(f[3], f[5]));
  EXPECT_TRUE(moved(f[5], f[6]));
}

// The careless person shows any board with all its corners in view, at any tilt up to 60 deg.
TEST(Operator, CarelessShowsAnyBoardInView) {
  const CameraModel cam = c525_reference_model();
  const std::vector<Pose> boards = bootstrap_boards(operator_preset("careless"), 60, 7);
  const Board board;
  double max_tilt = 0, min_tilt = 90;
  for (const Pose& p : boards) {
    for (const auto& q : project_points(cam, p, board.corners())) {
      EXPECT_GE(q.x, -1.0);
      EXPECT_GE(q.y, -1.0);
      EXPECT_LE(q.x, cam.width());
      EXPECT_LE(q.y, cam.height());
    }
    max_tilt = std::max(max_tilt, tilt_deg(p));
    min_tilt = std::min(min_tilt, tilt_deg(p));
  }
  EXPECT_GT(max_tilt, 45.0);
  EXPECT_LT(min_tilt, 15.0);
}
