// Error metrics used by every benchmark (paper §2.1 and §5).
#pragma once

#include <vector>

#include "calib/calibration.hpp"
#include "lens/camera_model.hpp"

namespace posecal {

struct TestError {
  double rms_px = 0;      // eps_test: RMS reprojection error over all held-out points
  int frames_used = 0;    // frames whose pose could be fitted
  int frames_failed = 0;  // frames where PnP failed (counted, not hidden)
  int points = 0;
};

// eps_test: RMS reprojection error on held-out frames, each frame's board pose re-fitted by PnP
// with the estimated intrinsics (the paper's estimation error).
TestError test_error(const CameraModel& estimate, const std::vector<Observation>& test_frames);

// eps_gt (synthetic runs): mean pixel distance, over a cols x rows grid of the image, between the
// true and the estimated projection of the same rays. Grid points at pixel
// ((i + 0.5) W / cols - 0.5, (j + 0.5) H / rows - 0.5). Returns NaN if no grid ray exists.
double ground_truth_error(const CameraModel& truth, const CameraModel& estimate, int cols = 40,
                          int rows = 23);

// eps_gt over the grid of the expected error (calib/expected_error.hpp): cols x rows points from
// image edge to image edge, corners included, at pixel (i (W-1)/(cols-1), j (H-1)/(rows-1)); the
// mean distance, or with `rms` the root mean square. NaN if no grid ray exists.
double ground_truth_error_edges(const CameraModel& truth, const CameraModel& estimate, int cols = 40, int rows = 23,
                                bool rms = false);

// eps_gt with the camera frame's rotation taken out: the mean distance over the ground_truth_error
// grid after the rotation R that minimises sum |pi_est(R ray) - pixel|^2 (Gauss-Newton from the
// identity). A rotation of the camera frame is absorbed by the board poses, so the images do not
// determine it; and a tilted sensor or a principal-point shift imitates one to first order
// (docs/pose-selection.md, "Lens models beyond OpenCV's five coefficients"), which plain eps_gt
// counts as error of f tau pixels. mrcal compares models the same way. *rotation_rad (optional)
// gets the angle of R. NaN if no grid ray exists.
double ground_truth_error_aligned(const CameraModel& truth, const CameraModel& estimate,
                                  int cols = 40, int rows = 23, double* rotation_rad = nullptr);

}  // namespace posecal
