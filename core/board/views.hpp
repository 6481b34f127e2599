// Board views for synthetic experiments: random well-spread poses (the OpenCV baselines of the
// benchmarks), the fixed test set for eps_test, and visibility checks.
#pragma once

#include <cstdint>
#include <optional>
#include <random>
#include <vector>

#include "lens/camera_model.hpp"
#include "lens/geometry.hpp"
#include "board/board.hpp"

namespace posecal {

// Board pose with the board's centre at `centre_cam` (camera frame), rotated from fronto-parallel
// (R = I: board x to the image's right, y down) by `tilt_rad` about the in-plane axis at angle
// `tilt_axis_rad` from the image x axis, then rolled by `roll_rad` about the optical axis.
// `facing` (optional) is applied after them: the orientation a fronto-parallel board has at that
// place (board_frame_at_pixel()).
Pose board_pose_at(const Board& board, const Eigen::Vector3d& centre_cam, double tilt_axis_rad,
                   double tilt_rad, double roll_rad,
                   const Eigen::Matrix3d& facing = Eigen::Matrix3d::Identity());

// Where the centre of a board seen at pixel `px` lies at `depth`, and how a board there faces
// the camera. For the models of the plane Z = 1, depth is the Z coordinate and the board is
// parallel to the image plane (facing = I), as the paper places it. For a ray model (the
// fisheye) depth is the distance along the pixel's ray and the board faces the camera (facing
// turns the optical axis onto the ray, the least rotation that does): a board parallel to the
// image plane is seen edge-on towards 90 degrees from the axis and not at all beyond. False if
// the pixel has no preimage. `fold_free_r`: CameraModel::fold_free_radius() of the model, a
// shortcut for many calls.
bool board_frame_at_pixel(const CameraModel& model, const Eigen::Vector2d& px, double depth,
                          Eigen::Vector3d* centre_cam, Eigen::Matrix3d* facing,
                          double fold_free_r = 0);

// True if the whole board (its outline, sampled densely, and every corner) projects inside the
// image with `margin_px` to spare, in front of the camera.
bool board_fully_visible(const CameraModel& model, const Board& board, const Pose& T_cam_board,
                         double margin_px = 2.0);

// The cheap part of board_fully_visible(): the four corners of `outline` (Board::outline())
// project inside the image with `margin_px` to spare and the projected outline is convex.
bool board_outline_in_view(const CameraModel& model, const std::vector<cv::Point3d>& outline, const Eigen::Matrix3d& R,
                           const Eigen::Vector3d& t, double margin_px);

struct ViewSampling {
  double max_tilt_deg = 45.0;
  double min_width_fraction = 0.3;  // board width in the image, as a fraction of image width
  double max_width_fraction = 0.7;
  double margin_px = 4.0;
  int max_tries = 2000;
};

// A random view with the board fully visible, or nullopt if none was found in max_tries.
// `draws` (optional) receives the number of draws it took.
std::optional<Pose> random_board_view(std::mt19937_64& rng, const CameraModel& model,
                                      const Board& board, const ViewSampling& sampling = {},
                                      int* draws = nullptr);

// A board view in terms that do not depend on the intrinsics: the board's width as a fraction
// of the image width (its depth follows from the focal length), its orientation (tilt about an
// in-plane axis, then roll about the optical axis, as board_pose_at) and the pixel its centre
// projects to. ViewSampler::realise() turns it into a pose under a camera model.
struct ViewDraw {
  double width_fraction = 0;
  double tilt_rad = 0, tilt_axis_rad = 0, roll_rad = 0;
  Eigen::Vector2d centre_px = Eigen::Vector2d::Zero();
};

// Random whole-board views for many candidates at once (the engine's view candidates), a few
// microseconds each instead of random_board_view's tens. The width fraction, tilt, tilt axis and
// roll are drawn as random_board_view draws them; the board's pinhole outline at that depth then
// gives the range of image positions where it fits, the draw is kept with probability
// proportional to that range's area (so the distribution is random_board_view's, which draws the
// position uniformly over the image and rejects, up to the pinhole approximation of the fit), and
// the position is drawn inside it. realise() then checks the outline's four corners under the
// full model (distortion included) with the margin, and that the projected outline is convex; the
// dense check of board_fully_visible() is left to the caller, for the few views it keeps.
class ViewSampler {
 public:
  ViewSampler(const CameraModel& model, const Board& board, const ViewSampling& sampling);
  // One view, or nullopt after max_tries draws (sampling.max_tries if < 0); `draws` as for
  // random_board_view. A draw counts whether it fails the pinhole fit or realise().
  std::optional<Pose> draw(std::mt19937_64& rng, int* draws = nullptr, int max_tries = -1) const;
  // The same draw, the pose as a rotation matrix (no conversion); false where draw() gives nullopt.
  bool draw(std::mt19937_64& rng, Eigen::Matrix3d* R_cam_board, Eigen::Vector3d* t_cam_board, int* draws = nullptr,
            int max_tries = -1) const;
  // Only the intrinsics-free part: one draw that passes the pinhole fit (false after max_tries).
  bool draw_view(std::mt19937_64& rng, ViewDraw* view, int* draws = nullptr, int max_tries = -1) const;
  // The pose of `view` under this sampler's model: false if its centre pixel has no preimage, a
  // corner of the outline leaves the image (with the margin) or the outline is not convex.
  bool realise(const ViewDraw& view, Eigen::Matrix3d* R_cam_board, Eigen::Vector3d* t_cam_board) const;

 private:
  CameraModel model_;
  ViewSampling s_;
  std::vector<cv::Point3d> outline_;
  Eigen::Vector3d centre_board_;
  double board_width_m_ = 0;
  double reference_area_ = 0;  // the image less the margins: acceptance 1
  double fold_free_r_ = 0;     // CameraModel::fold_free_radius() of model_
  bool ray_model_ = false;     // boards face the camera (board_frame_at_pixel())
};

// `count` random views (throws Error(kInternal) if the camera cannot see the board at all).
std::vector<Pose> random_board_views(uint64_t seed, int count, const CameraModel& model,
                                     const Board& board, const ViewSampling& sampling = {});

// The fixed synthetic test set for eps_test: 50 views at various distances (board 20-80% of the
// image width) and angles (tilt up to 50 deg) covering the whole view. Deterministic.
std::vector<Pose> test_set_views(const CameraModel& model, const Board& board, int count = 50);

}  // namespace posecal
