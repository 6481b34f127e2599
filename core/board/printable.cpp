// The printable board at exact physical scale (docs/board.md, "Printing the board").
//
// PDF: vector, drawn with cairo, in points (1/72 inch). Either one page of the board's own size,
// or sheets of a paper size (A4, A3, Letter) in the orientation that needs the fewest sheets;
// a board larger than one sheet is tiled, neighbouring sheets sharing an overlap strip with cut
// marks in the margins. Every page carries the board's specification, a 100 mm ruler and the
// instruction to print at 100 %, and the document its title, subject and creator.
// PNG: the board alone at `dpi`, written with libpng, the resolution in its pHYs chunk.
#include <cairo-pdf.h>
#include <cairo.h>
#include <png.h>

#include <algorithm>
#include <cctype>
#include <cmath>
#include <cstdio>
#include <opencv2/aruco/charuco.hpp>
#include <opencv2/imgproc.hpp>
#include <string_view>

#include "board/board_internal.hpp"
#include "common/atomic_file.hpp"
#include "common/error.hpp"

namespace posecal {

namespace {

constexpr double kPointsPerM = 72.0 / 0.0254;
constexpr double kMm = 0.001;
// Below the board on every page: two lines of text and the ruler (metres). 18 mm, so that the
// default board (252 x 168 mm) fits one landscape A4 sheet with 10 mm margins.
constexpr double kFooterM = 18 * kMm;
constexpr double kRulerM = 100 * kMm;
// Neighbouring sheets of a tiled board both print this strip of it; the cut runs in its middle.
constexpr double kOverlapM = 10 * kMm;
constexpr int kMaxSheets = 200;

struct PaperGeometry {
  double w_m = 0, h_m = 0;  // portrait
};

PaperGeometry paper_geometry(Paper paper) {
  switch (paper) {
    case Paper::kA4: return {0.210, 0.297};
    case Paper::kA3: return {0.297, 0.420};
    case Paper::kLetter: return {8.5 * 0.0254, 11 * 0.0254};
    case Paper::kBoard: break;
  }
  return {};
}

std::string mm_text(double m) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "%.3f mm", m / kMm);
  return buf;
}

// How a board of w x h metres is cut into sheets whose board area is avail_w x avail_h.
struct Tiling {
  int nx = 1, ny = 1;
  double step_x = 0, step_y = 0;  // board-frame offset between neighbouring sheets
};

int sheets_along(double board, double avail, double* step) {
  *step = avail - kOverlapM;
  if (board <= avail) return 1;
  if (*step <= 0) return kMaxSheets + 1;
  const double n = std::ceil((board - avail) / *step) + 1;
  return n > kMaxSheets ? kMaxSheets + 1 : static_cast<int>(n);
}

// The page: size, where the board's area starts, and what the sheet shows of the board.
struct Page {
  double w_m = 0, h_m = 0;          // page size
  double area_x = 0, area_y = 0;    // top-left of the board area on the page
  double area_w = 0, area_h = 0;    // board area (the footer is below it)
  double board_x0 = 0, board_y0 = 0;  // the board point shown at the area's top-left
  double edge = 0;                  // the unprinted edge of the page
  double shown_w = 0, shown_h = 0;  // how much of the board this sheet shows
  int col = 0, row = 0;             // sheet index
};

class PdfWriter {
 public:
  PdfWriter(const Board& board, const PrintOptions& o) : board_(board), o_(o) {}

  std::string write() {
    const cv::Size2d size = board_.board_size_m();
    board_w_ = size.width;
    board_h_ = size.height;
    std::vector<Page> pages = layout();
    cairo_surface_t* surface =
        cairo_pdf_surface_create_for_stream(&PdfWriter::append, &bytes_, pages[0].w_m * kPointsPerM,
                                            pages[0].h_m * kPointsPerM);
    cairo_pdf_surface_restrict_to_version(surface, CAIRO_PDF_VERSION_1_5);
    const std::string title = "posecal calibration board " + board_.spec().to_string();
    cairo_pdf_surface_set_metadata(surface, CAIRO_PDF_METADATA_TITLE, title.c_str());
    cairo_pdf_surface_set_metadata(surface, CAIRO_PDF_METADATA_SUBJECT,
                                   "Print at 100 % (no fit to page); the ruler measures 100 mm");
    cairo_pdf_surface_set_metadata(surface, CAIRO_PDF_METADATA_CREATOR, "posecal");
    cairo_t* cr = cairo_create(surface);
    for (const Page& p : pages) {
      cairo_pdf_surface_set_size(surface, p.w_m * kPointsPerM, p.h_m * kPointsPerM);
      draw_page(cr, p, static_cast<int>(pages.size()));
      cairo_show_page(cr);
    }
    cairo_destroy(cr);
    cairo_surface_finish(surface);
    const cairo_status_t status = cairo_surface_status(surface);
    cairo_surface_destroy(surface);
    if (status != CAIRO_STATUS_SUCCESS) {
      throw Error(ErrorCode::kInternal,
                  std::string("printable target: cairo failed: ") + cairo_status_to_string(status));
    }
    return bytes_;
  }

 private:
  static cairo_status_t append(void* closure, const unsigned char* data, unsigned int length) {
    static_cast<std::string*>(closure)->append(reinterpret_cast<const char*>(data), length);
    return CAIRO_STATUS_SUCCESS;
  }

  std::vector<Page> layout() {
    const double m = o_.margin_m;
    std::vector<Page> pages;
    if (o_.paper == Paper::kBoard) {
      // The board's own page: the board with its margin, the footer below, wide enough for the
      // ruler.
      Page p;
      p.edge = m;
      p.w_m = std::max(board_w_, kRulerM + 20 * kMm) + 2 * m;
      p.h_m = board_h_ + 2 * m + kFooterM;
      p.area_x = m + (p.w_m - 2 * m - board_w_) / 2;
      p.area_y = m;
      p.area_w = p.shown_w = board_w_;
      p.area_h = p.shown_h = board_h_;
      pages.push_back(p);
      return pages;
    }
    const PaperGeometry paper = paper_geometry(o_.paper);
    // A sheet's unprinted edge is the margin, but at least 5 mm (most printers' limit).
    const double edge = std::max(m, 5 * kMm);
    Tiling best;
    double best_w = 0, best_h = 0;
    int best_count = kMaxSheets + 1;
    for (const bool landscape : {false, true}) {
      const double w = landscape ? paper.h_m : paper.w_m;
      const double h = landscape ? paper.w_m : paper.h_m;
      Tiling t;
      t.nx = sheets_along(board_w_, w - 2 * edge, &t.step_x);
      t.ny = sheets_along(board_h_, h - 2 * edge - kFooterM, &t.step_y);
      const int count = t.nx > kMaxSheets || t.ny > kMaxSheets ? kMaxSheets + 1 : t.nx * t.ny;
      // Equal counts: the orientation of the board (landscape for a wide one).
      if (count < best_count || (count == best_count && landscape == (board_w_ > board_h_))) {
        best_count = count;
        best = t;
        best_w = w;
        best_h = h;
      }
    }
    if (best_count > kMaxSheets) {
      throw Error(ErrorCode::kInvalidArgument,
                  "printable target: the board (" + mm_text(board_w_) + " x " +
                      mm_text(board_h_) + ") needs more than " + std::to_string(kMaxSheets) +
                      " sheets of this paper, or the margin leaves no room; use a larger paper "
                      "or a smaller margin");
    }
    const double avail_w = best_w - 2 * edge;
    const double avail_h = best_h - 2 * edge - kFooterM;
    for (int r = 0; r < best.ny; ++r) {
      for (int c = 0; c < best.nx; ++c) {
        Page p;
        p.edge = edge;
        p.w_m = best_w;
        p.h_m = best_h;
        p.col = c;
        p.row = r;
        p.board_x0 = c * best.step_x;
        p.board_y0 = r * best.step_y;
        p.shown_w = std::min(avail_w, board_w_ - p.board_x0);
        p.shown_h = std::min(avail_h, board_h_ - p.board_y0);
        p.area_w = avail_w;
        p.area_h = avail_h;
        // One sheet: the board centred in the area; tiles start at the area's corner so that
        // the overlap strips are where the cut marks say.
        p.area_x = edge + (best.nx == 1 ? (avail_w - p.shown_w) / 2 : 0);
        p.area_y = edge + (best.ny == 1 ? (avail_h - p.shown_h) / 2 : 0);
        pages.push_back(p);
      }
    }
    tiling_ = best;
    return pages;
  }

  // Board-frame rectangle to page points, filled black.
  void board_rect(cairo_t* cr, const Page& p, double x, double y, double w, double h) const {
    cairo_rectangle(cr, (p.area_x + x - p.board_x0) * kPointsPerM,
                    (p.area_y + y - p.board_y0) * kPointsPerM, w * kPointsPerM, h * kPointsPerM);
  }

  void draw_board(cairo_t* cr, const Page& p) const {
    cairo_save(cr);
    // Only this sheet's part of the board.
    cairo_rectangle(cr, p.area_x * kPointsPerM, p.area_y * kPointsPerM, p.shown_w * kPointsPerM,
                    p.shown_h * kPointsPerM);
    cairo_clip(cr);
    cairo_set_source_rgb(cr, 0, 0, 0);
    const BoardSpec& spec = board_.spec();
    const double s = spec.square_length_m;
    const int square_rows = spec.type == BoardType::kChessboard ? spec.rows + 1 : spec.rows;
    const int square_cols = spec.type == BoardType::kChessboard ? spec.cols + 1 : spec.cols;
    for (int i = 0; i < square_rows; ++i) {
      for (int j = 0; j < square_cols; ++j) {
        if ((i + j) % 2 == 0) board_rect(cr, p, j * s, i * s, s, s);
      }
    }
    cairo_fill(cr);
    if (spec.type == BoardType::kCharuco) {
      // Marker cells from OpenCV's own drawing, so the PDF is the board the detector expects.
      for (const BoardMarkerCell& cell : board_.marker_cells()) {
        board_rect(cr, p, cell.x_m, cell.y_m, cell.size_m, cell.size_m);
      }
      cairo_fill(cr);
    }
    cairo_restore(cr);
  }

  // Cut marks for a tiled board: short lines in the margins at the middle of each overlap
  // strip, the same board coordinate on both sheets that share it.
  void draw_cut_marks(cairo_t* cr, const Page& p) const {
    if (tiling_.nx == 1 && tiling_.ny == 1) return;
    cairo_save(cr);
    cairo_set_source_rgb(cr, 0.85, 0, 0);
    cairo_set_line_width(cr, 0.2 * kMm * kPointsPerM);
    const double len = 4 * kMm;
    auto line = [&](double x0, double y0, double x1, double y1) {
      cairo_move_to(cr, x0 * kPointsPerM, y0 * kPointsPerM);
      cairo_line_to(cr, x1 * kPointsPerM, y1 * kPointsPerM);
    };
    for (int k = 1; k < tiling_.nx; ++k) {
      const double bx = k * tiling_.step_x + kOverlapM / 2;  // board x of the cut
      const double x = p.area_x + bx - p.board_x0;
      if (x < p.area_x || x > p.area_x + p.shown_w) continue;
      line(x, p.area_y - len - 0.5 * kMm, x, p.area_y - 0.5 * kMm);
      line(x, p.area_y + p.shown_h + 0.5 * kMm, x, p.area_y + p.shown_h + 0.5 * kMm + len);
    }
    for (int k = 1; k < tiling_.ny; ++k) {
      const double by = k * tiling_.step_y + kOverlapM / 2;
      const double y = p.area_y + by - p.board_y0;
      if (y < p.area_y || y > p.area_y + p.shown_h) continue;
      line(p.area_x - len - 0.5 * kMm, y, p.area_x - 0.5 * kMm, y);
      line(p.area_x + p.shown_w + 0.5 * kMm, y, p.area_x + p.shown_w + 0.5 * kMm + len, y);
    }
    cairo_stroke(cr);
    cairo_restore(cr);
  }

  // Text at (x, y) (baseline), shrunk if needed to end within max_w.
  void text(cairo_t* cr, double x_m, double y_m, double size_m, const std::string& s,
            double max_w_m = 1e9) const {
    cairo_set_font_size(cr, size_m * kPointsPerM);
    cairo_text_extents_t e;
    cairo_text_extents(cr, s.c_str(), &e);
    if (e.x_advance > max_w_m * kPointsPerM) {
      cairo_set_font_size(cr, size_m * kPointsPerM * max_w_m * kPointsPerM / e.x_advance);
    }
    cairo_move_to(cr, x_m * kPointsPerM, y_m * kPointsPerM);
    cairo_show_text(cr, s.c_str());
  }

  // The footer: the specification, the instruction and the 100 mm ruler, whose bar is exactly
  // kRulerM long (0.5 mm thick) with ticks every millimetre.
  void draw_footer(cairo_t* cr, const Page& p, int sheets) const {
    const BoardSpec& spec = board_.spec();
    // Left-aligned with the board, unless the ruler would then leave the page.
    const double x = std::min(p.area_x, p.w_m - p.edge - kRulerM - 12 * kMm);
    const double text_w = p.w_m - p.edge - x;
    const double top = p.area_y + (o_.paper == Paper::kBoard ? p.shown_h : p.area_h) + 2 * kMm;
    cairo_save(cr);
    cairo_set_source_rgb(cr, 0, 0, 0);
    cairo_select_font_face(cr, "sans-serif", CAIRO_FONT_SLANT_NORMAL, CAIRO_FONT_WEIGHT_NORMAL);
    std::string line1 = board_.spec().to_string() + ": " + std::to_string(spec.cols) + " x " +
                        std::to_string(spec.rows) +
                        (spec.type == BoardType::kCharuco ? " squares" : " inner corners") +
                        " of " + mm_text(spec.square_length_m);
    if (spec.type == BoardType::kCharuco) line1 += ", markers " + mm_text(spec.marker_length_m);
    line1 += "; board " + mm_text(board_w_) + " x " + mm_text(board_h_);
    if (sheets > 1) {
      line1 += "; sheet " + std::to_string(p.row * tiling_.nx + p.col + 1) + " of " +
               std::to_string(sheets) + " (row " + std::to_string(p.row + 1) + ", column " +
               std::to_string(p.col + 1) + ")";
    }
    text(cr, x, top + 3 * kMm, 2.4 * kMm, line1, text_w);
    std::string line2 =
        "Print at 100 % (not 'fit to page'). Check: the bar below measures 100 mm and a square " +
        mm_text(spec.square_length_m) + ".";
    if (sheets > 1) line2 += " Trim at the red marks, overlap the next sheet, match the pattern.";
    text(cr, x, top + 6.5 * kMm, 2.4 * kMm, line2, text_w);
    const double bar_y = top + 8 * kMm;
    cairo_rectangle(cr, x * kPointsPerM, bar_y * kPointsPerM, kRulerM * kPointsPerM,
                    0.5 * kMm * kPointsPerM);
    cairo_fill(cr);
    for (int mm = 0; mm <= 100; ++mm) {
      const double len = mm % 10 == 0 ? 4 * kMm : mm % 5 == 0 ? 2.5 * kMm : 1.5 * kMm;
      const double w = 0.15 * kMm;
      const double tx = x + mm * kMm - (mm == 0 ? 0 : mm == 100 ? w : w / 2);
      cairo_rectangle(cr, tx * kPointsPerM, (bar_y + 0.5 * kMm) * kPointsPerM, w * kPointsPerM,
                      len * kPointsPerM);
    }
    cairo_fill(cr);
    for (int mm = 0; mm <= 100; mm += 10) {
      text(cr, x + mm * kMm + 0.5 * kMm, bar_y + 7.5 * kMm, 2.2 * kMm,
           mm == 100 ? "100 mm" : std::to_string(mm));
    }
    cairo_restore(cr);
  }

  void draw_page(cairo_t* cr, const Page& p, int sheets) const {
    draw_board(cr, p);
    draw_cut_marks(cr, p);
    draw_footer(cr, p, sheets);
  }

  const Board& board_;
  const PrintOptions& o_;
  double board_w_ = 0, board_h_ = 0;
  Tiling tiling_;
  std::string bytes_;
};

std::string png_bytes(const cv::Mat& grey, double dpi) {
  png_structp png = png_create_write_struct(PNG_LIBPNG_VER_STRING, nullptr, nullptr, nullptr);
  if (png == nullptr) throw Error(ErrorCode::kInternal, "printable target: libpng failed");
  png_infop info = png_create_info_struct(png);
  std::string out;
  // libpng reports errors by longjmp: nothing with a destructor is created below this point.
  if (info == nullptr || setjmp(png_jmpbuf(png))) {
    png_destroy_write_struct(&png, &info);
    throw Error(ErrorCode::kInternal, "printable target: PNG encoding failed");
  }
  png_set_write_fn(
      png, &out,
      [](png_structp p, png_bytep data, png_size_t n) {
        static_cast<std::string*>(png_get_io_ptr(p))->append(reinterpret_cast<char*>(data), n);
      },
      nullptr);
  png_set_IHDR(png, info, static_cast<png_uint_32>(grey.cols), static_cast<png_uint_32>(grey.rows),
               8, PNG_COLOR_TYPE_GRAY, PNG_INTERLACE_NONE, PNG_COMPRESSION_TYPE_DEFAULT,
               PNG_FILTER_TYPE_DEFAULT);
  const auto ppm = static_cast<png_uint_32>(std::lround(dpi / 0.0254));
  png_set_pHYs(png, info, ppm, ppm, PNG_RESOLUTION_METER);
  png_write_info(png, info);
  for (int r = 0; r < grey.rows; ++r) png_write_row(png, grey.ptr<png_byte>(r));
  png_write_end(png, nullptr);
  png_destroy_write_struct(&png, &info);
  return out;
}

void write_or_throw(const std::string& path, std::string_view bytes) {
  std::string error;
  if (!write_file_atomic(path, bytes, &error)) throw Error(ErrorCode::kIo, error);
}

}  // namespace

Paper paper_from_name(const std::string& name) {
  std::string n;
  for (char c : name) n += static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
  if (n == "board") return Paper::kBoard;
  if (n == "a4") return Paper::kA4;
  if (n == "a3") return Paper::kA3;
  if (n == "letter") return Paper::kLetter;
  throw Error(ErrorCode::kInvalidArgument,
              "unknown paper '" + name + "': use board, a4, a3 or letter");
}

std::vector<BoardMarkerCell> Board::marker_cells() const {
  std::vector<BoardMarkerCell> cells;
  if (spec_.type != BoardType::kCharuco) return cells;
  const int bits = impl_->dictionary->markerSize + 2;
  const double cell = spec_.marker_length_m / bits;
  for (size_t m = 0; m < impl_->board->ids.size(); ++m) {
    cv::Mat marker;
    cv::aruco::drawMarker(impl_->dictionary, impl_->board->ids[m], bits, marker, 1);
    const cv::Point3f tl = impl_->board->objPoints[m][0];
    for (int r = 0; r < bits; ++r) {
      for (int c = 0; c < bits; ++c) {
        if (marker.at<uchar>(r, c) < 128) cells.push_back({tl.x + c * cell, tl.y + r * cell, cell});
      }
    }
  }
  return cells;
}

void Board::write_printable(const std::string& path, const PrintOptions& o) const {
  if (!(o.dpi >= 50 && o.dpi <= 2400)) {
    throw Error(ErrorCode::kInvalidArgument, "printable target: dpi must be in [50, 2400]");
  }
  if (!(o.margin_m >= 0 && o.margin_m < 1)) {
    throw Error(ErrorCode::kInvalidArgument, "printable target: margin must be in [0, 1) m");
  }
  const std::string ext = path.size() >= 4 ? path.substr(path.size() - 4) : "";
  if (ext == ".pdf" || ext == ".PDF") {
    write_or_throw(path, PdfWriter(*this, o).write());
    return;
  }
  if (ext != ".png" && ext != ".PNG") {
    throw Error(ErrorCode::kInvalidArgument,
                "printable target '" + path + "': use a .png or .pdf file name");
  }
  if (o.paper != Paper::kBoard) {
    throw Error(ErrorCode::kInvalidArgument,
                "printable target '" + path +
                    "': a paper size applies to a PDF; a PNG is the board alone at its dpi");
  }
  // Raster: render finely with an integer number of texels per square, then area-resample to
  // the exact physical size at `dpi` (edges that fall between pixels become grey).
  const cv::Size2d size_m = board_size_m();
  const double px_per_m = o.dpi / 0.0254;
  const int out_w = static_cast<int>(std::lround((size_m.width + 2 * o.margin_m) * px_per_m));
  const int out_h = static_cast<int>(std::lround((size_m.height + 2 * o.margin_m) * px_per_m));
  if (static_cast<double>(out_w) * out_h > 4e8) {
    throw Error(ErrorCode::kInvalidArgument, "printable target: image would be too large");
  }
  // At least 10 texels per marker side: OpenCV draws a marker only with room for its bits and
  // border (7 + 2 for the largest dictionaries), whatever the dpi.
  const double marker_ratio =
      spec_.marker_length_m > 0 ? spec_.marker_length_m / spec_.square_length_m : 1.0;
  const int P = std::max({8, static_cast<int>(std::ceil(spec_.square_length_m * px_per_m)) * 4,
                          static_cast<int>(std::ceil(10.0 / marker_ratio))});
  const BoardTexture tex = render(P, o.margin_m / spec_.square_length_m);
  cv::Mat out;
  cv::resize(tex.image, out, cv::Size(out_w, out_h), 0, 0, cv::INTER_AREA);
  write_or_throw(path, png_bytes(out, o.dpi));
}

}  // namespace posecal
