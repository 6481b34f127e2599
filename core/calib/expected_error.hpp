// The expected projection error of a calibration: how far, in pixels, the estimated intrinsics
// are expected to project a ray from where the true ones do, predicted from the intrinsics'
// covariance (docs/math.md, "Expected projection error"). It is what a user of the calibration
// gets, in the unit they care about, and what `accuracy_px` stops on.
#pragma once

#include <opencv2/core.hpp>

#include "calib/calibration.hpp"

namespace posecal {

// The grid the figure is taken over: cols x rows points from image edge to image edge, corners
// included; point (i, j) at pixel (i (W - 1) / (cols - 1), j (H - 1) / (rows - 1)).
inline constexpr int kExpectedErrorCols = 40;
inline constexpr int kExpectedErrorRows = 23;
inline constexpr int kExpectedErrorPoints = kExpectedErrorCols * kExpectedErrorRows;
inline constexpr int kExpectedErrorDraws = 1000;

struct ExpectedError {
  // RMS over the grid of the predicted error: sqrt(mean over points of trace(J Sigma J^T)), J the
  // ray's d(pixel)/d(free intrinsics) and Sigma their covariance marginalised over the poses.
  double rms_px = 0;       // at the measured corner noise (Sigma scaled by the residual variance)
  double rms_unit_px = 0;  // at 1 px corner noise (Sigma_p = I)
  int points = 0;          // grid points whose ray exists under the estimate
  int grid_points = 0;     // cols x rows
  // The distribution over the noise of the realised eps_gt on this grid (the mean distance
  // between the true and the estimated projection of a ray), first order: its mean and its 90th
  // percentile, from kExpectedErrorDraws draws of the intrinsics' error ~ N(0, Sigma) (fixed
  // seed: the same result gives the same figures). The p90 is what 9 of 10 such calibrations
  // stay within, the stop figure of accuracy_px.
  double mean_px = 0;
  double p90_px = 0;
  // The intrinsic that holds the error back: the one whose exact knowledge would lower the
  // expected squared error most (-1 if every intrinsic is fixed), and the share of rms_px^2 it
  // would remove, in [0, 1].
  int limiting_param = -1;
  double limiting_share = 0;

  // False if the estimate folds inside the image: some grid point has no ray under it, and the
  // figures leave that part of the image out (a lens projects one-to-one onto its image, so such
  // an estimate is wrong there by an amount no covariance predicts).
  bool covers_image() const { return points == grid_points; }
};

// Of the cols x rows grid (placed as the expected error's), the points whose ray exists under
// `model`: all of them unless the model folds inside the image.
int grid_points_with_ray(const CameraModel& model, int cols = kExpectedErrorCols,
                         int rows = kExpectedErrorRows);

// Throws Error(kInvalidArgument) for a grid smaller than 2x2 or a result without covariance.
// With no grid point in the image's preimage the figures are NaN and points is 0.
ExpectedError expected_error(const CalibrationResult& result, int cols = kExpectedErrorCols,
                             int rows = kExpectedErrorRows);

// The map behind rms_px: a rows x cols CV_32F image of the predicted RMS error at each grid point
// (the same edge-to-edge placement; cols = W and rows = H give one value per pixel), at the
// measured noise; NaN where the ray does not exist.
cv::Mat expected_error_map(const CalibrationResult& result, int cols, int rows);

}  // namespace posecal
