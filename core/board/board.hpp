// Calibration targets: ChArUco (default) and the classic chessboard.
//
// Board frame (same as OpenCV 4.6's CharucoBoard object points): origin at the top-left outer
// corner of the square pattern, x along the columns, y down the rows, z into the board; metres.
// For the chessboard the inner corner (row i, column j) is at ((j + 1) s, (i + 1) s, 0), so both
// targets share one convention.
//
// Detections use OpenCV's pixel convention (pixel centres at integer coordinates).
#pragma once

#include <memory>
#include <opencv2/core.hpp>
#include <string>
#include <vector>

namespace posecal {

enum class BoardType { kCharuco, kChessboard };

// Paper for the printable PDF: the board's own size, or sheets of a standard size.
enum class Paper { kBoard, kA4, kA3, kLetter };
// "board", "a4", "a3", "letter" (any case); Error(kInvalidArgument) naming anything else.
Paper paper_from_name(const std::string& name);

struct PrintOptions {
  double dpi = 300;        // PNG resolution, [50, 2400]
  double margin_m = 0.01;  // white border around the board; on paper, the sheet's unprinted
                           // edge (at least 5 mm)
  Paper paper = Paper::kBoard;
};

// One black cell of a marker on the board, board frame (metres): top-left corner and side.
struct BoardMarkerCell {
  double x_m, y_m, size_m;
};

struct BoardSpec {
  BoardType type = BoardType::kCharuco;
  // ChArUco: number of squares. Chessboard: number of inner corners.
  int cols = 9;
  int rows = 6;
  double square_length_m = 0.028;
  double marker_length_m = 0.0182;  // ChArUco only; paper setup: 0.65 of the square
  std::string dictionary = "DICT_4X4_50";

  // Limits of a spec: 3 to kMaxSide squares (ChArUco) or inner corners (chessboard) per side;
  // square length in [kMinSquareM, kMaxLengthM] metres; ChArUco marker length between
  // kMinMarkerRatio and kMaxMarkerRatio of the square (the renderer's 128 texels per square then
  // give every dictionary's marker enough texels, and the marker keeps a white margin of at
  // least 2.5% of the square on each side; OpenCV's board, which holds the lengths as float,
  // rejects a marker that rounds to the square's length).
  static constexpr int kMaxSide = 100;
  static constexpr double kMinSquareM = 1e-4;
  static constexpr double kMaxLengthM = 10.0;
  static constexpr double kMinMarkerRatio = 0.1;
  static constexpr double kMaxMarkerRatio = 0.95;

  // "charuco:9x6:0.028:0.0182:DICT_4X4_50" or "chessboard:9x6:0.025" (inner corners), lengths
  // in metres as plain decimal numbers. Throws Error(kInvalidArgument) naming the spec and the
  // offending field.
  static BoardSpec parse(const std::string& spec);
  std::string to_string() const;
  // Throws Error(kInvalidArgument) if inconsistent (marker too large, too few corners...).
  void validate() const;
};

struct Detection {
  std::vector<int> ids;                   // corner ids, ascending
  std::vector<cv::Point2d> image_points;  // subpixel, OpenCV pixel convention
  std::vector<cv::Point3d> board_points;  // matching board coordinates (z = 0)
  int markers = 0;                        // ArUco markers seen (ChArUco only)
  // ChArUco: the factor of the copy the markers were searched in (1: full resolution; see
  // DetectorOptions::search_max_side and docs/performance.md, "Busy frames"). 0 for a chessboard.
  int search_shrink = 0;
  size_t size() const { return ids.size(); }
  bool empty() const { return ids.empty(); }
};

struct DetectorOptions {
  // ChArUco: minimum number of adjacent markers for a corner to be interpolated (OpenCV's
  // minMarkers). Chessboard: ignored.
  int min_markers = 2;
  // Half-size of cornerSubPix's window for the chessboard; 0 picks it from the corner spacing.
  int subpix_half_window = 0;
  // Frames whose longer side exceeds this many pixels are searched (chessboard corners, ArUco
  // markers) in a copy shrunk by the smallest integer factor that brings the longer side within
  // it (pixel averaging, INTER_AREA); the corners are then refined at full resolution. Bounds the
  // cost of a frame (docs/performance.md, "Detection against the frame size": a chessboard search
  // in 12 MP of noise took > 150 s); frames up to this size take the full-resolution path
  // unchanged. 0: always search at full resolution.
  int search_max_side = kSearchMaxSide;
  static constexpr int kSearchMaxSide = 1280;
  // ChArUco: candidate marker quads under this many pixels per marker cell (border included) are
  // not searched. OpenCV's own minimum is 3% of the frame's longer side, 4 px of perimeter in a
  // 136-px frame, where a striped pattern gave thousands of candidates and its pairwise filter
  // (quadratic in their number) took up to 1.6 s per frame. No DICT_4X4 marker was decoded at
  // 1.33 px per cell or less (blur 0.8 px); 0 keeps OpenCV's rule alone.
  double min_marker_pixels_per_cell = 1.25;
  // ChArUco: at most this many candidate marker quads per frame (one threshold scale), or twice
  // the board's squares (cols x rows: each holds a marker or is black) if that is more. A frame
  // of clutter (a chessboard poster, a dot grid, a perforated sheet) gave OpenCV 4.6 thousands of
  // candidates, filtered pairwise (quadratic in their number): 2.4 s for a 1280x720 checkerboard
  // of 10 px squares. Above the cap the frame is searched for the largest quads only: the
  // smallest minimum perimeter that leaves at most the cap. 300 quads of clutter cost OpenCV
  // about 40 ms; the 9x6 board gives 63. Busy frames: a search image of more than this many
  // blobs of a chessboard square's size (or twice the board's squares; twice that for ChArUco,
  // whose markers' bits are blobs too) is searched on a copy shrunk twice as much (OpenCV's
  // chessboard search took 1.4 s on 1280x720 noise, 5.3 s on a checkerboard texture of 14 px
  // squares; its marker search 135-180 ms on noise). 0: neither (docs/performance.md,
  // "Cluttered frames" and "Busy frames").
  int max_candidate_quads = kMaxCandidateQuads;
  static constexpr int kMaxCandidateQuads = 300;
  // Chessboard: OpenCV's search runs only on frames with enough chessboard-like lattice
  // crossings (board/saddles.hpp: a quarter of the board's interior corners). OpenCV's search
  // took 0.4-1.9 s on a circuit board or a photo at 1280 px and found nothing; the test costs a
  // few milliseconds (docs/performance.md, "Scenes without a board"). false: always search.
  bool chessboard_precheck = true;
  // Chessboard: frames that are not busy are searched by OpenCV's sector-based search
  // (cv::findChessboardCornersSB) alone: on a copy of at most kSectorSearchMaxSide px a side,
  // then on the search image, then on the copy with its histogram equalised. OpenCV's search of
  // quads runs only on busy frames, where it is bounded. The quads' search is unbounded on a
  // steeply tilted board under sensor noise (0.5-20 s a frame at 1280x720) and on a board partly
  // out of view (1-8 s); the sector search took 134-176 ms at 1280x720 and found every board the
  // quads' search found there (docs/performance.md, "Steep boards under noise" and "Boards partly
  // out of view"). false: the quads' search alone, on every frame.
  bool chessboard_sector_search = true;
  static constexpr int kSectorSearchMaxSide = 640;
};

// A rendered board: texel (u, v) (OpenCV pixel convention) shows board point
// X = (u + 0.5) * metres_per_texel - margin_m, likewise Y.
struct BoardTexture {
  cv::Mat image;  // CV_8UC1
  double metres_per_texel = 0;
  double margin_m = 0;
};

// The largest frame Board::detect accepts: 100 megapixels (2x a 48 MP sensor). Shrinking a
// frame for the search costs time in proportion to its pixels (docs/performance.md).
inline constexpr long long kMaxDetectPixels = 100'000'000;

class Board {
 public:
  explicit Board(const BoardSpec& spec = BoardSpec{});
  ~Board();
  Board(const Board&);
  Board& operator=(const Board&);

  const BoardSpec& spec() const { return spec_; }
  // ChArUco: cells across a marker, its black border included (DICT_4X4: 6); 0 for a chessboard.
  int marker_grid_cells() const;
  // Total number of corners a full detection yields.
  int num_corners() const { return static_cast<int>(corners_.size()); }
  // Board coordinates of every corner, indexed by id.
  const std::vector<cv::Point3d>& corners() const { return corners_; }
  // Outer extent of the square pattern in metres (width along x, height along y).
  cv::Size2d board_size_m() const;
  // The four outer corners of the square pattern (TL, TR, BR, BL), board frame.
  std::vector<cv::Point3d> outline() const;

  // Detects the target in an 8-bit grey (or BGR) image. Never throws for image content;
  // throws Error(kInvalidArgument) for an empty or non-8-bit image, or one of more than
  // kMaxDetectPixels pixels (naming the limit).
  Detection detect(const cv::Mat& image, const DetectorOptions& options = {}) const;
  // detect() limited to `region` of the image (full-frame pixels, clipped to the image), searched
  // on a copy of it shrunk by `shrink` (at least 1; raised where the region's longer side needs
  // it, as detect() does for a whole frame). The corners are refined at full resolution in the
  // whole frame, so a board well inside the region gives detect()'s corners up to the
  // refinement's tolerance. For tracking (core/board/tracking.hpp). Errors as detect(); an
  // empty region (after clipping) finds nothing.
  Detection detect_in(const cv::Mat& image, const cv::Rect& region, int shrink,
                      const DetectorOptions& options = {}) const;
  // ... and, for a ChArUco board whose markers' perimeters are known to lie in
  // [min_perimeter_px, max_perimeter_px] (full-resolution pixels; from the last frame), only
  // candidate quads of that size are decoded, at one threshold scale fitted to them, instead of
  // OpenCV's three (chessboard: the bounds are ignored).
  Detection detect_in(const cv::Mat& image, const cv::Rect& region, int shrink,
                      double min_perimeter_px, double max_perimeter_px,
                      const DetectorOptions& options = {}) const;

  // Renders the board pattern (no margin) at an integer number of texels per square, plus
  // `margin_squares` of white border. Texel edges coincide with square edges exactly.
  BoardTexture render(int texels_per_square, double margin_squares = 0.0) const;

  // Printable target at exact physical scale (core/board/printable.cpp): vector PDF on the
  // board's own page or on sheets of a paper size (tiled when the board is larger), each page
  // with the specification, a 100 mm ruler and "print at 100 %"; or PNG of the board alone at
  // `dpi` with the resolution in its pHYs chunk. Chosen by the extension of `path`; written
  // atomically. Throws Error(kInvalidArgument) for a bad option, an unknown extension, a paper
  // size with a PNG or more than 200 sheets; Error(kIo) when the file cannot be written.
  void write_printable(const std::string& path, const PrintOptions& options) const;
  void write_printable(const std::string& path, double dpi = 300.0, double margin_m = 0.01) const {
    PrintOptions o;
    o.dpi = dpi;
    o.margin_m = margin_m;
    write_printable(path, o);
  }
  // The black cells of every ChArUco marker, board frame (empty for a chessboard): what the
  // vector PDF fills, read from OpenCV's own marker drawing.
  std::vector<BoardMarkerCell> marker_cells() const;

 private:
  struct Impl;
  // Where a search looks: a region of the frame (empty: all of it) and the least shrink factor.
  struct Search {
    cv::Rect region;
    int shrink = 1;
    double min_perimeter_px = 0, max_perimeter_px = 0;  // markers' (0: unknown)
  };
  Detection detect_gray(const cv::Mat& gray, const Search& where,
                        const DetectorOptions& options) const;
  // detect() for each kind of board (grey image, cv::Exception for "not found").
  std::vector<cv::Point2f> detect_chessboard(const cv::Mat& gray, const Search& where,
                                             const DetectorOptions& options) const;
  void detect_charuco(const cv::Mat& gray, const Search& where, const DetectorOptions& options,
                      Detection* det) const;
  BoardSpec spec_;
  std::vector<cv::Point3d> corners_;
  std::shared_ptr<const Impl> impl_;
};

}  // namespace posecal
