// A cheap test of whether a frame can hold a chessboard at all, run before
// OpenCV's chessboard search (Board::detect_chessboard). OpenCV's search is unbounded on scenes
// without a board (0.4-1.9 s per frame on a circuit board or a photo at 1280 px,
// docs/performance.md, "Scenes without a board"); this test costs a few milliseconds.
#pragma once

#include <opencv2/core.hpp>

namespace posecal {

// The number of lattice crossings in `gray` (CV_8UC1): saddle points (the Hessian of the
// locally contrast-normalised image has eigenvalues of opposite sign) that have two pairs of
// opposite neighbours, each neighbour a saddle of the opposite polarity (its Hessian turned by
// 90 degrees), as the inner corners of a chessboard do. The largest count over the image (or,
// above 640 px, its half-size copy) and two copies shrunk by 2 and 4 more (large squares under
// sensor noise are found there). The kMaxSaddles strongest saddles above 2% of the strongest are
// examined; a level with more than that, nearly all as strong as the strongest (a dense lattice: a
// checkerboard texture, which the strongest would only sample), gives kCannotTell, and so does a
// frame under 48 px a side (the smallest level examined): such frames are searched.
int chessboard_crossings(const cv::Mat& gray);

// chessboard_crossings' count and, from the level that gave it, the median over the crossings
// of the shorter of their two axes, in `gray`'s pixels: the distance to the nearest crossing of
// opposite polarity along the board's more foreshortened direction, a square's shorter side
// (within 4% on rendered boards of 6-60 px squares). 0 without crossings and for kCannotTell.
struct ChessboardLattice {
  int crossings = 0;
  double spacing_px = 0;
  double long_spacing_px = 0;  // the same median of the longer axis
  cv::Rect2d extent;           // the crossings' bounding box (a board's and any others)
};
// `shrunk`: `gray` is a frame already shrunk for the search (Board::detect above
// DetectorOptions::search_max_side), examined as it is rather than from a half-size copy.
ChessboardLattice chessboard_lattice(const cv::Mat& gray, bool shrunk = false);

inline constexpr int kMaxSaddles = 600;
inline constexpr int kCannotTell = 1 << 20;

// The crossings a frame must have before the chessboard search runs for a board of
// cols x rows inner corners: a quarter of the board's interior corners (the (cols - 2) x
// (rows - 2) that have neighbours on every side), at least one; 0 (always search) for a board with
// fewer than 3 corners along a side, which has no interior corner.
int chessboard_crossings_needed(int cols, int rows);

}  // namespace posecal
