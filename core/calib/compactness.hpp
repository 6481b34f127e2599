// The paper's compactness test (§5.3): how many of a calibration's keyframes a greedy search on
// a test set needs for the same estimation error. It measures how far a pose selection is from
// a minimal set; it cannot choose poses itself (it needs the test set).
#pragma once

#include <vector>

#include "calib/calibration.hpp"

namespace posecal {

struct CompactSubset {
  std::vector<int> keyframes;  // indices into the input, in the order they were added
  double eps_test = 0;         // of the subset's calibration
  double eps_test_all = 0;     // of the calibration from every keyframe
};

// The first `keep_first` keyframes (the initial poses) are kept unconditionally; then each step
// adds the keyframe whose calibration with the subset has the lowest eps_test on `test`, until
// no keyframe lowers it further or none is left (paper §5.3, steps 1-5). Calibrations that fail
// (a subset that cannot determine the parameters) are skipped. Throws Error(kInvalidArgument)
// for fewer than 2 keyframes, keep_first outside [2, keyframes], or an empty test set.
CompactSubset greedy_compact_subset(const std::vector<Observation>& keyframes, const std::vector<Observation>& test,
                                    cv::Size image_size, const CalibrationOptions& options = {}, int keep_first = 2);

}  // namespace posecal
