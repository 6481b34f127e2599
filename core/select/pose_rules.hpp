// Target pose generation (paper §3.3 and §3.4). All poses are T_cam_board in the camera frame,
// metres; they depend on the current intrinsic estimate only through visibility and placement.
#pragma once

#include <functional>
#include <string>
#include <vector>

#include "lens/camera_model.hpp"
#include "lens/geometry.hpp"
#include "board/board.hpp"
#include "device/guidance.hpp"

namespace posecal {

// Binary subdivision of (0, 1): 0.25, 0.75, 0.125, 0.375, 0.625, 0.875, 0.0625, ...
// (paper §3.3, step 2). Stateless: returns the n-th element (n >= 0).
double binary_subdivision(int n);

struct PoseGenOptions {
  double max_tilt_deg = 70.0;      // C_K tilt range (-70, 70) deg (paper §3.3)
  double roll_deg = 22.5;          // rotation about the optical axis (paper §3.3, step 3)
  double shift_fraction = 0.05;    // cx/cy shift, fraction of the image size (step 4)
  double init_tilt_deg = 45.0;     // first initial pose (paper §3.4)
  double distortion_width_fraction = 0.33;  // C_Delta board width / image width (paper §3.3)
  double distortion_threshold_step = 0.05;  // threshold decrements over the normalised map
  double mask_max_overlap = 0.9;   // a region whose box is this much masked is skipped
  int distortion_map_step_px = 20; // distortion map sampling (reference implementation: 20)
  // Margin kept between any target board and the image border, fraction of the image size.
  // The paper clips C_Delta boards to the image (margin 0); a small margin keeps a board the
  // operator places a little off target fully visible (docs/pose-selection.md).
  double border_margin_fraction = 0.02;
  double fullscreen_fill = 0.95;   // second initial pose: fraction of the limiting image axis
  // C_K poses: the untilted board's size, fraction of the limiting image axis (then moved back
  // if the tilted board would leave the view). The reference implementation's fixed distance
  // of 1.6 board widths gives about 0.53 on a C525.
  double pinhole_fill = 0.8;
  // C_Delta poses: tilt about the axis perpendicular to the direction from the image centre, in
  // degrees (0 = parallel to the image plane, as in the paper).
  double distortion_tilt_deg = 0.0;
  bool is_valid(std::string* error) const;
};

struct TargetPose {
  Pose T_cam_board;
  TargetKind kind = TargetKind::kPinhole;
  std::string note;     // what was adjusted (moved back to stay in view, fallback, ...)
  double tilt_deg = 0;  // C_K poses: tilt angle used
  int axis = -1;        // C_K poses: 0 tilt about x, 1 about y
  int sequence_index = -1;  // C_K poses: element of the subdivision sequence
  int shift_sign = 0;   // C_K poses for cx/cy: direction of the shift
  cv::Rect region;      // C_Delta poses: the distorted region (pixels) this pose samples
  cv::Rect mask_cells;  // C_Delta poses: cells of the distortion mask it visits
};

// Scores a candidate target (lower is better), e.g. the predicted variance of the targeted
// parameter after capturing it.
using PoseScorer = std::function<double(const TargetPose&)>;

class PoseGenerator {
 public:
  PoseGenerator(const Board& board, cv::Size image_size, const PoseGenOptions& options = {});

  // Initialisation (paper §3.4): first a pose tilted init_tilt_deg about x (with the roll),
  // then the board parallel to the image plane covering the view.
  // `retry` > 0: the pose offered after the first `retry` were not reached in time; the tilted
  // pose is tilted 10 degrees less per retry (down to 25 degrees), the other is the same.
  TargetPose initial_pose(int index, const CameraModel& estimate, int retry = 0) const;
  // Pose for one intrinsic (index into fx fy cx cy k1 k2 p1 p2 k3): C_K poses for 0..3, C_Delta
  // poses for the distortion coefficients (falling back to a C_K pose, noted, when no distorted
  // region is left). Advances the per-axis subdivision sequences and the distortion mask.
  // Without a scorer this is the paper's rule: the next element of the sequence (alternating
  // shift sign) or the most distorted unvisited region. With a scorer, the best of up to
  // `candidates` rule-generated poses (the next sequence elements with both shift signs, the
  // next most distorted regions) is taken (docs/pose-selection.md).
  TargetPose next_pose(int param_index, const CameraModel& estimate, const PoseScorer& scorer = nullptr,
                       int candidates = 4);
  // The candidates next_pose() chooses from, in the paper's order (first = paper's choice).
  std::vector<TargetPose> candidates(int param_index, const CameraModel& estimate, int count);
  // Marks a candidate as used (sequence element / distortion region).
  void commit(const TargetPose& pose);

  // The C_K pose for a tilt axis (0: about x, for fy/cy; 1: about y, for fx/cx) at a given
  // tilt, optionally shifted along the image axis by shift_px. Exposed for tests.
  TargetPose pinhole_pose(int axis, double tilt_deg, double shift_px, const CameraModel& estimate) const;
  // Mask of already-visited distorted regions (cells of distortion_map_step_px), for tests.
  const cv::Mat& distortion_mask() const { return mask_; }
  int pinhole_poses_generated(int axis) const;

 private:
  std::vector<TargetPose> distortion_candidates(const CameraModel& estimate, int count) const;
  TargetPose distortion_pose_for(const CameraModel& estimate, const cv::Rect& box_cells) const;
  // Moves the board back along the line of sight until it is fully visible with the margin.
  bool keep_in_view(const CameraModel& estimate, Pose* pose, std::string* note) const;

  Board board_;
  cv::Size size_;
  PoseGenOptions options_;
  std::vector<bool> used_[2];  // subdivision sequence elements used, per axis
  int shift_sign_[2] = {1, 1};
  cv::Mat mask_;  // CV_8U, 1 = visited
};

// Projected area overlap (intersection over union) of the board at two poses, both projected
// with `model` including distortion (paper §4.2). Rasterised at 1/raster_scale resolution.
double board_jaccard(const CameraModel& model, const Board& board, const Pose& a, const Pose& b,
                     int raster_scale = 4);

// The board outline projected densely (points per edge) through the model, pixels; empty if any
// point is behind the camera.
std::vector<cv::Point2d> projected_outline(const CameraModel& model, const Board& board,
                                           const Pose& pose, int points_per_edge = 12);

}  // namespace posecal
