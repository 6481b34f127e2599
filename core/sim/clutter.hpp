// Background clutter for the detection tests and benchmarks (issue 16): textures of many small
// quads, as a chessboard poster, a dot-grid target or a perforated sheet behind the board give
// ArUco's marker search, and a rendered board composed in front of one.
#pragma once

#include <opencv2/core.hpp>

#include "sim/synthetic.hpp"

namespace posecal {

// A checkerboard of `square_px` squares (black 0, white 255) filling `size`, blurred by a
// Gaussian of `blur_sigma_px` (0: none). 8-bit grey.
cv::Mat checkerboard_clutter(cv::Size size, int square_px, double blur_sigma_px = 0.8);

// Black squares of `dot_px` on white, `gap_px` apart, filling `size`; blurred as above.
cv::Mat dot_grid_clutter(cv::Size size, int dot_px, int gap_px, double blur_sigma_px = 0.8);

// The board at T_cam_board rendered by `camera` in front of `background` (8-bit grey,
// camera.model().size()): where the board covers a pixel, partly or wholly, it hides the
// background in proportion (the frame is rendered over black and over white, and the difference
// is the background's share). The camera's sensor noise, if any, is in the board's pixels only;
// give it noise_sigma 0 and a background of 0 texture for an exact composition.
cv::Mat render_in_front_of(SyntheticCamera& camera, const Pose& T_cam_board,
                           const cv::Mat& background);

}  // namespace posecal
