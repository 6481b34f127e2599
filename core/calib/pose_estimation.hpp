// The pose of one board view with the intrinsics held fixed.
#pragma once

#include "calib/calibration.hpp"
#include "lens/camera_model.hpp"
#include "lens/geometry.hpp"

namespace posecal {

// Fits the pose of one frame with fixed intrinsics (IPPE refined by Levenberg-Marquardt, and
// OpenCV's iterative PnP, and for a ray model pose_from_rays() on every point's ray; the lower
// reprojection error wins). Returns false if the frame has fewer
// than 4 points or the fit fails; *rms_px (optional) receives the fit's RMS residual.
bool estimate_pose(const CameraModel& model, const Observation& frame, Pose* T_cam_board,
                   double* rms_px = nullptr);

// The pose of a planar board (every object point at z = 0) from unit rays to its points, in any
// direction (also 90 degrees or more from the axis, where cv::solvePnP's plane Z = 1 ends): the
// homography from the board plane to the rays by a linear fit (each ray parallel to H (x, y, 1)),
// then, if `refine`, Levenberg-Marquardt on the rays' angular errors. False if the points
// (at least 4, not all on a line) do not determine it.
bool pose_from_rays(const std::vector<cv::Point3d>& object,
                    const std::vector<Eigen::Vector3d>& rays, Pose* T_cam_board,
                    bool refine = true);

// Correspondences as cv::solvePnP takes them for `model`: OpenCV's pinhole models pass K and
// their distortion vector with the points as they are; a model OpenCV's pinhole functions do not
// hold (the fisheye) passes the image points unprojected to the plane Z = 1 with K = I and no
// distortion, dropping points 90 degrees or more from the axis.
struct PnPInput {
  cv::Mat K;
  std::vector<double> dist;
  std::vector<cv::Point3d> object;
  std::vector<cv::Point2d> image;
};
PnPInput pnp_input(const CameraModel& model, const std::vector<cv::Point3d>& object,
                   const std::vector<cv::Point2d>& image);

}  // namespace posecal
