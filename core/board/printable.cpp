// The printable board at exact physical scale: a vector PDF or a PNG whose pHYs chunk carries the
// resolution. (The hand-written PDF and the pHYs splicing are to be replaced by cairo and libpng,
// issue 17.)
#include <zlib.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <string_view>
#include <opencv2/aruco/charuco.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <sstream>

#include "board/board_internal.hpp"
#include "common/atomic_file.hpp"
#include "common/error.hpp"

namespace posecal {

namespace {

void png_set_dpi(std::vector<uchar>& png, double dpi) {
  // Insert a pHYs chunk (pixels per metre) right after IHDR (8-byte signature + 25-byte IHDR).
  const uint32_t ppm = static_cast<uint32_t>(std::lround(dpi / 0.0254));
  std::vector<uchar> chunk;
  auto put32 = [&](uint32_t v) {
    for (int s = 24; s >= 0; s -= 8) chunk.push_back(static_cast<uchar>((v >> s) & 0xff));
  };
  put32(9);
  const size_t type_pos = chunk.size();
  for (char c : std::string("pHYs")) chunk.push_back(static_cast<uchar>(c));
  put32(ppm);
  put32(ppm);
  chunk.push_back(1);  // unit: metre
  const uLong crc = crc32(0, chunk.data() + type_pos, static_cast<uInt>(chunk.size() - type_pos));
  put32(static_cast<uint32_t>(crc));
  png.insert(png.begin() + 33, chunk.begin(), chunk.end());
}

// A one-page PDF of the given size (points) around a content stream.
std::string pdf_document(const std::string& stream, double page_w, double page_h) {
  std::ostringstream pdf;
  std::vector<size_t> offsets;
  pdf << "%PDF-1.4\n";
  auto obj = [&](const std::string& body) {
    offsets.push_back(static_cast<size_t>(pdf.tellp()));
    pdf << offsets.size() << " 0 obj\n" << body << "\nendobj\n";
  };
  std::ostringstream page;
  page.setf(std::ios::fixed);
  page.precision(4);
  page << "<< /Type /Page /Parent 2 0 R /MediaBox [0 0 " << page_w << " " << page_h
       << "] /Contents 4 0 R >>";
  obj("<< /Type /Catalog /Pages 2 0 R >>");
  obj("<< /Type /Pages /Kids [3 0 R] /Count 1 >>");
  obj(page.str());
  obj("<< /Length " + std::to_string(stream.size()) + " >>\nstream\n" + stream + "endstream");
  const size_t xref = static_cast<size_t>(pdf.tellp());
  pdf << "xref\n0 " << offsets.size() + 1 << "\n0000000000 65535 f \n";
  for (size_t off : offsets) {
    char line[32];
    std::snprintf(line, sizeof line, "%010zu 00000 n \n", off);
    pdf << line;
  }
  pdf << "trailer\n<< /Size " << offsets.size() + 1 << " /Root 1 0 R >>\nstartxref\n"
      << xref << "\n%%EOF\n";
  return pdf.str();
}

}  // namespace

// The PDF page's content stream: every square and every marker cell a filled rectangle at exact
// size. PDF user units are 1/72 inch; y points up, so rows are mirrored.
std::string Board::pdf_content(double margin_m, double page_h) const {
  const double pt_per_m = 72.0 / 0.0254;
  std::ostringstream content;
  content.setf(std::ios::fixed);
  content.precision(4);
  content << "0 g\n";
  auto rect = [&](double x_m, double y_m, double w_m, double h_m) {
    const double x = (x_m + margin_m) * pt_per_m;
    const double y = page_h - (y_m + h_m + margin_m) * pt_per_m;
    content << x << " " << y << " " << w_m * pt_per_m << " " << h_m * pt_per_m << " re f\n";
  };
  const double s = spec_.square_length_m;
  if (spec_.type == BoardType::kChessboard) {
    for (int i = 0; i < spec_.rows + 1; ++i)
      for (int j = 0; j < spec_.cols + 1; ++j)
        if ((i + j) % 2 == 0) rect(j * s, i * s, s, s);
  } else {
    // Read the square colours and marker bits from OpenCV's own drawing so the PDF matches
    // the board the detector expects, cell for cell.
    const int bits = impl_->dictionary->markerSize + 2;
    for (int i = 0; i < spec_.rows; ++i)
      for (int j = 0; j < spec_.cols; ++j)
        if ((i + j) % 2 == 0) rect(j * s, i * s, s, s);
    for (size_t m = 0; m < impl_->board->ids.size(); ++m) {
      cv::Mat marker;
      cv::aruco::drawMarker(impl_->dictionary, impl_->board->ids[m], bits, marker, 1);
      const cv::Point3f tl = impl_->board->objPoints[m][0];
      const double cell = spec_.marker_length_m / bits;
      for (int r = 0; r < bits; ++r)
        for (int c = 0; c < bits; ++c)
          if (marker.at<uchar>(r, c) < 128) rect(tl.x + c * cell, tl.y + r * cell, cell, cell);
    }
  }
  return content.str();
}

namespace {

void write_or_throw(const std::string& path, std::string_view bytes) {
  std::string error;
  if (!write_file_atomic(path, bytes, &error)) throw Error(ErrorCode::kIo, error);
}

}  // namespace

void Board::write_printable(const std::string& path, double dpi, double margin_m) const {
  if (!(dpi >= 50 && dpi <= 2400)) {
    throw Error(ErrorCode::kInvalidArgument, "printable target: dpi must be in [50, 2400]");
  }
  if (!(margin_m >= 0 && margin_m < 1)) {
    throw Error(ErrorCode::kInvalidArgument, "printable target: margin must be in [0, 1) m");
  }
  const std::string ext = path.size() >= 4 ? path.substr(path.size() - 4) : "";
  const cv::Size2d size_m = board_size_m();
  if (ext == ".pdf" || ext == ".PDF") {
    const double pt_per_m = 72.0 / 0.0254;
    const double page_w = (size_m.width + 2 * margin_m) * pt_per_m;
    const double page_h = (size_m.height + 2 * margin_m) * pt_per_m;
    write_or_throw(path, pdf_document(pdf_content(margin_m, page_h), page_w, page_h));
    return;
  }
  if (ext != ".png" && ext != ".PNG") {
    throw Error(ErrorCode::kInvalidArgument,
                "printable target '" + path + "': use a .png or .pdf file name");
  }
  // Raster: render finely with an integer number of texels per square, then area-resample to
  // the exact physical size at `dpi` (edges that fall between pixels become grey).
  const double px_per_m = dpi / 0.0254;
  const int out_w = static_cast<int>(std::lround((size_m.width + 2 * margin_m) * px_per_m));
  const int out_h = static_cast<int>(std::lround((size_m.height + 2 * margin_m) * px_per_m));
  if (static_cast<double>(out_w) * out_h > 4e8) {
    throw Error(ErrorCode::kInvalidArgument, "printable target: image would be too large");
  }
  // At least 10 texels per marker side: OpenCV draws a marker only with room for its bits and
  // border (7 + 2 for the largest dictionaries), whatever the dpi.
  const double marker_ratio = spec_.marker_length_m > 0 ? spec_.marker_length_m / spec_.square_length_m : 1.0;
  const int P = std::max({8, static_cast<int>(std::ceil(spec_.square_length_m * px_per_m)) * 4,
                          static_cast<int>(std::ceil(10.0 / marker_ratio))});
  const BoardTexture tex = render(P, margin_m / spec_.square_length_m);
  cv::Mat out;
  cv::resize(tex.image, out, cv::Size(out_w, out_h), 0, 0, cv::INTER_AREA);
  std::vector<uchar> png;
  if (!cv::imencode(".png", out, png)) throw Error(ErrorCode::kIo, "PNG encoding failed");
  png_set_dpi(png, dpi);
  write_or_throw(path, std::string_view(reinterpret_cast<const char*>(png.data()), png.size()));
}

}  // namespace posecal
