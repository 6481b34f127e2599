#include "board/board.hpp"

#include <zlib.h>

#include <algorithm>
#include <array>
#include <charconv>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <functional>
#include <limits>
#include <map>
#include <opencv2/aruco/charuco.hpp>
#include <opencv2/calib3d.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <optional>
#include <sstream>

#include "board/board_internal.hpp"
#include "board/saddles.hpp"
#include "common/error.hpp"

namespace posecal {

namespace {

const std::map<std::string, int>& dictionary_table() {
  static const std::map<std::string, int> table = {
      {"DICT_4X4_50", cv::aruco::DICT_4X4_50},
      {"DICT_4X4_100", cv::aruco::DICT_4X4_100},
      {"DICT_4X4_250", cv::aruco::DICT_4X4_250},
      {"DICT_4X4_1000", cv::aruco::DICT_4X4_1000},
      {"DICT_5X5_50", cv::aruco::DICT_5X5_50},
      {"DICT_5X5_100", cv::aruco::DICT_5X5_100},
      {"DICT_5X5_250", cv::aruco::DICT_5X5_250},
      {"DICT_5X5_1000", cv::aruco::DICT_5X5_1000},
      {"DICT_6X6_50", cv::aruco::DICT_6X6_50},
      {"DICT_6X6_100", cv::aruco::DICT_6X6_100},
      {"DICT_6X6_250", cv::aruco::DICT_6X6_250},
      {"DICT_6X6_1000", cv::aruco::DICT_6X6_1000},
      {"DICT_7X7_50", cv::aruco::DICT_7X7_50},
      {"DICT_7X7_100", cv::aruco::DICT_7X7_100},
      {"DICT_7X7_250", cv::aruco::DICT_7X7_250},
      {"DICT_7X7_1000", cv::aruco::DICT_7X7_1000},
      {"DICT_ARUCO_ORIGINAL", cv::aruco::DICT_ARUCO_ORIGINAL},
      {"DICT_APRILTAG_16h5", cv::aruco::DICT_APRILTAG_16h5},
      {"DICT_APRILTAG_25h9", cv::aruco::DICT_APRILTAG_25h9},
      {"DICT_APRILTAG_36h10", cv::aruco::DICT_APRILTAG_36h10},
      {"DICT_APRILTAG_36h11", cv::aruco::DICT_APRILTAG_36h11},
  };
  return table;
}

[[noreturn]] void bad_spec(const std::string& spec, const std::string& why) {
  throw Error(ErrorCode::kInvalidArgument, "target spec '" + spec + "': " + why);
}

// A length in metres: a plain decimal number (no hex, inf or nan) in [min_m, kMaxLengthM].
double parse_length(const std::string& spec, const std::string& field, const std::string& text,
                    double min_m) {
  const bool decimal =
      !text.empty() && text.find_first_not_of("0123456789.eE+-") == std::string::npos;
  size_t used = 0;
  double v = 0;
  try {
    if (decimal) v = std::stod(text, &used);
  } catch (...) {  // out of range (underflow or overflow)
    used = 0;
  }
  if (!decimal || used != text.size()) bad_spec(spec, field + " '" + text + "' is not a number");
  if (!std::isfinite(v) || v <= 0) bad_spec(spec, field + " must be a positive length in metres");
  if (v > BoardSpec::kMaxLengthM) {
    bad_spec(spec, field + " " + text + " m is implausible (lengths are in metres, at most 10)");
  }
  if (v < min_m) {
    bad_spec(spec,
             field + " " + text + " m is below the smallest, " + std::to_string(min_m) + " m");
  }
  return v;
}

// "COLSxROWS": two decimal integers.
bool parse_grid(const std::string& text, int* cols, int* rows) {
  const size_t x = text.find('x');
  if (x == std::string::npos) return false;
  const auto whole = [](const std::string& t, int* out) {
    const auto r = std::from_chars(t.data(), t.data() + t.size(), *out);
    return !t.empty() && r.ec == std::errc() && r.ptr == t.data() + t.size();
  };
  return whole(text.substr(0, x), cols) && whole(text.substr(x + 1), rows);
}

}  // namespace

BoardSpec BoardSpec::parse(const std::string& spec) {
  std::vector<std::string> f;
  std::stringstream ss(spec);
  std::string item;
  while (std::getline(ss, item, ':')) f.push_back(item);
  if (f.empty()) bad_spec(spec, "empty; expected e.g. charuco:9x6:0.028:0.0182:DICT_4X4_50");
  BoardSpec out;
  if (f[0] == "charuco") {
    out.type = BoardType::kCharuco;
    if (f.size() != 5) bad_spec(spec, "expected charuco:COLSxROWS:SQUARE_M:MARKER_M:DICT");
  } else if (f[0] == "chessboard") {
    out.type = BoardType::kChessboard;
    if (f.size() != 3) bad_spec(spec, "expected chessboard:COLSxROWS:SQUARE_M (inner corners)");
  } else {
    bad_spec(spec, "unknown target type '" + f[0] + "' (charuco or chessboard)");
  }
  int cols = 0, rows = 0;
  if (!parse_grid(f[1], &cols, &rows)) {
    bad_spec(spec, "grid '" + f[1] + "' is not COLSxROWS");
  }
  out.cols = cols;
  out.rows = rows;
  out.square_length_m = parse_length(spec, "square length", f[2], BoardSpec::kMinSquareM);
  if (out.type == BoardType::kCharuco) {
    out.marker_length_m = parse_length(spec, "marker length", f[3], 0.0);
    out.dictionary = f[4];
  } else {
    out.marker_length_m = 0;
    out.dictionary.clear();
  }
  try {
    out.validate();
  } catch (const Error& e) {
    bad_spec(spec, e.what());
  }
  return out;
}

void BoardSpec::validate() const {
  auto fail = [](const std::string& why) { throw Error(ErrorCode::kInvalidArgument, why); };
  const int min_side =
      3;  // OpenCV's chessboard detector needs 3; a 2-row ChArUco's corners are collinear
  if (cols < min_side || rows < min_side || cols > kMaxSide || rows > kMaxSide) {
    fail("grid " + std::to_string(cols) + "x" + std::to_string(rows) + " must be between 3x3 and " +
         std::to_string(kMaxSide) + "x" + std::to_string(kMaxSide));
  }
  if (!(square_length_m >= kMinSquareM && square_length_m <= kMaxLengthM)) {
    fail("square length must be in [" + std::to_string(kMinSquareM) + ", " +
         std::to_string(kMaxLengthM) + "] m");
  }
  if (type == BoardType::kCharuco) {
    // The ratios are decimal fractions: a relative 1e-12 lets a marker of exactly 0.1 (or 0.95)
    // of the square, written in decimal, through (0.0028 / 0.028 is just below 0.1 in binary).
    const double tol = 1.0 + 1e-12;
    if (!(marker_length_m * tol >= kMinMarkerRatio * square_length_m) ||
        !(marker_length_m <= kMaxMarkerRatio * square_length_m * tol)) {
      fail("marker length must be between " + std::to_string(kMinMarkerRatio) + " and " +
           std::to_string(kMaxMarkerRatio) + " of the square length");
    }
    auto it = dictionary_table().find(dictionary);
    if (it == dictionary_table().end()) fail("unknown ArUco dictionary '" + dictionary + "'");
    const int markers = (cols * rows) / 2;
    auto dict = cv::aruco::getPredefinedDictionary(it->second);
    if (markers > dict->bytesList.rows) {
      fail("board needs " + std::to_string(markers) + " markers but " + dictionary + " has only " +
           std::to_string(dict->bytesList.rows));
    }
  }
}

namespace {

// The shortest plain decimal that parses back to exactly `v` ("0.028"): the spec is written into
// result files and journals and read back, so it must round-trip (a 10-digit text once turned a
// marker of exactly 0.1 of the square into one just below it, which parse refuses).
std::string length_text(double v) {
  char buf[512];
  const auto r = std::to_chars(buf, buf + sizeof buf, v, std::chars_format::fixed);
  return r.ec == std::errc() ? std::string(buf, r.ptr) : std::to_string(v);
}

}  // namespace

std::string BoardSpec::to_string() const {
  std::ostringstream os;
  if (type == BoardType::kCharuco) {
    os << "charuco:" << cols << "x" << rows << ":" << length_text(square_length_m) << ":"
       << length_text(marker_length_m) << ":" << dictionary;
  } else {
    os << "chessboard:" << cols << "x" << rows << ":" << length_text(square_length_m);
  }
  return os.str();
}

Board::Board(const BoardSpec& spec) : spec_(spec) {
  spec_.validate();
  auto impl = std::make_shared<Impl>();
  const double s = spec_.square_length_m;
  if (spec_.type == BoardType::kCharuco) {
    impl->dictionary = cv::aruco::getPredefinedDictionary(dictionary_table().at(spec_.dictionary));
    impl->board = cv::aruco::CharucoBoard::create(
        spec_.cols, spec_.rows, static_cast<float>(spec_.square_length_m),
        static_cast<float>(spec_.marker_length_m), impl->dictionary);
    impl->params = cv::aruco::DetectorParameters::create();
    // Corner ids as OpenCV numbers them: row-major over the inner corners. Recomputed in double
    // precision rather than taken from the board's float copy.
    for (int i = 0; i < spec_.rows - 1; ++i)
      for (int j = 0; j < spec_.cols - 1; ++j) corners_.emplace_back((j + 1) * s, (i + 1) * s, 0.0);
  } else {
    for (int i = 0; i < spec_.rows; ++i)
      for (int j = 0; j < spec_.cols; ++j) corners_.emplace_back((j + 1) * s, (i + 1) * s, 0.0);
  }
  impl_ = impl;
}

Board::~Board() = default;
Board::Board(const Board&) = default;
Board& Board::operator=(const Board&) = default;

int Board::marker_grid_cells() const {
  if (spec_.type != BoardType::kCharuco) return 0;
  return impl_->dictionary->markerSize + 2 * impl_->params->markerBorderBits;
}

cv::Size2d Board::board_size_m() const {
  const double s = spec_.square_length_m;
  if (spec_.type == BoardType::kCharuco) return {spec_.cols * s, spec_.rows * s};
  return {(spec_.cols + 1) * s, (spec_.rows + 1) * s};
}

std::vector<cv::Point3d> Board::outline() const {
  const cv::Size2d sz = board_size_m();
  return {{0, 0, 0}, {sz.width, 0, 0}, {sz.width, sz.height, 0}, {0, sz.height, 0}};
}

namespace {

cv::Mat to_gray(const cv::Mat& image) {
  if (image.empty()) throw Error(ErrorCode::kInvalidArgument, "detect: empty image");
  if (image.depth() != CV_8U)
    throw Error(ErrorCode::kInvalidArgument, "detect: image is not 8-bit");
  if (image.channels() == 1) return image;
  cv::Mat gray;
  if (image.channels() == 3) {
    cv::cvtColor(image, gray, cv::COLOR_BGR2GRAY);
  } else if (image.channels() == 4) {
    cv::cvtColor(image, gray, cv::COLOR_BGRA2GRAY);
  } else {
    throw Error(ErrorCode::kInvalidArgument, "detect: image must have 1, 3 or 4 channels");
  }
  return gray;
}

// The shortest distance between neighbouring corners of a chessboard's cols x rows grid.
double min_corner_spacing(const std::vector<cv::Point2f>& pts, int cols, int rows) {
  double min_d = 1e9;
  for (int i = 0; i < rows; ++i) {
    for (int j = 0; j < cols; ++j) {
      const cv::Point2f& p = pts[i * cols + j];
      if (j + 1 < cols) min_d = std::min(min_d, cv::norm(p - pts[i * cols + j + 1]));
      if (i + 1 < rows) min_d = std::min(min_d, cv::norm(p - pts[(i + 1) * cols + j]));
    }
  }
  return min_d;
}

// Subpixel window half-size from the smallest distance between neighbouring corners: large
// enough to see the saddle, small enough not to reach the next corner.
int subpix_half_window(const std::vector<cv::Point2f>& pts, int cols, int rows, int max_hw = 11) {
  return std::clamp(static_cast<int>(min_corner_spacing(pts, cols, rows) * 0.4), 2, max_hw);
}

// Chebyshev (L-infinity) distance from the origin to the segment a-b: cornerSubPix's window is a
// square, so this is how far a window centred at the origin can reach before touching it. The
// distance is convex and piecewise linear in the segment parameter, so its minimum lies at an end
// or where a coordinate vanishes or |x| = |y|.
double chebyshev_distance_to_segment(const cv::Point2d& a, const cv::Point2d& b) {
  const cv::Point2d d = b - a;
  double best = std::max(std::abs(a.x), std::abs(a.y));
  best = std::min(best, std::max(std::abs(b.x), std::abs(b.y)));
  auto consider = [&](double num, double den) {
    if (std::abs(den) < 1e-12) return;
    const double t = num / den;
    if (t <= 0 || t >= 1) return;
    const cv::Point2d p = a + t * d;
    best = std::min(best, std::max(std::abs(p.x), std::abs(p.y)));
  };
  consider(-a.x, d.x);           // x = 0
  consider(-a.y, d.y);           // y = 0
  consider(a.y - a.x, d.x - d.y);  // x = y
  consider(-a.x - a.y, d.x + d.y);  // x = -y
  return best;
}

// How far a square window centred on a ChArUco corner reaches before it touches one of the four
// adjacent squares' markers, from the local image axes of one square step along the board's x
// (ju) and y (jv). `inset` is the marker's distance from its square's edges in squares
// ((1 - marker / square) / 2). All four squares are treated as holding a marker (conservative).
double marker_clearance_px(const cv::Point2d& ju, const cv::Point2d& jv, double inset) {
  double best = std::numeric_limits<double>::infinity();
  const double lo = inset, hi = 1.0 - inset;
  for (int su : {-1, 1})
    for (int sv : {-1, 1}) {
      const cv::Point2d q[4] = {su * lo * ju + sv * lo * jv, su * hi * ju + sv * lo * jv,
                                su * hi * ju + sv * hi * jv, su * lo * ju + sv * hi * jv};
      for (int k = 0; k < 4; ++k) best = std::min(best, chebyshev_distance_to_segment(q[k], q[(k + 1) % 4]));
    }
  return best;
}

// The Gaussian (sigma, px) the image is smoothed with before our refinement of a ChArUco corner
// whose window clears the adjacent markers by twice that beyond kMarginPx. On a sharp image few
// pixels about the saddle carry a gradient, and cornerSubPix's fit of them is biased by where the
// edges cross the pixel grid: the mean error of a corner over 6 noise draws (its bias) was 0.046
// px RMS at blur 0.5 px on the ray-cast renderer, 0.023 px with this smoothing (the warping
// renderer 0.037 -> 0.029); the noise about the mean unchanged (0.011 -> 0.012 px). In closed
// loops (C525, 30 report cameras) the default's eps_gt fell from 0.350 to 0.189 px with a sharp
// renderer. Smoothing every window gained more there (0.156 px) but spread the markers' edges
// into the windows of steep boards: corners pulled up to 0.9-1.4 px off at 65 degrees of tilt
// (bias 0.10 -> 0.20-0.24 px RMS), where the clearance rule had brought them back; smoothing with
// the window shrunk by the smoothing's reach was worse still. 1.4 px pulled corners of boards
// tilted 55 degrees off on the warping renderer. `build/bin/detector_bias`, `bench_pose_selection`;
// docs/benchmarks.md, "Smoothing before the refinement".
constexpr double kRefineSmoothingPx = 1.0;

// What a refinement window keeps clear of the nearest edge that does not pass through its corner
// (a marker's border, a square's far edge) beyond its own reach: blur and the estimate's own
// movement during the refinement.
constexpr double kMarginPx = 1.5;

// One square step along a grid line at corner `c`, from its neighbours on either side (either may
// be missing): the central difference, or the one-sided one, or nothing for an isolated corner.
std::optional<cv::Point2d> grid_step(const cv::Point2f* before, const cv::Point2d& c,
                                     const cv::Point2f* after) {
  if (before && after) return (cv::Point2d(*after) - cv::Point2d(*before)) * 0.5;
  if (after) return cv::Point2d(*after) - c;
  if (before) return c - cv::Point2d(*before);
  return std::nullopt;
}

// The steps along the board's two axes at corner `id` (ChArUco numbering, `corners_per_row` a
// row) from an affine map of board grid to image fitted to the detected corners within two grid
// steps of it (Chebyshev), the corner among them; none unless they span two rows and two columns
// and five or more are found (so a missing neighbour leaves enough to fit).
std::optional<std::pair<cv::Point2d, cv::Point2d>> local_grid_steps(
    const std::vector<int>& ids, const std::vector<cv::Point2f>& corners, int corners_per_row,
    int id) {
  constexpr int kReach = 2;
  const int col = id % corners_per_row, row = id / corners_per_row;
  cv::Matx33d normal = cv::Matx33d::zeros();
  cv::Matx32d rhs = cv::Matx32d::zeros();
  int n = 0, cols_lo = col, cols_hi = col, rows_lo = row, rows_hi = row;
  for (size_t k = 0; k < ids.size(); ++k) {
    const int c = ids[k] % corners_per_row - col, r = ids[k] / corners_per_row - row;
    if (std::abs(c) > kReach || std::abs(r) > kReach) continue;
    const cv::Vec3d x(c, r, 1);
    normal += x * x.t();
    rhs += x * cv::Matx12d(corners[k].x, corners[k].y);
    cols_lo = std::min(cols_lo, col + c);
    cols_hi = std::max(cols_hi, col + c);
    rows_lo = std::min(rows_lo, row + r);
    rows_hi = std::max(rows_hi, row + r);
    ++n;
  }
  if (n < 5 || cols_lo == cols_hi || rows_lo == rows_hi) return std::nullopt;
  cv::Matx32d a;
  if (!cv::solve(normal, rhs, a, cv::DECOMP_LU)) return std::nullopt;  // the corners on one line
  return std::pair{cv::Point2d(a(0, 0), a(0, 1)), cv::Point2d(a(1, 0), a(1, 1))};
}

// cornerSubPix on one corner with a window of half-size `hw`; `smooth`: on the frame smoothed by
// kRefineSmoothingPx, on a patch about the corner (the pixels beyond it taken from the frame, not
// mirrored) wide enough for its window, the corner's movement and the kernel, so the cost stays
// with the corners whatever the frame's size.
cv::Point2f refine_corner(const cv::Mat& gray, cv::Point2f corner, int hw, bool smooth) {
  const cv::TermCriteria until(cv::TermCriteria::EPS + cv::TermCriteria::COUNT, 50, 1e-3);
  const int reach = hw + 2 + static_cast<int>(std::ceil(3 * kRefineSmoothingPx));
  const cv::Point c(corner);
  const cv::Rect patch = cv::Rect(c.x - reach, c.y - reach, 2 * reach + 1, 2 * reach + 1) &
                         cv::Rect(0, 0, gray.cols, gray.rows);
  // (cornerSubPix needs 2 hw + 5 pixels a side; a patch cut shorter by the frame's edge is
  // refined in the frame as it is.)
  cv::Mat smoothed;
  cv::Point2f origin(0, 0);
  if (smooth && std::min(patch.width, patch.height) >= 2 * hw + 5) {
    cv::GaussianBlur(gray(patch), smoothed, cv::Size(), kRefineSmoothingPx);
    origin = cv::Point2f(static_cast<float>(patch.x), static_cast<float>(patch.y));
  }
  std::vector<cv::Point2f> pts = {corner - origin};
  cv::cornerSubPix(smoothed.empty() ? gray : smoothed, pts, cv::Size(hw, hw), cv::Size(-1, -1),
                   until);
  return pts[0] + origin;
}

// OpenCV refines ChArUco corners with a window of at most 11x11 (cornerRefinementWinSize = 5),
// shrunk near the markers' corners; too small for large squares, and on tilted boards it leaves
// biases of up to 0.4 px. Refine again with a window scaled to the local square size (12% of the
// distance to the nearest neighbouring corner) that also stays clear of the adjacent markers'
// borders, measured along the local, possibly foreshortened and skewed, image axes of the board:
// at tilts beyond ~60 degrees a window from the corner spacing alone reaches a marker's border
// and pulls the corner several pixels off (docs/benchmarks.md, "The corner detector's bias").
// A corner whose markers come closer than kMinClearancePx is dropped: no window both sees the
// saddle and misses the markers. A window clear of the markers sees the image smoothed
// (kRefineSmoothingPx). A corner with no detected neighbour along one axis takes that axis from
// the corners about it (local_grid_steps); only one without enough of them keeps OpenCV's
// refinement (on a 110-degree lens 45 degrees off the axis such corners had kept biases of up to
// 1.03 px; docs/benchmarks.md, "Corners at the edge of what was detected").
void refine_charuco_corners(const cv::Mat& gray, int corners_per_row, double marker_inset,
                            std::vector<int>* ids, std::vector<cv::Point2f>* corners) {
  constexpr double kMinClearancePx = kMarginPx + 1.0;
  std::map<int, size_t> index;
  for (size_t i = 0; i < ids->size(); ++i) index[(*ids)[i]] = i;
  auto at = [&](int id) -> const cv::Point2f* {
    auto it = index.find(id);
    return it == index.end() ? nullptr : &(*corners)[it->second];
  };
  auto step = [&](int id, int prev, int next) {
    return grid_step(prev >= 0 ? at(prev) : nullptr, (*corners)[index[id]],
                     next >= 0 ? at(next) : nullptr);
  };
  std::vector<bool> drop(ids->size(), false), smooth(ids->size(), false);
  std::vector<int> half_window(ids->size(),
                               0);  // 0: isolated (OpenCV's refinement kept) or dropped
  for (size_t i = 0; i < ids->size(); ++i) {
    const int id = (*ids)[i], col = id % corners_per_row;
    auto ju = step(id, col > 0 ? id - 1 : -1, col + 1 < corners_per_row ? id + 1 : -1);
    auto jv = step(id, id - corners_per_row, id + corners_per_row);
    // A corner without a neighbour along one of the board's axes (at the image's edge, or next
    // to markers not found): that axis from the corners about it.
    if (!ju || !jv) {
      const auto local = local_grid_steps(*ids, *corners, corners_per_row, id);
      if (!local) continue;  // isolated corner: keep OpenCV's refinement
      if (!ju) ju = local->first;
      if (!jv) jv = local->second;
    }
    const double d = std::min(cv::norm(*ju), cv::norm(*jv));
    const double clearance = marker_clearance_px(*ju, *jv, marker_inset);
    if (clearance < kMinClearancePx) {
      drop[i] = true;
      continue;
    }
    const int by_spacing = std::clamp(static_cast<int>(0.12 * d), 2, 10);
    const int by_markers = static_cast<int>(std::floor(clearance - kMarginPx));
    half_window[i] = std::max(1, std::min(by_spacing, by_markers));
    // Smoothed where the window clears the markers by the smoothing's reach (2 sigma) as well.
    smooth[i] = clearance - kMarginPx - half_window[i] >= 2 * kRefineSmoothingPx;
  }
  for (size_t i = 0; i < ids->size(); ++i) {
    if (half_window[i] > 0)
      (*corners)[i] = refine_corner(gray, (*corners)[i], half_window[i], smooth[i]);
  }
  size_t kept = 0;
  for (size_t i = 0; i < ids->size(); ++i) {
    if (drop[i]) continue;
    (*ids)[kept] = (*ids)[i];
    (*corners)[kept] = (*corners)[i];
    ++kept;
  }
  ids->resize(kept);
  corners->resize(kept);
}

// How far a square window centred on a chessboard's inner corner reaches before it touches an
// edge of the four squares about it that does not pass through the corner, from the local image
// axes of one square step along the board's x (ju) and y (jv).
double square_clearance_px(const cv::Point2d& ju, const cv::Point2d& jv) {
  double best = std::numeric_limits<double>::infinity();
  for (int su : {-1, 1})
    for (int sv : {-1, 1}) {
      const cv::Point2d far = su * ju + sv * jv;
      best = std::min({best, chebyshev_distance_to_segment(su * ju, far),
                       chebyshev_distance_to_segment(sv * jv, far)});
    }
  return best;
}

// A chessboard's corners, already refined on the frame (cornerSubPix, half-window `hw`), refined
// again on the frame smoothed by kRefineSmoothingPx where the window clears the far edges of the
// squares about the corner by twice that beyond kMarginPx, as ChArUco corners are
// (refine_charuco_corners); the first refinement gives this one its start. The bias of a
// sharp board's corners (their mean error over noise draws) fell from 0.044 to 0.020 px RMS at
// blur 0.5 px on the ray-cast renderer (warping renderer 0.032 -> 0.025), no tilt or blur worse;
// the window from the corner spacing never reached those edges on the boards measured, so it is
// not shrunk (`detector_bias --board chessboard:9x6:0.028`; docs/benchmarks.md, "Smoothing
// before the refinement").
void smooth_refine_chessboard_corners(const cv::Mat& gray, int cols, int rows, int hw,
                                      std::vector<cv::Point2f>* corners) {
  const std::vector<cv::Point2f> pts = *corners;
  auto at = [&](int r, int c) -> const cv::Point2f* {
    return r >= 0 && c >= 0 && r < rows && c < cols ? &pts[static_cast<size_t>(r * cols + c)]
                                                    : nullptr;
  };
  // One square step along (dr, dc); a chessboard has at least two corners along each axis.
  auto step = [&](int r, int c, int dr, int dc) {
    return *grid_step(at(r - dr, c - dc), *at(r, c), at(r + dr, c + dc));
  };
  for (int r = 0; r < rows; ++r) {
    for (int c = 0; c < cols; ++c) {
      const double clearance = square_clearance_px(step(r, c, 0, 1), step(r, c, 1, 0));
      if (clearance - kMarginPx - hw < 2 * kRefineSmoothingPx) continue;
      const auto i = static_cast<size_t>(r * cols + c);
      (*corners)[i] = refine_corner(gray, pts[i], hw, true);
    }
  }
}
}  // namespace

namespace {

// A copy for the search, shrunk by the integer factor `k` (pixel averaging: cv::resize's INTER_AREA
// takes its fast path for an integer factor; the last < k columns and rows are left out).
cv::Mat shrink_for_search(const cv::Mat& gray, int k) {
  const cv::Mat whole = gray(cv::Rect(0, 0, gray.cols / k * k, gray.rows / k * k));
  cv::Mat small;
  cv::resize(whole, small, cv::Size(gray.cols / k, gray.rows / k), 0, 0, cv::INTER_AREA);
  return small;
}

// The contours of the dark blobs of `gray` and of their holes, as OpenCV's marker search finds
// them at one scale: adaptive threshold (mean of a `window` square, less `constant`), every
// contour point kept (its length is the contour's perimeter as OpenCV counts it).
std::vector<std::vector<cv::Point>> threshold_contours(const cv::Mat& gray, int window,
                                                       double constant) {
  cv::Mat bin;
  cv::adaptiveThreshold(gray, bin, 255, cv::ADAPTIVE_THRESH_MEAN_C, cv::THRESH_BINARY_INV, window,
                        constant);
  std::vector<std::vector<cv::Point>> contours;
  cv::findContours(bin, contours, cv::RETR_LIST, cv::CHAIN_APPROX_NONE);
  return contours;
}

// Candidate marker quads of one adaptive-threshold scale, tested as OpenCV 4.6's marker search
// tests its contours: a closed contour of [min_len, max_len] points (its perimeter, as OpenCV
// counts it) whose polygonal approximation (tolerance `accuracy` x its length) is a convex
// quadrilateral with sides of at least `corner_rate` x its length and no corner within `border`
// px of the image's edge.
struct QuadTest {
  int window = 0;  // adaptive threshold window (odd)
  double constant = 0;
  int min_len = 0, max_len = 0;
  double accuracy = 0, corner_rate = 0;
  int border = 0;
};

// The number of quads `gray` gives at one scale, counting stopped at `stop_at`; with
// `perimeters`, their lengths too. The length test comes first: most contours of a frame of noise
// or clutter are shorter than a marker, and approxPolyDP is the costly part.
int count_quads(const std::vector<std::vector<cv::Point>>& contours, cv::Size size, const QuadTest& t,
                int stop_at, std::vector<int>* perimeters) {
  int n = 0;
  std::vector<cv::Point> poly;
  for (const auto& c : contours) {
    const int len = static_cast<int>(c.size());
    if (len < t.min_len || len > t.max_len) continue;
    cv::approxPolyDP(c, poly, len * t.accuracy, true);
    if (poly.size() != 4 || !cv::isContourConvex(poly)) continue;
    const double min_side = t.corner_rate * len;
    bool quad = true;
    for (int j = 0; j < 4 && quad; ++j) {
      const cv::Point& p = poly[j];
      const cv::Point d = p - poly[(j + 1) % 4];
      quad =
          static_cast<double>(d.x) * d.x + static_cast<double>(d.y) * d.y >= min_side * min_side &&
          p.x >= t.border && p.y >= t.border && p.x < size.width - t.border &&
          p.y < size.height - t.border;
    }
    if (!quad) continue;
    if (perimeters) perimeters->push_back(len);
    if (++n >= stop_at) break;
  }
  return n;
}

// Frames whose longer side is at most this are pre-counted at full resolution; larger ones are
// first counted on a half-size copy (a quarter of the pixels), and only when that count exceeds
// the cap at full resolution. The fuzzer's slow 256x256 frames are textures of 1-2 px dashes,
// which a half-size copy averages away.
constexpr int kPrecountFullResolutionMaxSide = 640;

using Contours = std::vector<std::vector<cv::Point>>;

// Busy frames, issue 16. OpenCV's chessboard search links the quads it finds pairwise, at each of
// its thresholds and dilations, and when no board is found it tries them all: a 1280x720 frame
// of uniform noise took 0.8-1.4 s, a checkerboard texture of 14 px squares 5.3 s, of 20 px 1.2 s,
// strong sensor noise (sigma 40-80 grey levels, no board) 0.2-1.0 s, where a board frame takes
// 3-15 ms. OpenCV's marker search thresholds at three scales and follows every contour: 135 ms on
// 1280x720 uniform noise, which has no quads for the candidate cap to drop. Such frames show many
// blobs of a chessboard square's size (8 px and more): contours of at least kBusyMinPoints points
// at half size, at the marker search's middle threshold (window 13, constant 7, halved). Measured
// there: noise 1358, the 14 px checkerboard 2251, sensor noise of sigma 20-80 1200-1300; board
// frames 72-140 up to sigma 10 (a textured background included). Above the cap of them the frame
// is searched on a copy shrunk twice as much (corners refined at full resolution).
constexpr int kBusyMinPoints = 16;
constexpr int kQuarterSearchMinSide = 120;  // a busy chessboard frame's first, coarse search
constexpr int kCharucoBusyFactor = 2;  // ChArUco's limit: twice the cap (see detect_charuco)
constexpr int kHalfSizeWindow = 7;        // OpenCV's middle marker-search window (13) at half size
constexpr double kThresholdConstant = 7;  // OpenCV's adaptiveThreshConstant

Contours half_size_contours(const cv::Mat& search) {
  return threshold_contours(shrink_for_search(search, 2), kHalfSizeWindow, kThresholdConstant);
}

// Noisy search copies, issue 16. A shrunk copy of a huge frame of noise is noise again, of a
// lower amplitude (48 MP of uniform noise shrunk 7 times: sigma 10.6 grey levels): too weak for
// the half-size blob count above (5 blobs), yet strong against OpenCV's threshold constant (7),
// so its marker search follows 60,000-88,000 contours at each of its three scales (81 ms of
// 1 MP). Such a copy is searched on one shrunk twice as much (there: 11 ms). The measure is the
// median absolute difference of horizontally adjacent pixels (every 4th row): about 0.95 sigma of
// white noise, blind to a board's edges, which are few pixels. A shrunk copy of a camera's frame
// averages its sensor noise away (sigma 2-8 over k x k pixels) and natural texture shows 1-4 grey
// levels; 1280x720 frames (not shrunk) keep their search, sensor noise of sigma 15 included.
constexpr int kNoisyCopyDifference = 8;

int median_neighbour_difference(const cv::Mat& gray) {
  std::array<int, 256> histogram{};
  long long n = 0;
  for (int y = 0; y < gray.rows; y += 4) {
    const uchar* row = gray.ptr<uchar>(y);
    for (int x = 1; x < gray.cols; ++x) ++histogram[std::abs(row[x] - row[x - 1])];
    n += gray.cols - 1;
  }
  long long below = 0;
  for (int d = 0; d < 256; ++d) {
    below += histogram[d];
    if (2 * below >= n) return d;
  }
  return 255;
}

bool busy(const Contours& half_size, int cap) {
  int n = 0;
  for (const auto& c : half_size) {
    if (static_cast<int>(c.size()) >= kBusyMinPoints && ++n > cap) return true;
  }
  return false;
}

// Issue 16, cluttered frames (DetectorOptions::max_candidate_quads): when the search image gives
// more than `cap` candidate quads at OpenCV's middle threshold scale, raises the minimum marker
// perimeter to the smallest that leaves at most `cap` of them (the board's markers are usually
// the largest quads, the clutter small). Below the cap the parameters are left as they are, and
// the detection is OpenCV's, bit for bit. A search image of more than
// kPrecountFullResolutionMaxSide is counted first at half size: `half_size` is its
// half_size_contours when the caller has them (they are the ones the count needs with OpenCV's
// default threshold parameters), else they are made here. Cost on a 1280x720 frame: the
// half-size count, about 0.5 ms with a board; a frame of clutter adds the full-resolution count,
// 3-6 ms (docs/performance.md, "Cluttered frames").
void cap_candidate_quads(const cv::Mat& search, int cap, const Contours* half_size,
                         cv::aruco::DetectorParameters* params) {
  const int max_side = std::max(search.cols, search.rows);
  QuadTest full;
  // OpenCV thresholds at windows min, min + step, ..., max; the count takes the middle one.
  const int scales = (params->adaptiveThreshWinSizeMax - params->adaptiveThreshWinSizeMin) /
                         std::max(1, params->adaptiveThreshWinSizeStep) +
                     1;
  full.window =
      params->adaptiveThreshWinSizeMin + (scales - 1) / 2 * params->adaptiveThreshWinSizeStep;
  full.constant = params->adaptiveThreshConstant;
  full.min_len = static_cast<int>(params->minMarkerPerimeterRate * max_side);  // as OpenCV
  full.max_len = static_cast<int>(params->maxMarkerPerimeterRate * max_side);
  full.accuracy = params->polygonalApproxAccuracyRate;
  full.corner_rate = params->minCornerDistanceRate;
  full.border = params->minDistanceToBorder;
  if (max_side > kPrecountFullResolutionMaxSide) {
    // The same tests at half size: lengths, window and border halved, the approximation's
    // tolerance doubled (a pixel there is two; at OpenCV's tolerance the 5-px squares of a
    // 10-px checkerboard are not quads, at twice it all 4411 are, and 133 blobs of uniform noise).
    QuadTest half = full;
    half.window = std::max(3, (full.window / 2) | 1);
    half.min_len = full.min_len / 2;
    half.max_len = full.max_len / 2;
    half.accuracy = 2 * full.accuracy;
    half.border = full.border / 2;
    const cv::Size half_frame(search.cols / 2, search.rows / 2);
    const bool reuse =
        half_size && half.window == kHalfSizeWindow && half.constant == kThresholdConstant;
    const Contours made =
        reuse ? Contours{}
              : threshold_contours(shrink_for_search(search, 2), half.window, half.constant);
    if (count_quads(reuse ? *half_size : made, half_frame, half, cap + 1, nullptr) <= cap) return;
  }
  std::vector<int> perimeters;
  if (count_quads(threshold_contours(search, full.window, full.constant), search.size(), full,
                  std::numeric_limits<int>::max(), &perimeters) <= cap) {
    return;
  }
  std::nth_element(perimeters.begin(), perimeters.begin() + cap, perimeters.end(),
                   std::greater<int>());
  const int keep_from = perimeters[cap] + 1;  // the (cap + 1)-th longest and shorter go
  // OpenCV keeps contours of at least (int)(rate x longer side) points.
  params->minMarkerPerimeterRate =
      std::max(params->minMarkerPerimeterRate, (keep_from + 0.5) / max_side);
}

// DetectorOptions::max_candidate_quads for a board of `squares` squares: never below twice them,
// so that a large board does not push its own markers out; 0 when the cap is off.
int quad_cap(const DetectorOptions& options, int squares) {
  return options.max_candidate_quads > 0 ? std::max(options.max_candidate_quads, 2 * squares) : 0;
}

// The factor by which a frame is shrunk for the search (1: searched at full resolution).
int search_factor(const cv::Mat& gray, const DetectorOptions& options) {
  const int max_side = std::max(gray.cols, gray.rows);
  if (options.search_max_side <= 0 || max_side <= options.search_max_side) return 1;
  return (max_side + options.search_max_side - 1) / options.search_max_side;
}

// A point of the shrunk copy in full-resolution pixels (pixel centres at integer coordinates).
cv::Point2f to_full_resolution(const cv::Point2f& p, int k) {
  return {static_cast<float>((p.x + 0.5) * k - 0.5), static_cast<float>((p.y + 0.5) * k - 0.5)};
}

void check_detect_size(const cv::Mat& image) {
  const long long pixels = static_cast<long long>(image.cols) * image.rows;
  if (pixels > kMaxDetectPixels) {
    throw Error(ErrorCode::kInvalidArgument,
                "detect: a " + std::to_string(image.cols) + "x" + std::to_string(image.rows) +
                    " image is above the limit of " + std::to_string(kMaxDetectPixels / 1'000'000) +
                    " megapixels (kMaxDetectPixels)");
  }
}

// A busy chessboard frame's half-size copy with its dark details narrower than
// kClutterClosingPx closed (grey-level dilation, then erosion). OpenCV's chessboard search links
// every quad of the frame with every other: among the 5 px squares of a 10 px checkerboard poster
// at half size it took 164-220 ms to find a board of 28-40 px squares (one run each, OpenCV's
// Python binding, axis-aligned boards, blur 0.8 px); on the closed copy the poster's texture is
// gone (it becomes white) and the same boards are found in about 1 ms. Clutter up to 16 px is
// removed so; the board's own squares (found from 14 px at half size) keep their shape, and the
// corners are refined at full resolution. Where the closed copy shows no board, the plain copy
// is searched as before (docs/performance.md, "Busy frames").
constexpr int kClutterClosingPx = 9;

cv::Mat closed_for_search(const cv::Mat& search) {
  cv::Mat closed;
  cv::morphologyEx(
      search, closed, cv::MORPH_CLOSE,
      cv::getStructuringElement(cv::MORPH_RECT, cv::Size(kClutterClosingPx, kClutterClosingPx)));
  return closed;
}

// The refinement of a board the sector search found is kept unless it fits a plane's projection
// (a homography) worse than the sector search's own corners did: by more than twice their RMS
// residual plus kRefinedGridSlackPx. Squares of 8.5 px under blur 2 px, tilted 60 degrees: the
// refined corners (cornerSubPix's window 7x7 px) 1.1-1.4 px RMS from the true ones, residual
// 1.1-1.3 px against 0.34 px before; every board where the refinement helped kept its residual
// within 0.2 px of the sector search's (72 rendered frames, docs/performance.md, "Steep boards
// under noise"). Lens distortion adds to both residuals alike.
constexpr double kRefinedGridSlackPx = 0.2;

// The RMS distance of a chessboard's cols x rows corners from the homography fitted to them.
double grid_residual(const std::vector<cv::Point2f>& pts, int cols, int rows) {
  std::vector<cv::Point2f> grid;
  for (int r = 0; r < rows; ++r) {
    for (int c = 0; c < cols; ++c) grid.emplace_back(static_cast<float>(c), static_cast<float>(r));
  }
  const cv::Mat H = cv::findHomography(grid, pts, 0);
  if (H.empty()) return std::numeric_limits<double>::infinity();
  std::vector<cv::Point2f> fitted;
  cv::perspectiveTransform(grid, fitted, H);
  double ss = 0;
  for (size_t i = 0; i < pts.size(); ++i) ss += std::pow(cv::norm(fitted[i] - pts[i]), 2);
  return std::sqrt(ss / static_cast<double>(pts.size()));
}

// The sector search on a copy of at most DetectorOptions::kSectorSearchMaxSide px finds boards
// whose squares are this large there (in the pre-check's lattice: chessboard_lattice's spacing):
// among 288 rendered 1280x720 frames (noise 2-12 grey levels, blur 0.8-2 px, 0.4-3 m, tilt
// 0-66 degrees, half of them partly out of view), every board that only the search at full
// resolution found had squares of 6-12 px there, 3-6 px on the copy (docs/performance.md,
// "Boards partly out of view").
constexpr int kCoarseSquareMinPx = 8;

// The search image's try of the sector search, where it runs (small squares), searches a crop:
// the lattice's crossings grown by this many board lengths (each the longer square side times the
// corners along the board's longer side), unless the squares are under
// kFineSearchCropMinSquarePx px there. Boards of 6.3 px squares that the whole frame's search
// found were lost on 5 of 6 crops tried (2 of the 115 boards found among the 288 rendered frames
// above); none of 7.1 px or more, there nor among 240 other rendered frames (other seeds, poses,
// blur and noise). A C525 frame partly out of view with squares under 16 px: median 63 ms
// instead of 162 (docs/performance.md, "Boards partly out of view").
constexpr double kFineSearchBoardLengths = 1.5;
constexpr double kFineSearchCropMinSquarePx = 7;

// The part of a search image of `size` that the sector search's try at the search image's
// resolution searches for a board of cols x rows corners: the lattice's crossings grown by
// kFineSearchBoardLengths board lengths (a board lies within its own length of any of its
// interior corners), or the whole image where the squares are under kFineSearchCropMinSquarePx.
cv::Rect fine_search_area(const ChessboardLattice& lattice, int cols, int rows, cv::Size size) {
  const cv::Rect whole(cv::Point(0, 0), size);
  if (lattice.spacing_px < kFineSearchCropMinSquarePx) return whole;
  const double pad = kFineSearchBoardLengths * (std::max(cols, rows) + 1) * lattice.long_spacing_px;
  const cv::Rect2d& e = lattice.extent;
  return whole & cv::Rect(cv::Point(static_cast<int>(std::floor(e.x - pad)),
                                    static_cast<int>(std::floor(e.y - pad))),
                          cv::Point(static_cast<int>(std::ceil(e.x + e.width + pad)) + 1,
                                    static_cast<int>(std::ceil(e.y + e.height + pad)) + 1));
}

// OpenCV's sector-based chessboard search on `search` (cv::findChessboardCornersSB with `flags`):
// the corners in cv::findChessboardCorners' order, or none. The two detectors number the corners
// from opposite ends. Where the board's two orders differ in colour (inner corners odd along one
// side, even along the other), the quads' search starts at the corner whose first square (between
// corners 0, 1, cols and cols + 1) is dark, the sector search at the one whose first square is
// light: 68 rendered frames and OpenCV's photos, every one. Elsewhere (a board the same after a
// half turn) the quads' rule for an even x even board is applied: the last row below the first.
std::vector<cv::Point2f> find_by_sectors(const cv::Mat& search, cv::Size pattern, int flags) {
  std::vector<cv::Point2f> pts;
  try {
    if (!cv::findChessboardCornersSB(search, pattern, pts, flags)) return {};
  } catch (const cv::Exception&) {
    return {};  // too small an image for its pyramid: not found
  }
  const auto n = static_cast<size_t>(pattern.width) * static_cast<size_t>(pattern.height);
  if (pts.size() != n) return {};
  const auto w = static_cast<size_t>(pattern.width);
  bool reverse = false;
  if ((pattern.width + pattern.height) % 2 == 1) {
    const cv::Point2f first = 0.25f * (pts[0] + pts[1] + pts[w] + pts[w + 1]);
    const cv::Point2f next = first + (pts[1] - pts[0]);  // the square after it along the row
    // The mean of the 3x3 pixels about a square's centre (clipped to the image).
    auto at = [&](const cv::Point2f& p) {
      const int x = std::clamp(static_cast<int>(std::lround(p.x)), 0, search.cols - 1);
      const int y = std::clamp(static_cast<int>(std::lround(p.y)), 0, search.rows - 1);
      const cv::Rect patch =
          cv::Rect(x - 1, y - 1, 3, 3) & cv::Rect(0, 0, search.cols, search.rows);
      return cv::mean(search(patch))[0];
    };
    reverse = at(first) > at(next);
  } else {
    reverse = pts[n - w].y < pts[0].y;
  }
  if (reverse) std::reverse(pts.begin(), pts.end());
  return pts;
}

}  // namespace

// Chessboard: a lattice pre-check, then OpenCV's sector search (or, on busy frames, its quads'
// search) on shrunk copies; the corners are refined at full resolution with a window from the
// corner spacing (wide enough to reach the saddle from a shrunk copy's estimate, which is off by
// up to about half the factor).
std::vector<cv::Point2f> Board::detect_chessboard(const cv::Mat& gray, const Search& where,
                                                  const DetectorOptions& options) const {
  std::vector<cv::Point2f> pts;
  const cv::Size pattern(spec_.cols, spec_.rows);
  const int flags =
      cv::CALIB_CB_ADAPTIVE_THRESH | cv::CALIB_CB_NORMALIZE_IMAGE | cv::CALIB_CB_FAST_CHECK;
  const cv::Mat area = where.region.empty() ? gray : gray(where.region);
  int k = std::max(where.shrink, search_factor(area, options));
  cv::Mat search = k > 1 ? shrink_for_search(area, k) : area;
  const int cap = quad_cap(options, (spec_.cols + 1) * (spec_.rows + 1));
  // Frames with too few chessboard crossings are not searched (board/saddles.hpp). A frame that
  // is not busy is searched by OpenCV's sector search alone (find_by_sectors), which is bounded
  // where the quads' search is not (a steeply tilted board, or one partly out of view, under
  // sensor noise). A busy frame keeps the quads' search: first on a copy shrunk four times as
  // much as the search image, where the texture of clutter is averaged away and a board of large
  // squares in front of it is found in a few milliseconds (OpenCV's search among the clutter's
  // quads at half size took 110-180 ms; docs/performance.md, "Busy frames"); only if no board is
  // found there (a board of small squares) on one shrunk twice as much, with the clutter's fine
  // dark detail closed (closed_for_search), then on the plain copy. (A search image under 32 px
  // a side has no room for a board at half size; it is cheap as it is, and never busy.)
  ChessboardLattice lattice;  // not examined without the pre-check: spacing 0, every try runs
  if (options.chessboard_precheck) {
    lattice = chessboard_lattice(search, k > 1);
    if (lattice.crossings < chessboard_crossings_needed(spec_.cols, spec_.rows)) return {};
  }
  // The corners found on a copy shrunk by `f`, in the frame's pixels and refined there.
  auto to_frame = [&](std::vector<cv::Point2f> found, int f) {
    const cv::Point2f origin(static_cast<float>(where.region.x),
                             static_cast<float>(where.region.y));
    for (auto& p : found) p = (f > 1 ? to_full_resolution(p, f) : p) + origin;
    return found;
  };
  auto refine = [&](std::vector<cv::Point2f>& corners, int f) {
    int hw = options.subpix_half_window;
    if (hw <= 0 && f == 1) hw = subpix_half_window(corners, spec_.cols, spec_.rows);
    if (hw <= 0) hw = subpix_half_window(corners, spec_.cols, spec_.rows, std::max(11, 3 * f));
    cv::cornerSubPix(gray, corners, cv::Size(hw, hw), cv::Size(-1, -1),
                     cv::TermCriteria(cv::TermCriteria::EPS + cv::TermCriteria::COUNT, 50, 1e-3));
    smooth_refine_chessboard_corners(gray, spec_.cols, spec_.rows, hw, &corners);
  };
  // Busy frames (clutter's quads; see busy()) keep the quads' search on shrunk copies below,
  // which is bounded there; the sector search took 134-328 ms on textures and dot grids that
  // cost it 34-69 ms.
  const bool is_busy =
      cap > 0 && std::min(search.cols, search.rows) >= 32 && busy(half_size_contours(search), cap);
  if (options.chessboard_sector_search && !is_busy) {
    // Up to three tries, each bounded: a copy of at most kSectorSearchMaxSide px a side (21-84
    // ms at 640x360), the search image itself if it is larger (100-190 ms at 1280x720; boards
    // of small squares), and the copy again with its histogram equalised (OpenCV's
    // CALIB_CB_NORMALIZE_IMAGE; four of OpenCV's photos are found only so, five of 72 steep
    // rendered boards only without). The search image is skipped where the pre-check's lattice
    // shows squares of kCoarseSquareMinPx or more on the copy. The quads' search does not
    // follow: on a board partly out of view under sensor noise it took 1-8 s a frame at 1280x720
    // and found nothing (docs/performance.md, "Boards partly out of view").
    const int max_side = std::max(area.cols, area.rows);
    const int coarse = std::max(k, (max_side + DetectorOptions::kSectorSearchMaxSide - 1) /
                                       DetectorOptions::kSectorSearchMaxSide);
    const cv::Mat coarse_copy = coarse == k ? search : shrink_for_search(area, coarse);
    const bool fine_needed =
        coarse != k && lattice.spacing_px * k / coarse < static_cast<double>(kCoarseSquareMinPx);
    // That try searches only about the lattice's crossings (fine_search_area).
    const cv::Rect fine =
        fine_needed ? fine_search_area(lattice, spec_.cols, spec_.rows, search.size()) : cv::Rect();
    struct Try {
      bool fine;  // the search image's try (else the copy of at most kSectorSearchMaxSide px)
      int flags;
      bool run;
    };
    const std::array<Try, 3> tries = {Try{false, 0, true}, Try{true, 0, fine_needed},
                                      Try{false, cv::CALIB_CB_NORMALIZE_IMAGE, true}};
    for (const Try& t : tries) {
      if (!t.run) continue;
      // (A crop is copied: OpenCV's sector search is given continuous pixels.)
      const cv::Mat image = !t.fine                        ? coarse_copy
                            : fine.size() == search.size() ? search
                                                           : search(fine).clone();
      std::vector<cv::Point2f> found = find_by_sectors(image, pattern, t.flags);
      if (found.empty()) continue;
      if (t.fine) {
        for (auto& p : found)
          p += cv::Point2f(static_cast<float>(fine.x), static_cast<float>(fine.y));
      }
      const int shrink = t.fine ? k : coarse;
      const std::vector<cv::Point2f> start = to_frame(found, shrink);
      std::vector<cv::Point2f> corners = start;
      refine(corners, shrink);
      // A refinement that lost the grid (kRefinedGridSlackPx) is dropped; the next try decides.
      if (grid_residual(corners, spec_.cols, spec_.rows) <=
          2 * grid_residual(start, spec_.cols, spec_.rows) + kRefinedGridSlackPx) {
        return corners;
      }
    }
    return {};
  }
  bool found = false;
  if (is_busy) {
    const int quarter = 4 * k;
    if (std::min(area.cols / quarter, area.rows / quarter) >= kQuarterSearchMinSide &&
        cv::findChessboardCorners(shrink_for_search(area, quarter), pattern, pts, flags)) {
      k = quarter;
      found = true;
    } else {
      k *= 2;
      search = shrink_for_search(area, k);
      found = cv::findChessboardCorners(closed_for_search(search), pattern, pts, flags);
    }
  }
  if (!found && !cv::findChessboardCorners(search, pattern, pts, flags)) return {};
  pts = to_frame(pts, k);
  refine(pts, k);
  return pts;
}

// ChArUco: markers (on a shrunk copy for large frames), OpenCV's corner interpolation and
// refinement at full resolution, then ours (refine_charuco_corners).
void Board::detect_charuco(const cv::Mat& gray, const Search& where, const DetectorOptions& options,
                           Detection* det) const {
  std::vector<std::vector<cv::Point2f>> marker_corners;
  std::vector<int> marker_ids;
  const cv::Mat area = where.region.empty() ? gray : gray(where.region);
  int k = std::max(where.shrink, search_factor(area, options));
  cv::Mat search = k > 1 ? shrink_for_search(area, k) : area;
  const int cap = quad_cap(options, spec_.cols * spec_.rows);
  // A busy search image (uniform noise, dense clutter; see busy()) is searched on a copy shrunk
  // twice as much. Search images of kPrecountFullResolutionMaxSide or less are not tested: the
  // test runs at half size, where the fine textures that slow small frames down are averaged
  // away; they are cheap enough as they are (640x480 noise: about 50 ms). The limit is twice the
  // chessboard's: the markers' bits add blobs, and sensor noise of sigma 15 on a board frame gives
  // 276-453 (9x6 and 12x9 boards), frames that keep the full-resolution search (70-95 ms) and all
  // their corners; from sigma 20 (831 and more) the half-size search finds 10-37% fewer corners
  // than the full-resolution one, in bounded time (docs/performance.md, "Cluttered frames").
  Contours half_size;
  if (cap > 0 && std::max(search.cols, search.rows) > kPrecountFullResolutionMaxSide) {
    half_size = half_size_contours(search);
    if (busy(half_size, kCharucoBusyFactor * cap) ||
        (k > 1 && where.max_perimeter_px <= 0 &&
         median_neighbour_difference(search) >= kNoisyCopyDifference)) {
      k *= 2;
      search = shrink_for_search(area, k);
      half_size.clear();
    }
  }
  det->search_shrink = k;
  // Quads too small to be decoded are not searched (DetectorOptions::min_marker_pixels_per_cell).
  const int cells = impl_->dictionary->markerSize + 2 * impl_->params->markerBorderBits;
  const double min_perimeter_px = 4.0 * options.min_marker_pixels_per_cell * cells;
  const cv::Ptr<cv::aruco::DetectorParameters> params =
      cv::makePtr<cv::aruco::DetectorParameters>(*impl_->params);
  const double search_side = std::max(search.cols, search.rows);
  params->minMarkerPerimeterRate =
      std::max(params->minMarkerPerimeterRate, min_perimeter_px / search_side);
  const bool sized = where.max_perimeter_px > 0;
  if (sized) {
    // Markers of a known size (tracking): only quads of that size, thresholded at one window of
    // about half the smallest marker's side (odd, 5 to 15 px of the search image; the lower
    // perimeter bound is half the smallest marker's). Wider windows lost markers at a shrink of
    // 3 (17 px and more on a 1189x720 region: 32 of 40 corners), narrower ones found them all.
    params->minMarkerPerimeterRate =
        std::max(params->minMarkerPerimeterRate, where.min_perimeter_px / k / search_side);
    params->maxMarkerPerimeterRate =
        std::max(params->minMarkerPerimeterRate * 1.01, where.max_perimeter_px / k / search_side);
    const int half_side = static_cast<int>(where.min_perimeter_px / k / 4);
    const int window = std::clamp(half_side / 2, 2, 7) * 2 + 1;
    params->adaptiveThreshWinSizeMin = window;
    params->adaptiveThreshWinSizeMax = window;
    params->adaptiveThreshWinSizeStep = 1;
    // OpenCV's distance to the image's border in full-resolution pixels, not the copy's.
    params->minDistanceToBorder = (params->minDistanceToBorder + k - 1) / k;
  }
  if (cap > 0 && !sized) {
    cap_candidate_quads(search, cap, half_size.empty() ? nullptr : &half_size, params.get());
  }
  cv::aruco::detectMarkers(search, impl_->dictionary, marker_corners, marker_ids, params);
  const cv::Point2f origin(static_cast<float>(where.region.x), static_cast<float>(where.region.y));
  for (auto& quad : marker_corners)
    for (auto& p : quad) p = (k > 1 ? to_full_resolution(p, k) : p) + origin;
  det->markers = static_cast<int>(marker_ids.size());
  if (marker_ids.empty()) return;
  std::vector<cv::Point2f> ch_corners;
  std::vector<int> ch_ids;
  cv::aruco::interpolateCornersCharuco(marker_corners, marker_ids, gray, impl_->board, ch_corners,
                                       ch_ids, cv::noArray(), cv::noArray(), options.min_markers);
  // OpenCV 4.6's interpolateCornersCharuco adds (0.5, 0.5) to every refined corner, off the
  // pixel-centre convention (measured: tests/unit/test_target.cpp renders one scene and
  // compares both detectors with the true projections). Remove it before refining again.
  for (auto& c : ch_corners) c -= cv::Point2f(0.5f, 0.5f);
  const double inset = 0.5 * (1.0 - spec_.marker_length_m / spec_.square_length_m);
  refine_charuco_corners(gray, spec_.cols - 1, inset, &ch_ids, &ch_corners);
  std::vector<size_t> order(ch_ids.size());
  for (size_t i = 0; i < order.size(); ++i) order[i] = i;
  std::sort(order.begin(), order.end(), [&](size_t a, size_t b) { return ch_ids[a] < ch_ids[b]; });
  for (size_t i : order) {
    const int id = ch_ids[i];
    if (id < 0 || id >= num_corners()) continue;
    det->ids.push_back(id);
    det->image_points.emplace_back(ch_corners[i].x, ch_corners[i].y);
    det->board_points.push_back(corners_[id]);
  }
}

Detection Board::detect(const cv::Mat& image, const DetectorOptions& options) const {
  check_detect_size(image);  // before any work on the pixels
  return detect_gray(to_gray(image), Search{}, options);
}

Detection Board::detect_in(const cv::Mat& image, const cv::Rect& region, int shrink,
                           const DetectorOptions& options) const {
  return detect_in(image, region, shrink, 0, 0, options);
}

Detection Board::detect_in(const cv::Mat& image, const cv::Rect& region, int shrink,
                           double min_perimeter_px, double max_perimeter_px,
                           const DetectorOptions& options) const {
  check_detect_size(image);
  const cv::Mat gray = to_gray(image);
  const cv::Rect clipped = region & cv::Rect(0, 0, gray.cols, gray.rows);
  if (clipped.empty()) return Detection{};
  const bool bounded = std::isfinite(min_perimeter_px) && std::isfinite(max_perimeter_px) &&
                       min_perimeter_px > 0 && max_perimeter_px > min_perimeter_px;
  return detect_gray(gray,
                     Search{clipped, std::max(1, shrink), bounded ? min_perimeter_px : 0,
                            bounded ? max_perimeter_px : 0},
                     options);
}

Detection Board::detect_gray(const cv::Mat& gray, const Search& where,
                             const DetectorOptions& options) const {
  Detection det;
  try {
    if (spec_.type == BoardType::kCharuco) {
      detect_charuco(gray, where, options, &det);
      return det;
    }
    const std::vector<cv::Point2f> pts = detect_chessboard(gray, where, options);
    for (size_t i = 0; i < pts.size(); ++i) {
      det.ids.push_back(static_cast<int>(i));
      det.image_points.emplace_back(pts[i].x, pts[i].y);
      det.board_points.push_back(corners_[i]);
    }
  } catch (const cv::Exception&) {
    // OpenCV rejects some degenerate inputs by exception; for detection that means "not found".
    return Detection{};
  }
  return det;
}

BoardTexture Board::render(int texels_per_square, double margin_squares) const {
  if (texels_per_square < 4) {
    throw Error(ErrorCode::kInvalidArgument, "render: need at least 4 texels per square");
  }
  const int P = texels_per_square;
  const int margin = static_cast<int>(std::lround(margin_squares * P));
  const int sq_x = spec_.type == BoardType::kCharuco ? spec_.cols : spec_.cols + 1;
  const int sq_y = spec_.type == BoardType::kCharuco ? spec_.rows : spec_.rows + 1;
  BoardTexture tex;
  tex.image = cv::Mat(sq_y * P + 2 * margin, sq_x * P + 2 * margin, CV_8U, cv::Scalar(255));
  tex.metres_per_texel = spec_.square_length_m / P;
  tex.margin_m = margin * tex.metres_per_texel;
  cv::Mat inner = tex.image(cv::Rect(margin, margin, sq_x * P, sq_y * P));
  if (spec_.type == BoardType::kCharuco) {
    cv::Mat board;
    impl_->board->draw(cv::Size(sq_x * P, sq_y * P), board, 0, 1);
    board.copyTo(inner);
  } else {
    for (int i = 0; i < sq_y; ++i)
      for (int j = 0; j < sq_x; ++j)
        if ((i + j) % 2 == 0) inner(cv::Rect(j * P, i * P, P, P)).setTo(0);
  }
  return tex;
}

}  // namespace posecal
