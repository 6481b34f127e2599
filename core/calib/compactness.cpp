#include "calib/compactness.hpp"

#include <cmath>
#include <limits>

#include "calib/metrics.hpp"
#include "common/error.hpp"

namespace posecal {

namespace {

// eps_test of the calibration from `frames`, +inf if it cannot be computed.
double subset_eps_test(const std::vector<Observation>& frames, const std::vector<Observation>& test, cv::Size size,
                       const CalibrationOptions& options) {
  try {
    const CalibrationResult r = calibrate(frames, size, options);
    const TestError te = test_error(r.model, test);
    return te.frames_used > 0 && std::isfinite(te.rms_px) ? te.rms_px : std::numeric_limits<double>::infinity();
  } catch (const Error&) {
    return std::numeric_limits<double>::infinity();
  }
}

}  // namespace

CompactSubset greedy_compact_subset(const std::vector<Observation>& keyframes, const std::vector<Observation>& test,
                                    cv::Size image_size, const CalibrationOptions& options, int keep_first) {
  const int n = static_cast<int>(keyframes.size());
  if (n < 2) throw Error(ErrorCode::kInvalidArgument, "compactness test: needs at least 2 keyframes");
  if (keep_first < 2 || keep_first > n)
    throw Error(ErrorCode::kInvalidArgument, "compactness test: keep_first must be in [2, " + std::to_string(n) + "]");
  if (test.empty()) throw Error(ErrorCode::kInvalidArgument, "compactness test: the test set is empty");
  CompactSubset out;
  out.eps_test_all = subset_eps_test(keyframes, test, image_size, options);
  std::vector<bool> used(n, false);
  std::vector<Observation> frames;
  for (int i = 0; i < keep_first; ++i) {
    used[i] = true;
    out.keyframes.push_back(i);
    frames.push_back(keyframes[i]);
  }
  out.eps_test = subset_eps_test(frames, test, image_size, options);
  while (static_cast<int>(frames.size()) < n) {
    int best = -1;
    double best_eps = out.eps_test;
    for (int i = 0; i < n; ++i) {
      if (used[i]) continue;
      frames.push_back(keyframes[i]);
      const double e = subset_eps_test(frames, test, image_size, options);
      frames.pop_back();
      if (e < best_eps) best_eps = e, best = i;
    }
    if (best < 0) break;  // nothing lowers eps_test any more (step 5)
    used[best] = true;
    out.keyframes.push_back(best);
    frames.push_back(keyframes[best]);
    out.eps_test = best_eps;
  }
  return out;
}

}  // namespace posecal
