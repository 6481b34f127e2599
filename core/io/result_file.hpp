// A calibration result's figures in a model file and back: what posecal's OpenCV files keep
// besides the model (the standard deviations, the covariance of the intrinsics, the coefficients
// held and their covariance, the expected error), so that a result read from a file gives the
// same expected error and map as the session that wrote it (posecal report --result).
#pragma once

#include <optional>

#include "calib/calibration.hpp"
#include "io/model_file.hpp"

namespace posecal {

// Sets the result's fields of `extras` (nr_of_frames, avg_reprojection_error, param_std,
// covariance, held, held_covariance, expected_error_px), each scaled by the residual variance;
// the others (strings, converged, interrupted) are left as they are.
void put_result_figures(const CalibrationResult& r, CalibrationFileExtras* extras);

// The result as far as the file tells it: the model, the covariance of the intrinsics (already
// scaled: residual_variance 1), `fixed` where its diagonal is 0 (posecal writes 0 for a fixed
// parameter), and the held coefficients with their covariance. Enough for expected_error() and
// expected_error_map(); no poses. None if the file holds no covariance of the intrinsics.
std::optional<CalibrationResult> result_figures_of(const ModelFile& file);

}  // namespace posecal
