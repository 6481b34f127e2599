// Tracking the board from frame to frame (issue 18, item 3): a live loop sees the same board in
// nearly the same place frame after frame, so the search for it can be limited to where it was.
//
// BoardTracker::detect searches a region around the last frame's corners (the board's outer ring
// of squares and the motion of one frame added), on a copy shrunk as far as its markers or
// squares stay well resolved (Board::detect_in); the corners are refined at full resolution in
// the whole frame either way. The result is kept when it has at least as many corners as the
// last frame had; otherwise (the board moved out of the region, grew, or a marker was not
// decoded on the shrunk copy) the whole frame is searched as Board::detect does, and so it is
// every `whole_frame_every` frames and whenever the last frame showed no board. So tracking
// never finds less than the last frame's count without also trying the whole frame.
// docs/performance.md, "Many cameras on one station", has the cost and the fallback rates.
#pragma once

#include <cstdint>

#include "board/board.hpp"

namespace posecal {

struct TrackingOptions {
  // A search of the whole frame after this many tracked ones, whatever they found.
  int whole_frame_every = 15;
  // The shrunk copy keeps at least this many pixels per marker cell (ChArUco: the marker's bits
  // and its black border; DICT_4X4 markers were decoded down to about 1.5 px per cell).
  double min_cell_px = 4.0;
  // Chessboard: at least this many pixels per square on the shrunk copy.
  double min_square_px = 16.0;
  // At most this shrink factor.
  int max_shrink = 4;
};

// Where the next search looks and how far its copy is shrunk, from the last detection.
struct TrackingPlan {
  cv::Rect region;
  int shrink = 1;
  // ChArUco: the markers' perimeters to search for, full-resolution pixels (0: any).
  double min_perimeter_px = 0, max_perimeter_px = 0;
};

// The search for a board whose last corners are `last` in a frame of `frame` size, moving by
// `motion` pixels a frame (the last frame's); an empty region when `last` has fewer than 4
// corners or no two neighbouring ones. Exposed for tests and benchmarks.
TrackingPlan plan_tracking(const Board& board, const Detection& last, cv::Size frame,
                           const TrackingOptions& options = {}, cv::Point2d motion = {0, 0});

class BoardTracker {
 public:
  explicit BoardTracker(TrackingOptions options = {}) : options_(options) {}

  // The board in `image`: tracked when possible, else searched in the whole frame (see above).
  Detection detect(const Board& board, const cv::Mat& image, const DetectorOptions& options);
  // Board::detect, remembered as the last frame's board (the next detect() tracks from it).
  Detection detect_whole(const Board& board, const cv::Mat& image, const DetectorOptions& options);
  // Forget the last board: the next detect() searches the whole frame.
  void reset();

  // Whether the last detect() kept the tracked search's result.
  bool last_was_tracked() const { return last_tracked_; }
  struct Counts {
    uint64_t tracked = 0;   // frames whose tracked search was kept
    uint64_t fallback = 0;  // tracked searches that found fewer corners: the whole frame after it
    uint64_t whole = 0;     // frames searched in the whole frame only
  };
  const Counts& counts() const { return counts_; }

 private:
  Detection search_whole(const Board& board, const cv::Mat& image, const DetectorOptions& options);
  void remember(Detection d);
  TrackingOptions options_;
  Detection last_;
  cv::Point2d motion_{0, 0};  // of the corners from the frame before last_ to last_
  int since_whole_ = 0;
  bool last_tracked_ = false;
  Counts counts_;
};

}  // namespace posecal
