// The pose of one board view with the intrinsics held fixed.
#pragma once

#include "calib/calibration.hpp"
#include "lens/camera_model.hpp"
#include "lens/geometry.hpp"

namespace posecal {

// Fits the pose of one frame with fixed intrinsics (IPPE refined by Levenberg-Marquardt, and
// OpenCV's iterative PnP; the lower reprojection error wins). Returns false if the frame has fewer
// than 4 points or the fit fails; *rms_px (optional) receives the fit's RMS residual.
bool estimate_pose(const CameraModel& model, const Observation& frame, Pose* T_cam_board,
                   double* rms_px = nullptr);

}  // namespace posecal
