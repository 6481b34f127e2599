#include "board/tracking.hpp"

#include <algorithm>
#include <cmath>
#include <map>
#include <opencv2/imgproc.hpp>
#include <vector>

#include "common/statistics.hpp"

namespace posecal {

TrackingPlan plan_tracking(const Board& board, const Detection& last, cv::Size frame,
                           const TrackingOptions& options, cv::Point2d motion) {
  if (last.size() < 4) return {};
  const BoardSpec& spec = board.spec();
  const bool charuco = spec.type == BoardType::kCharuco;
  const int per_row = charuco ? spec.cols - 1 : spec.cols;
  // One square along each grid direction: the median distance between neighbouring corners.
  std::map<int, cv::Point2d> at;
  for (size_t i = 0; i < last.size(); ++i) at[last.ids[i]] = last.image_points[i];
  std::vector<double> along_u, along_v;
  for (const auto& [id, p] : at) {
    if (id % per_row + 1 < per_row) {
      if (auto it = at.find(id + 1); it != at.end()) along_u.push_back(cv::norm(it->second - p));
    }
    if (auto it = at.find(id + per_row); it != at.end())
      along_v.push_back(cv::norm(it->second - p));
  }
  if (along_u.empty() && along_v.empty()) return {};
  const double u = median(along_u), v = median(along_v);
  const double shortest = along_u.empty() ? v : along_v.empty() ? u : std::min(u, v);
  const double longest = std::max(u, v);
  if (!(shortest > 0)) return {};
  const double ratio = spec.marker_length_m / spec.square_length_m;
  // As far as the shrunk copy keeps the markers' cells resolved: min_cell_px along the board's
  // longer image direction, three quarters of it along the foreshortened one (a board tilted by
  // 45 degrees was otherwise searched unshrunk); the chessboard's squares likewise.
  const double across = std::min(shortest / 0.75, longest);
  const double resolved = charuco ? across * ratio / board.marker_grid_cells() / options.min_cell_px
                                  : shortest / options.min_square_px;
  TrackingPlan plan;
  plan.shrink =
      std::clamp(static_cast<int>(std::floor(resolved)), 1, std::max(1, options.max_shrink));
  if (charuco) {
    // A marker's perimeter lies between 4 x its shortest and longest side; a contour along a
    // diagonal counts about 0.71 points per pixel of length, and the board may grow or shrink
    // by some 30% in a frame.
    std::vector<double> all(along_u);
    all.insert(all.end(), along_v.begin(), along_v.end());
    const auto [lo, hi] = std::minmax_element(all.begin(), all.end());
    plan.min_perimeter_px = 0.5 * 4.0 * ratio * *lo;
    plan.max_perimeter_px = 1.4 * 4.0 * ratio * *hi;
  }
  // The inner corners' box, widened by the board's outer ring of squares (one square, half again
  // for a foreshortened near side) and a frame's motion (a tenth of the board, 8 px at least).
  std::vector<cv::Point2f> pts(last.image_points.begin(), last.image_points.end());
  cv::Rect box = cv::boundingRect(pts);
  // Where the board is headed if it keeps the last frame's motion.
  if (std::isfinite(motion.x) && std::isfinite(motion.y)) {
    const cv::Point shift(static_cast<int>(std::lround(std::clamp(motion.x, -1e4, 1e4))),
                          static_cast<int>(std::lround(std::clamp(motion.y, -1e4, 1e4))));
    box |= box + shift;
  }
  const int margin =
      static_cast<int>(std::ceil(1.5 * longest + 0.1 * std::max(box.width, box.height) + 8.0));
  plan.region =
      cv::Rect(box.x - margin, box.y - margin, box.width + 2 * margin, box.height + 2 * margin) &
      cv::Rect(0, 0, frame.width, frame.height);
  return plan;
}

Detection BoardTracker::detect(const Board& board, const cv::Mat& image,
                               const DetectorOptions& options) {
  if (last_.size() >= 4 && since_whole_ < options_.whole_frame_every) {
    const TrackingPlan plan = plan_tracking(board, last_, image.size(), options_, motion_);
    if (!plan.region.empty()) {
      Detection d = board.detect_in(image, plan.region, plan.shrink, plan.min_perimeter_px,
                                    plan.max_perimeter_px, options);
      if (d.size() >= last_.size()) {
        ++counts_.tracked;
        ++since_whole_;
        last_tracked_ = true;
        remember(std::move(d));
        return last_;
      }
      ++counts_.fallback;
      return search_whole(board, image, options);
    }
  }
  ++counts_.whole;
  return search_whole(board, image, options);
}

Detection BoardTracker::detect_whole(const Board& board, const cv::Mat& image,
                                     const DetectorOptions& options) {
  ++counts_.whole;
  return search_whole(board, image, options);
}

Detection BoardTracker::search_whole(const Board& board, const cv::Mat& image,
                                     const DetectorOptions& options) {
  since_whole_ = 0;
  last_tracked_ = false;
  remember(board.detect(image, options));
  return last_;
}

// The mean motion of the corners seen in both frames (zero when fewer than 4 are).
void BoardTracker::remember(Detection d) {
  cv::Point2d sum(0, 0);
  int common = 0;
  for (size_t i = 0, j = 0; i < d.size() && j < last_.size();) {
    if (d.ids[i] < last_.ids[j]) {
      ++i;
    } else if (last_.ids[j] < d.ids[i]) {
      ++j;
    } else {
      sum += d.image_points[i++] - last_.image_points[j++];
      ++common;
    }
  }
  motion_ = common >= 4 ? sum / common : cv::Point2d(0, 0);
  last_ = std::move(d);
}

void BoardTracker::reset() {
  last_ = Detection{};
  motion_ = cv::Point2d(0, 0);
  since_whole_ = 0;
  last_tracked_ = false;
}

}  // namespace posecal
