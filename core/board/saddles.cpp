#include "board/saddles.hpp"

#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <numbers>
#include <opencv2/imgproc.hpp>
#include <utility>
#include <vector>

#include "common/statistics.hpp"

namespace posecal {

namespace {

// Local contrast normalisation: (I - mean) / sqrt(variance + kNoiseFloor^2) over a
// box window of kContrastWindow px. A board of 70 grey levels next to a circuit board of 200 keeps
// its corners among the strongest saddles; the floor keeps flat areas' sensor noise from being
// raised to the level of a board (a floor of 8 grey levels let a circuit board pass, one of 50
// lost a low-contrast board; measured on the opencv-doc photos, docs/performance.md).
constexpr int kContrastWindow = 15;
constexpr double kNoiseFloor = 25.0;
constexpr double kDerivativeSigma = 1.0;
constexpr double kRelativeThreshold = 0.02;  // of the strongest saddle
constexpr int kNeighbours = 8;
constexpr int kMinSide = 48;
constexpr int kMaxSide = 640;
constexpr int kLevels = 3;
constexpr double kDenseLattice = 0.5;  // of the strongest saddle's strength

struct Saddle {
  cv::Point2f p;
  float strength;
  float angle;  // of the Hessian's first principal axis, [-pi/2, pi/2]
};

// The peak of the strength `a` about its local maximum (x, y): a parabola through it and its
// two neighbours along each axis. Whole-pixel positions made a small board's opposite neighbours
// unequal by a pixel (4 and 5 px away among squares of 4.5 px at half size), more than the 25%
// that count_crossings allows, and a board of 9 px squares at 1280x720 gave 1-4 crossings at
// some angles and positions instead of 40-53.
cv::Point2f subpixel_peak(const cv::Mat& a, int x, int y) {
  auto offset = [](float before, float at, float after) {
    const float curvature = before - 2 * at + after;
    return curvature < 0 ? std::clamp(0.5f * (before - after) / curvature, -0.5f, 0.5f) : 0.0f;
  };
  float dx = 0;
  float dy = 0;
  if (x > 0 && x + 1 < a.cols) {
    const float* row = a.ptr<float>(y);
    dx = offset(row[x - 1], row[x], row[x + 1]);
  }
  if (y > 0 && y + 1 < a.rows) {
    dy = offset(a.at<float>(y - 1, x), a.at<float>(y, x), a.at<float>(y + 1, x));
  }
  return {static_cast<float>(x) + dx, static_cast<float>(y) + dy};
}

// Four float images, each reused as soon as its content is no longer needed, and OpenCV's
// vectorised element-wise operations: fresh buffers of a frame's size cost more in page faults
// than the filtering itself (about 10 ms each at 1280x720 on the machines of
// docs/performance.md).
std::vector<Saddle> find_saddles(const cv::Mat& gray, bool* dense) {
  cv::Mat a;  // the frame, then normalised, then the saddle strength
  cv::Mat b;  // local mean, then d2/dx2, then d2/dx2 - d2/dy2
  cv::Mat c;  // local mean square, then its denominator, then d2/dy2, then the 5x5 maxima
  cv::Mat d;  // the squared mean, then d2/dxdy
  gray.convertTo(a, CV_32F);
  cv::multiply(a, a, c);
  const cv::Size window(kContrastWindow, kContrastWindow);
  cv::blur(a, b, window);
  cv::blur(c, c, window);
  cv::multiply(b, b, d);
  cv::subtract(c, d, c);
  cv::max(c, 0.0, c);
  cv::add(c, cv::Scalar(kNoiseFloor * kNoiseFloor), c);
  cv::sqrt(c, c);
  cv::subtract(a, b, a);
  cv::divide(a, c, a);
  cv::GaussianBlur(a, a, cv::Size(), kDerivativeSigma);
  cv::Sobel(a, b, CV_32F, 2, 0, 3);
  cv::Sobel(a, c, CV_32F, 0, 2, 3);
  cv::Sobel(a, d, CV_32F, 1, 1, 3);
  cv::multiply(b, c, a);  // dxx dyy
  cv::subtract(b, c, b);  // dxx - dyy
  cv::multiply(d, d, c);  // dxy^2
  cv::subtract(c, a, a);  // the strength: minus the Hessian's determinant
  double strongest = 0;
  cv::minMaxLoc(a, nullptr, &strongest);
  cv::dilate(a, c, cv::Mat::ones(5, 5, CV_8U));
  const float threshold = static_cast<float>(std::max(kRelativeThreshold * strongest, 1e-9));
  std::vector<Saddle> saddles;
  for (int y = 0; y < a.rows; ++y) {
    const float* ar = a.ptr<float>(y);
    const float* cr = c.ptr<float>(y);
    for (int x = 0; x < a.cols; ++x) {
      if (ar[x] <= threshold || ar[x] < cr[x]) continue;
      const float angle = 0.5f * std::atan2(2.0f * d.at<float>(y, x), b.at<float>(y, x));
      saddles.push_back({subpixel_peak(a, x, y), ar[x], angle});
    }
  }
  if (saddles.size() > static_cast<size_t>(kMaxSaddles)) {
    std::nth_element(saddles.begin(), saddles.begin() + kMaxSaddles, saddles.end(),
                     [](const Saddle& a, const Saddle& b) { return a.strength > b.strength; });
    // More saddles than the cap, nearly all as strong as the strongest: a dense regular lattice
    // (a checkerboard texture, a dot grid), which the strongest kMaxSaddles would only sample.
    if (saddles[static_cast<size_t>(kMaxSaddles)].strength >= kDenseLattice * strongest) {
      *dense = true;
    }
    saddles.resize(kMaxSaddles);
  }
  return saddles;
}

// Neighbours on a chessboard have opposite polarity: the Hessian of one is the other's negated,
// so its principal axes are turned by 90 degrees (within 25).
bool opposite_polarity(float a, float b) {
  constexpr double kPi = std::numbers::pi;
  double d = std::fmod(static_cast<double>(a) - b - kPi / 2, kPi);
  if (d < 0) d += kPi;
  return std::min(d, kPi - d) < 25.0 * kPi / 180.0;
}

double norm(const cv::Point2f& v) { return std::hypot(v.x, v.y); }

// The kNeighbours nearest saddles of each saddle, from a grid of cells searched ring by ring
// until the ring lies farther than the farthest of the neighbours found.
std::vector<std::array<int, kNeighbours>> nearest_neighbours(const std::vector<Saddle>& saddles,
                                                             cv::Size size) {
  constexpr int kCell = 16;
  const int gw = size.width / kCell + 1;
  const int gh = size.height / kCell + 1;
  std::vector<std::vector<int>> grid(static_cast<size_t>(gw) * static_cast<size_t>(gh));
  auto cell_of = [&](const cv::Point2f& p) {
    return std::pair{std::clamp(static_cast<int>(p.x) / kCell, 0, gw - 1),
                     std::clamp(static_cast<int>(p.y) / kCell, 0, gh - 1)};
  };
  for (size_t i = 0; i < saddles.size(); ++i) {
    const auto [cx, cy] = cell_of(saddles[i].p);
    grid[static_cast<size_t>(cy) * static_cast<size_t>(gw) + static_cast<size_t>(cx)].push_back(
        static_cast<int>(i));
  }
  std::vector<std::array<int, kNeighbours>> out(saddles.size());
  std::vector<std::pair<float, int>> found;
  for (size_t i = 0; i < saddles.size(); ++i) {
    const cv::Point2f p = saddles[i].p;
    const auto [cx, cy] = cell_of(p);
    found.clear();
    for (int ring = 0; ring <= std::max(gw, gh); ++ring) {
      for (int y = cy - ring; y <= cy + ring; ++y) {
        for (int x = cx - ring; x <= cx + ring; ++x) {
          if (std::max(std::abs(x - cx), std::abs(y - cy)) != ring) continue;
          if (x < 0 || y < 0 || x >= gw || y >= gh) continue;
          for (const int j :
               grid[static_cast<size_t>(y) * static_cast<size_t>(gw) + static_cast<size_t>(x)]) {
            if (j == static_cast<int>(i)) continue;
            const cv::Point2f d = saddles[static_cast<size_t>(j)].p - p;
            found.emplace_back(d.dot(d), j);
          }
        }
      }
      if (found.size() >= static_cast<size_t>(kNeighbours)) {
        std::partial_sort(found.begin(), found.begin() + kNeighbours, found.end());
        found.resize(kNeighbours);
        // Every saddle not yet seen lies at least `ring * kCell` px away.
        const float reach = static_cast<float>(ring * kCell);
        if (found.back().first <= reach * reach) break;
      }
    }
    for (int k = 0; k < kNeighbours; ++k) {
      out[i][static_cast<size_t>(k)] =
          k < static_cast<int>(found.size()) ? found[static_cast<size_t>(k)].second : -1;
    }
  }
  return out;
}

// The crossings among `saddles` (ChessboardLattice, in the pixels of the level they were found
// on).
ChessboardLattice count_crossings(const std::vector<Saddle>& saddles, cv::Size size) {
  if (saddles.size() <= static_cast<size_t>(kNeighbours)) return {};
  const auto neighbours = nearest_neighbours(saddles, size);
  std::vector<double> shorter;
  std::vector<double> longer;
  cv::Point2f low(std::numeric_limits<float>::max(), std::numeric_limits<float>::max());
  cv::Point2f high(std::numeric_limits<float>::lowest(), std::numeric_limits<float>::lowest());
  for (size_t i = 0; i < saddles.size(); ++i) {
    std::array<cv::Point2f, kNeighbours> v;
    std::array<bool, kNeighbours> flipped{};
    for (size_t k = 0; k < v.size(); ++k) {
      const int j = neighbours[i][k];
      if (j < 0) continue;
      const Saddle& q = saddles[static_cast<size_t>(j)];
      v[k] = q.p - saddles[i].p;
      flipped[k] = opposite_polarity(saddles[i].angle, q.angle);
    }
    // Pairs of opposite neighbours: u and -u within 25% and of similar length.
    std::vector<cv::Point2f> axes;
    for (size_t j = 0; j < v.size(); ++j) {
      if (!flipped[j]) continue;
      for (size_t k = j + 1; k < v.size(); ++k) {
        if (!flipped[k]) continue;
        const double lj = norm(v[j]);
        const double lk = norm(v[k]);
        if (norm(v[j] + v[k]) < 0.25 * std::min(lj, lk) && lj > 0.6 * lk && lk > 0.6 * lj) {
          axes.push_back(v[j]);
        }
      }
    }
    // A crossing: two such axes, not parallel (|cos| < 0.8) and of comparable length.
    bool crossing = false;
    for (size_t p = 0; p < axes.size() && !crossing; ++p) {
      for (size_t q = p + 1; q < axes.size() && !crossing; ++q) {
        const double lp = norm(axes[p]);
        const double lq = norm(axes[q]);
        const double cosine = std::abs(axes[p].dot(axes[q])) / (lp * lq);
        crossing = cosine < 0.8 && lp > 0.4 * lq && lp < 2.5 * lq;
        if (crossing) {
          shorter.push_back(std::min(lp, lq));
          longer.push_back(std::max(lp, lq));
          low = {std::min(low.x, saddles[i].p.x), std::min(low.y, saddles[i].p.y)};
          high = {std::max(high.x, saddles[i].p.x), std::max(high.y, saddles[i].p.y)};
        }
      }
    }
  }
  ChessboardLattice lattice;
  lattice.crossings = static_cast<int>(shorter.size());
  lattice.spacing_px = median(std::move(shorter));
  lattice.long_spacing_px = median(std::move(longer));
  if (lattice.crossings > 0) lattice.extent = cv::Rect2d(low, high);
  return lattice;
}

}  // namespace

ChessboardLattice chessboard_lattice(const cv::Mat& gray, bool shrunk) {
  ChessboardLattice best;
  cv::Mat level = gray;
  double scale = 1;  // input pixels per pixel of `level`
  // Frames above kMaxSide px are examined from a half-size copy: a quarter of the cost (19-28 ms
  // instead of 85-120 ms at 1280 px, most of it page faults of fresh buffers), and boards of 8 px
  // squares at 1280 px still give 10 or more crossings there. A copy already shrunk is examined
  // as it is: halved again, a 1920x1080 frame was examined at a quarter of its resolution and
  // boards of 11-16 px squares there gave too few crossings (7 of 41 boards turned away).
  if (!shrunk && std::max(gray.cols, gray.rows) > kMaxSide) {
    cv::resize(gray, level, cv::Size(gray.cols / 2, gray.rows / 2), 0, 0, cv::INTER_AREA);
    scale = 2;
  }
  if (std::min(level.cols, level.rows) < kMinSide) return {kCannotTell, 0, 0, {}};
  for (int l = 0; l < kLevels && std::min(level.cols, level.rows) >= kMinSide; ++l) {
    bool dense = false;
    const std::vector<Saddle> saddles = find_saddles(level, &dense);
    if (dense) return {kCannotTell, 0, 0, {}};
    ChessboardLattice here = count_crossings(saddles, level.size());
    if (here.crossings > best.crossings) {
      here.spacing_px *= scale;
      here.long_spacing_px *= scale;
      here.extent = cv::Rect2d(here.extent.x * scale, here.extent.y * scale,
                               here.extent.width * scale, here.extent.height * scale);
      best = here;
    }
    cv::Mat smaller;
    cv::resize(level, smaller, cv::Size(level.cols / 2, level.rows / 2), 0, 0, cv::INTER_AREA);
    level = smaller;
    scale *= 2;
  }
  return best;
}

int chessboard_crossings(const cv::Mat& gray) { return chessboard_lattice(gray).crossings; }

int chessboard_crossings_needed(int cols, int rows) {
  if (cols < 3 || rows < 3) return 0;
  return std::max(1, (cols - 2) * (rows - 2) / 4);
}

}  // namespace posecal
