// The report's figures, drawn with cairo (plots.hpp). Each figure draws itself into a
// kFigureWidth x kFigureHeight area; the same drawing becomes a PNG (image surface) or a PDF page.
#include "report/plots.hpp"

#include <cairo-pdf.h>
#include <cairo.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <limits>
#include <memory>
#include <opencv2/imgproc.hpp>

#include "common/error.hpp"

namespace posecal {

namespace {

constexpr double kW = kFigureWidth;
constexpr double kH = kFigureHeight;
const char* const kFont = "DejaVu Sans";

struct Rgb {
  double r, g, b;
};

// Ten well-separated hues (the "tab10" idea), darker and lighter for keyframes beyond ten.
Rgb keyframe_colour(int i) {
  static const Rgb base[10] = {{0.12, 0.47, 0.71}, {1.00, 0.50, 0.05}, {0.17, 0.63, 0.17},
                               {0.84, 0.15, 0.16}, {0.58, 0.40, 0.74}, {0.55, 0.34, 0.29},
                               {0.89, 0.47, 0.76}, {0.50, 0.50, 0.50}, {0.74, 0.74, 0.13},
                               {0.09, 0.75, 0.81}};
  const Rgb c = base[i % 10];
  const double f = (i / 10) % 2 == 0 ? 1.0 : 0.6;
  return {c.r * f, c.g * f, c.b * f};
}

// A perceptually ordered map from dark blue through green to yellow (viridis' end points),
// t in [0, 1].
Rgb colour_map(double t) {
  static const Rgb stops[5] = {{0.267, 0.005, 0.329},
                               {0.231, 0.322, 0.545},
                               {0.129, 0.569, 0.549},
                               {0.369, 0.788, 0.384},
                               {0.993, 0.906, 0.144}};
  t = std::clamp(t, 0.0, 1.0) * 4;
  const int i = std::min(3, static_cast<int>(t));
  const double f = t - i;
  const Rgb a = stops[i], b = stops[i + 1];
  return {a.r + f * (b.r - a.r), a.g + f * (b.g - a.g), a.b + f * (b.b - a.b)};
}

void set_colour(cairo_t* cr, Rgb c, double alpha = 1) {
  cairo_set_source_rgba(cr, c.r, c.g, c.b, alpha);
}

enum class Align { kLeft, kCentre, kRight };

// Text with its baseline at y.
void text(cairo_t* cr, double x, double y, const std::string& s, double size,
          Align align = Align::kLeft, bool bold = false) {
  cairo_select_font_face(cr, kFont, CAIRO_FONT_SLANT_NORMAL,
                         bold ? CAIRO_FONT_WEIGHT_BOLD : CAIRO_FONT_WEIGHT_NORMAL);
  cairo_set_font_size(cr, size);
  cairo_text_extents_t e;
  cairo_text_extents(cr, s.c_str(), &e);
  const double dx = align == Align::kLeft     ? 0
                    : align == Align::kCentre ? -e.x_advance / 2
                                              : -e.x_advance;
  cairo_move_to(cr, x + dx, y);
  cairo_show_text(cr, s.c_str());
}

double text_width(cairo_t* cr, const std::string& s, double size) {
  cairo_select_font_face(cr, kFont, CAIRO_FONT_SLANT_NORMAL, CAIRO_FONT_WEIGHT_NORMAL);
  cairo_set_font_size(cr, size);
  cairo_text_extents_t e;
  cairo_text_extents(cr, s.c_str(), &e);
  return e.x_advance;
}

// Splits `s` into lines of at most `width` units at spaces.
std::vector<std::string> wrap(cairo_t* cr, const std::string& s, double size, double width) {
  std::vector<std::string> lines;
  std::string line, word;
  auto flush_word = [&] {
    if (word.empty()) return;
    const std::string candidate = line.empty() ? word : line + " " + word;
    if (!line.empty() && text_width(cr, candidate, size) > width) {
      lines.push_back(line);
      line = word;
    } else {
      line = candidate;
    }
    word.clear();
  };
  for (char c : s) {
    if (c == ' ') {
      flush_word();
    } else {
      word += c;
    }
  }
  flush_word();
  if (!line.empty()) lines.push_back(line);
  return lines;
}

std::string fmt(const char* format, double v) {
  char buf[64];
  std::snprintf(buf, sizeof buf, format, v);
  return buf;
}

// A short number for tick labels: no trailing zeros, exponent form for very small or large.
std::string tick_text(double v) {
  if (v == 0) return "0";
  const double a = std::fabs(v);
  if (a >= 1e5 || a < 1e-3) return fmt("%.0e", v);
  return fmt("%g", v);
}

void white_background(cairo_t* cr) {
  cairo_set_source_rgb(cr, 1, 1, 1);
  cairo_paint(cr);
}

void figure_title(cairo_t* cr, const std::string& title, const std::string& subtitle) {
  cairo_set_source_rgb(cr, 0, 0, 0);
  text(cr, 30, 38, title, 22, Align::kLeft, true);
  cairo_set_source_rgb(cr, 0.3, 0.3, 0.3);
  text(cr, 30, 62, subtitle, 13);
}

// Ticks at 1, 2 or 5 times a power of ten covering [lo, hi], about n of them.
std::vector<double> nice_ticks(double lo, double hi, int n) {
  std::vector<double> ticks;
  if (!(hi > lo) || !std::isfinite(lo) || !std::isfinite(hi)) return ticks;
  const double raw = (hi - lo) / n;
  const double p = std::pow(10.0, std::floor(std::log10(raw)));
  const double step = raw / p < 1.5 ? p : raw / p < 3.5 ? 2 * p : raw / p < 7.5 ? 5 * p : 10 * p;
  for (double t = std::ceil(lo / step) * step; t <= hi + step * 1e-9; t += step)
    ticks.push_back(std::fabs(t) < step * 1e-9 ? 0.0 : t);
  return ticks;
}

// A 1-2-5 value near v (> 0), for arrow scales.
double nice_value(double v) {
  const double p = std::pow(10.0, std::floor(std::log10(v)));
  const double m = v / p;
  return (m < 1.5 ? 1 : m < 3.5 ? 2 : m < 7.5 ? 5 : 10) * p;
}

// A rectangle of the figure showing data [xmin, xmax] x [ymin, ymax]. Image axes have y down
// (pixel rows); a log axis maps log10 of the value.
struct Axes {
  double x0 = 0, y0 = 0, w = 0, h = 0;
  double xmin = 0, xmax = 1, ymin = 0, ymax = 1;
  bool y_down = false;
  bool log_y = false;
  bool integer_x = false;  // ticks only at whole numbers (counts)
  double X(double x) const { return x0 + (x - xmin) / (xmax - xmin) * w; }
  double Y(double y) const {
    const double v = log_y ? std::log10(y) : y;
    const double lo = log_y ? std::log10(ymin) : ymin, hi = log_y ? std::log10(ymax) : ymax;
    const double f = (v - lo) / (hi - lo);
    return y_down ? y0 + f * h : y0 + h - f * h;
  }
};

// The image's pixel rectangle fitted (aspect kept) into the box (x, y, w, h).
Axes image_axes(cv::Size image, double x, double y, double w, double h) {
  Axes a;
  const double s = std::min(w / image.width, h / image.height);
  a.w = image.width * s;
  a.h = image.height * s;
  a.x0 = x + (w - a.w) / 2;
  a.y0 = y;
  a.xmin = -0.5;
  a.xmax = image.width - 0.5;
  a.ymin = -0.5;
  a.ymax = image.height - 0.5;
  a.y_down = true;
  return a;
}

// Frame, ticks with labels, axis labels.
void draw_axes(cairo_t* cr, const Axes& a, const std::string& xlabel, const std::string& ylabel) {
  cairo_set_source_rgb(cr, 0, 0, 0);
  cairo_set_line_width(cr, 1);
  cairo_rectangle(cr, a.x0, a.y0, a.w, a.h);
  cairo_stroke(cr);
  for (double t : nice_ticks(a.xmin, a.xmax, 8)) {
    if (a.integer_x && t != std::round(t)) continue;
    const double x = a.X(t);
    cairo_move_to(cr, x, a.y0 + a.h);
    cairo_line_to(cr, x, a.y0 + a.h + 5);
    cairo_stroke(cr);
    text(cr, x, a.y0 + a.h + 19, tick_text(t), 11, Align::kCentre);
  }
  std::vector<double> yt;
  if (a.log_y) {
    for (double e = std::floor(std::log10(a.ymin)); e <= std::ceil(std::log10(a.ymax)); ++e) {
      const double v = std::pow(10.0, e);
      if (v >= a.ymin * (1 - 1e-9) && v <= a.ymax * (1 + 1e-9)) yt.push_back(v);
    }
  } else {
    yt = nice_ticks(a.ymin, a.ymax, 6);
  }
  for (double t : yt) {
    const double y = a.Y(t);
    cairo_move_to(cr, a.x0 - 5, y);
    cairo_line_to(cr, a.x0, y);
    cairo_stroke(cr);
    text(cr, a.x0 - 8, y + 4, tick_text(t), 11, Align::kRight);
    if (a.log_y) {  // faint decade lines help read a log scale
      cairo_save(cr);
      cairo_set_source_rgba(cr, 0, 0, 0, 0.12);
      cairo_move_to(cr, a.x0, y);
      cairo_line_to(cr, a.x0 + a.w, y);
      cairo_stroke(cr);
      cairo_restore(cr);
    }
  }
  cairo_set_source_rgb(cr, 0, 0, 0);
  text(cr, a.x0 + a.w / 2, a.y0 + a.h + 40, xlabel, 13, Align::kCentre);
  cairo_save(cr);
  cairo_translate(cr, a.x0 - 58, a.y0 + a.h / 2);
  cairo_rotate(cr, -M_PI / 2);
  text(cr, 0, 0, ylabel, 13, Align::kCentre);
  cairo_restore(cr);
}

void arrow(cairo_t* cr, double x0, double y0, double x1, double y1, double head) {
  cairo_move_to(cr, x0, y0);
  cairo_line_to(cr, x1, y1);
  cairo_stroke(cr);
  const double len = std::hypot(x1 - x0, y1 - y0);
  if (len < 1e-9) return;
  head = std::min(head, len * 0.5);
  const double ux = (x1 - x0) / len, uy = (y1 - y0) / len;
  cairo_move_to(cr, x1, y1);
  cairo_line_to(cr, x1 - head * (ux - 0.5 * uy), y1 - head * (uy + 0.5 * ux));
  cairo_line_to(cr, x1 - head * (ux + 0.5 * uy), y1 - head * (uy - 0.5 * ux));
  cairo_close_path(cr);
  cairo_fill(cr);
}

void dot(cairo_t* cr, double x, double y, double r) {
  cairo_new_sub_path(cr);
  cairo_arc(cr, x, y, r, 0, 2 * M_PI);
  cairo_fill(cr);
}

// A vertical colour bar for [vmin, vmax] with ticks and a label.
void colour_bar(cairo_t* cr, double x, double y, double w, double h, double vmin, double vmax,
                const std::string& label) {
  const int steps = 100;
  for (int i = 0; i < steps; ++i) {
    set_colour(cr, colour_map((i + 0.5) / steps));
    cairo_rectangle(cr, x, y + h - (i + 1) * h / steps, w, h / steps + 0.5);
    cairo_fill(cr);
  }
  cairo_set_source_rgb(cr, 0, 0, 0);
  cairo_set_line_width(cr, 1);
  cairo_rectangle(cr, x, y, w, h);
  cairo_stroke(cr);
  if (vmax > vmin) {
    for (double t : nice_ticks(vmin, vmax, 6)) {
      const double ty = y + h - (t - vmin) / (vmax - vmin) * h;
      cairo_move_to(cr, x + w, ty);
      cairo_line_to(cr, x + w + 5, ty);
      cairo_stroke(cr);
      text(cr, x + w + 8, ty + 4, tick_text(t), 11);
    }
  } else {
    text(cr, x + w + 8, y + h / 2, tick_text(vmin), 11);
  }
  text(cr, x + w / 2, y - 10, label, 13, Align::kCentre);
}

// Paints a CV_32F map over the axes' image rectangle in the colour map, NaN in light grey.
void paint_map(cairo_t* cr, const Axes& a, const cv::Mat& map, double vmin, double vmax,
               bool smooth) {
  const int cols = map.cols, rows = map.rows;
  cairo_surface_t* img = cairo_image_surface_create(CAIRO_FORMAT_RGB24, cols, rows);
  cairo_surface_flush(img);
  unsigned char* data = cairo_image_surface_get_data(img);
  const int stride = cairo_image_surface_get_stride(img);
  if (data) {
    for (int r = 0; r < rows; ++r) {
      auto* px = reinterpret_cast<uint32_t*>(data + static_cast<size_t>(r) * stride);
      for (int c = 0; c < cols; ++c) {
        const float v = map.at<float>(r, c);
        Rgb col{0.85, 0.85, 0.85};
        if (std::isfinite(v)) col = colour_map(vmax > vmin ? (v - vmin) / (vmax - vmin) : 0.5);
        px[c] = (static_cast<uint32_t>(col.r * 255 + 0.5) << 16) |
                (static_cast<uint32_t>(col.g * 255 + 0.5) << 8) |
                static_cast<uint32_t>(col.b * 255 + 0.5);
      }
    }
  }
  cairo_surface_mark_dirty(img);
  cairo_save(cr);
  cairo_rectangle(cr, a.x0, a.y0, a.w, a.h);
  cairo_clip(cr);
  cairo_translate(cr, a.x0, a.y0);
  cairo_scale(cr, a.w / cols, a.h / rows);
  cairo_set_source_surface(cr, img, 0, 0);
  cairo_pattern_set_filter(cairo_get_source(cr),
                           smooth ? CAIRO_FILTER_BILINEAR : CAIRO_FILTER_NEAREST);
  cairo_pattern_set_extend(cairo_get_source(cr), CAIRO_EXTEND_PAD);
  cairo_paint(cr);
  cairo_restore(cr);
  cairo_surface_destroy(img);
}

// The finite range of a CV_32F map; {NaN, NaN} if it has no finite value.
std::pair<double, double> finite_range(const cv::Mat& map) {
  double lo = std::numeric_limits<double>::infinity(), hi = -lo;
  for (int r = 0; r < map.rows; ++r)
    for (int c = 0; c < map.cols; ++c) {
      const float v = map.at<float>(r, c);
      if (!std::isfinite(v)) continue;
      lo = std::min(lo, static_cast<double>(v));
      hi = std::max(hi, static_cast<double>(v));
    }
  if (lo > hi) return {std::nan(""), std::nan("")};
  return {lo, hi};
}

double rms_of(const KeyframeCorners& k) {
  double s = 0;
  for (size_t i = 0; i < k.observed.size(); ++i) {
    const cv::Point2d d = k.observed[i] - k.reprojected[i];
    s += d.dot(d);
  }
  return k.observed.empty() ? 0 : std::sqrt(s / k.observed.size());
}

// The keyframe's board outline: the convex hull of its corners.
std::vector<cv::Point2f> outline(const KeyframeCorners& k) {
  std::vector<cv::Point2f> pts(k.observed.begin(), k.observed.end()), hull;
  if (pts.size() >= 3) cv::convexHull(pts, hull);
  return hull.empty() ? pts : hull;
}

void legend_entry(cairo_t* cr, double x, double y, Rgb c, const std::string& label) {
  set_colour(cr, c);
  cairo_rectangle(cr, x, y - 10, 14, 12);
  cairo_fill(cr);
  cairo_set_source_rgb(cr, 0, 0, 0);
  text(cr, x + 20, y, label, 12);
}

void draw_coverage(cairo_t* cr, cv::Size image, const std::vector<KeyframeCorners>& kfs) {
  white_background(cr);
  figure_title(cr, "Coverage of the image",
               std::to_string(kfs.size()) +
                   " keyframes: each board outline (hull of its "
                   "detected corners) and its corners, numbered in capture order");
  const Axes a = image_axes(image, 90, 90, 700, 520);
  cairo_set_source_rgb(cr, 0.96, 0.96, 0.96);
  cairo_rectangle(cr, a.x0, a.y0, a.w, a.h);
  cairo_fill(cr);
  for (size_t i = 0; i < kfs.size(); ++i) {
    const Rgb c = keyframe_colour(static_cast<int>(i));
    const std::vector<cv::Point2f> hull = outline(kfs[i]);
    if (hull.empty()) continue;
    for (size_t j = 0; j < hull.size(); ++j) {
      if (j == 0)
        cairo_move_to(cr, a.X(hull[j].x), a.Y(hull[j].y));
      else
        cairo_line_to(cr, a.X(hull[j].x), a.Y(hull[j].y));
    }
    cairo_close_path(cr);
    set_colour(cr, c, 0.10);
    cairo_fill_preserve(cr);
    set_colour(cr, c, 0.9);
    cairo_set_line_width(cr, 2);
    cairo_stroke(cr);
    for (const cv::Point2d& p : kfs[i].observed) dot(cr, a.X(p.x), a.Y(p.y), 1.8);
  }
  // Numbers last, so no outline covers them.
  for (size_t i = 0; i < kfs.size(); ++i) {
    if (kfs[i].observed.empty()) continue;
    cv::Point2d centre(0, 0);
    for (const cv::Point2d& p : kfs[i].observed) centre += p;
    centre *= 1.0 / kfs[i].observed.size();
    const std::string n = std::to_string(kfs[i].index);
    cairo_set_source_rgba(cr, 1, 1, 1, 0.85);
    const double tw = text_width(cr, n, 15);
    cairo_rectangle(cr, a.X(centre.x) - tw / 2 - 3, a.Y(centre.y) - 14, tw + 6, 19);
    cairo_fill(cr);
    set_colour(cr, keyframe_colour(static_cast<int>(i)));
    text(cr, a.X(centre.x), a.Y(centre.y), n, 15, Align::kCentre, true);
  }
  draw_axes(cr, a, "x (px)", "y (px)");
  cairo_set_source_rgb(cr, 0, 0, 0);
  text(cr, 815, 100, "keyframe: corners", 13, Align::kLeft, true);
  const double step = std::min(22.0, 540.0 / std::max<size_t>(1, kfs.size()));
  for (size_t i = 0; i < kfs.size(); ++i) {
    legend_entry(cr, 815, 125 + i * step, keyframe_colour(static_cast<int>(i)),
                 std::to_string(kfs[i].index) + ": " + std::to_string(kfs[i].observed.size()));
  }
}

void draw_residuals(cairo_t* cr, cv::Size image, const std::vector<KeyframeCorners>& kfs) {
  white_background(cr);
  std::vector<double> mags;
  double ss = 0;
  size_t n = 0;
  for (const KeyframeCorners& k : kfs)
    for (size_t i = 0; i < k.observed.size(); ++i) {
      const cv::Point2d d = k.observed[i] - k.reprojected[i];
      mags.push_back(std::hypot(d.x, d.y));
      ss += d.dot(d);
      ++n;
    }
  const double rms = n ? std::sqrt(ss / n) : 0;
  const Axes a = image_axes(image, 90, 90, 640, 520);
  // Scale: the 95th-percentile residual becomes 3% of the image width.
  double p95 = 0;
  if (!mags.empty()) {
    std::sort(mags.begin(), mags.end());
    p95 = mags[std::min(mags.size() - 1, static_cast<size_t>(0.95 * mags.size()))];
  }
  const double scale = p95 > 0 ? nice_value(0.03 * image.width / p95) : 1;
  figure_title(cr, "Residuals per keyframe",
               "observed - reprojected (final calibration, each keyframe's pose), vectors x" +
                   tick_text(scale) + "; RMS over all corners " + fmt("%.3f", rms) + " px");
  cairo_set_source_rgb(cr, 0.97, 0.97, 0.97);
  cairo_rectangle(cr, a.x0, a.y0, a.w, a.h);
  cairo_fill(cr);
  const double head = 4;
  cairo_set_line_width(cr, 1.2);
  for (size_t f = 0; f < kfs.size(); ++f) {
    set_colour(cr, keyframe_colour(static_cast<int>(f)), 0.9);
    const KeyframeCorners& k = kfs[f];
    for (size_t i = 0; i < k.observed.size(); ++i) {
      const cv::Point2d& p = k.observed[i];
      const cv::Point2d d = (p - k.reprojected[i]) * scale;
      arrow(cr, a.X(p.x), a.Y(p.y), a.X(p.x + d.x), a.Y(p.y + d.y), head);
    }
  }
  draw_axes(cr, a, "x (px)", "y (px)");
  // A reference arrow of a round length in px.
  const double ref_px = p95 > 0 ? nice_value(p95) : 1;
  const double ref_len = ref_px * scale * a.w / image.width;
  cairo_set_source_rgb(cr, 0, 0, 0);
  cairo_set_line_width(cr, 1.5);
  arrow(cr, a.x0, a.y0 + a.h + 62, a.x0 + ref_len, a.y0 + a.h + 62, 6);
  text(cr, a.x0 + ref_len + 10, a.y0 + a.h + 66,
       "= " + tick_text(ref_px) + " px of residual (scale x" + tick_text(scale) + ")", 12);
  // RMS per keyframe as bars.
  double max_rms = 0;
  std::vector<double> frame_rms;
  for (const KeyframeCorners& k : kfs) {
    frame_rms.push_back(rms_of(k));
    max_rms = std::max(max_rms, frame_rms.back());
  }
  const double bx = 790, bw = 130;
  cairo_set_source_rgb(cr, 0, 0, 0);
  text(cr, bx - 30, 100, "RMS per keyframe (px)", 13, Align::kLeft, true);
  const double step = std::min(24.0, 520.0 / std::max<size_t>(1, kfs.size()));
  for (size_t f = 0; f < kfs.size(); ++f) {
    const double y = 125 + f * step;
    cairo_set_source_rgb(cr, 0, 0, 0);
    text(cr, bx - 8, y, std::to_string(kfs[f].index), 12, Align::kRight);
    set_colour(cr, keyframe_colour(static_cast<int>(f)));
    const double len = max_rms > 0 ? frame_rms[f] / max_rms * bw : 0;
    cairo_rectangle(cr, bx, y - std::min(12.0, step - 4), len, std::min(12.0, step - 4));
    cairo_fill(cr);
    cairo_set_source_rgb(cr, 0, 0, 0);
    text(cr, bx + len + 6, y, fmt("%.3f", frame_rms[f]), 11);
  }
}

void draw_distortion(cairo_t* cr, const CameraModel& m) {
  white_background(cr);
  const cv::Size image = m.size();
  const int step = std::max(1, std::max(image.width, image.height) / 240);
  const cv::Mat mag = m.distortion_map(step);
  const auto [lo, hi] = finite_range(mag);
  const double vmin = 0, vmax = std::isfinite(hi) && hi > 0 ? hi : 1;
  figure_title(cr, "Lens distortion",
               std::string("displacement of the lens model (") + lens_model_name(m.lens_model()) +
                   ") from a pinhole camera over the image: magnitude (colour, px), direction "
                   "(arrows)");
  const Axes a = image_axes(image, 90, 90, 720, 520);
  // The map's cell (i, j) is pixel (j step, i step): it covers [j step - step/2, ...).
  Axes cells = a;
  paint_map(cr, cells, mag, vmin, vmax, true);
  // Arrows from where a pinhole camera (same fx, fy, cx, cy) sees the ray to where the lens
  // puts it: p - K x_n(p), with x_n the ray of pixel p.
  const int nx = 16;
  const int ny =
      std::max(2, static_cast<int>(std::lround(nx * image.height / double(image.width))));
  struct Shift {
    cv::Point2d p, d;
  };
  std::vector<Shift> shifts;
  double max_d = 0;
  for (int j = 0; j < ny; ++j)
    for (int i = 0; i < nx; ++i) {
      const Eigen::Vector2d p((i + 0.5) * image.width / nx - 0.5,
                              (j + 0.5) * image.height / ny - 0.5);
      Eigen::Vector2d xn;
      if (!m.unproject(p, &xn)) continue;
      const cv::Point2d ideal(m.fx() * xn.x() + m.cx(), m.fy() * xn.y() + m.cy());
      const cv::Point2d d(p.x() - ideal.x, p.y() - ideal.y);
      shifts.push_back({{p.x(), p.y()}, d});
      max_d = std::max(max_d, std::hypot(d.x, d.y));
    }
  const double cell_px = image.width / static_cast<double>(nx);
  const double scale = max_d > 1e-6 ? nice_value(0.8 * cell_px / max_d) : 0;
  cairo_set_source_rgba(cr, 1, 1, 1, 0.95);
  cairo_set_line_width(cr, 1.5);
  for (const Shift& s : shifts) {
    arrow(cr, a.X(s.p.x - s.d.x * scale), a.Y(s.p.y - s.d.y * scale), a.X(s.p.x), a.Y(s.p.y), 5);
  }
  draw_axes(cr, a, "x (px)", "y (px)");
  colour_bar(cr, 880, 110, 22, 420, vmin, vmax, "|shift| (px)");
  cairo_set_source_rgb(cr, 0, 0, 0);
  text(cr, a.x0, a.y0 + a.h + 66,
       scale > 0 ? "arrows x" + tick_text(scale) +
                       ", from the pinhole position to the lens' one; "
                       "largest shift " +
                       fmt("%.2f", max_d) + " px; grey: no ray"
                 : std::string("no distortion: the lens model's coefficients are zero"),
       12);
}

void draw_expected_error(cairo_t* cr, cv::Size image, const cv::Mat& map, double rms_px) {
  white_background(cr);
  const auto [lo, hi] = finite_range(map);
  figure_title(cr, "Expected projection error",
               "predicted RMS error of a projected ray at the measured corner noise, from the "
               "intrinsics' covariance; RMS over the image " +
                   (std::isfinite(rms_px) ? fmt("%.4f", rms_px) + " px" : std::string("unknown")));
  const Axes a = image_axes(image, 90, 90, 720, 520);
  // The map is sampled edge to edge: cell centres at the grid points, so the painted cells
  // extend half a cell beyond the image; clip to it.
  Axes cells = a;
  const double cw = a.w / (map.cols - 1), ch = a.h / (map.rows - 1);
  cells.x0 -= cw / 2;
  cells.y0 -= ch / 2;
  cells.w += cw;
  cells.h += ch;
  cairo_save(cr);
  cairo_rectangle(cr, a.x0, a.y0, a.w, a.h);
  cairo_clip(cr);
  const bool any = std::isfinite(lo);
  const double vmin = any ? lo : 0, vmax = any && hi > lo ? hi : vmin + 1e-3;
  paint_map(cr, cells, map, vmin, vmax, false);
  cairo_restore(cr);
  // The grid values where the map is coarse enough to read them.
  if (map.cols <= 20 && map.rows <= 20) {
    for (int r = 0; r < map.rows; ++r)
      for (int c = 0; c < map.cols; ++c) {
        const float v = map.at<float>(r, c);
        if (!std::isfinite(v)) continue;
        cairo_set_source_rgb(cr, 1, 1, 1);
        text(cr, a.x0 + c * cw, a.y0 + r * ch + 4, fmt("%.2f", v), 9, Align::kCentre);
      }
  }
  draw_axes(cr, a, "x (px)", "y (px)");
  colour_bar(cr, 880, 110, 22, 420, vmin, vmax, "error (px)");
  cairo_set_source_rgb(cr, 0, 0, 0);
  text(cr, a.x0, a.y0 + a.h + 66,
       any ? "lowest " + fmt("%.4f", lo) + " px, highest " + fmt("%.4f", hi) + " px; grey: no ray"
           : std::string("no grid point has a ray under this calibration"),
       12);
}

void draw_sigma(cairo_t* cr, const std::vector<std::string>& names, const std::vector<int>& counts,
                const std::vector<std::vector<double>>& sigma) {
  white_background(cr);
  figure_title(cr, "Uncertainty after each keyframe",
               "sigma of each intrinsic (at the measured noise) from the first n keyframes, "
               "re-solved as the session solved them; px for fx, fy, cx, cy");
  double lo = std::numeric_limits<double>::infinity(), hi = 0;
  for (const auto& row : sigma)
    for (double v : row)
      if (std::isfinite(v) && v > 0) {
        lo = std::min(lo, v);
        hi = std::max(hi, v);
      }
  Axes a;
  a.x0 = 110;
  a.y0 = 90;
  a.w = 660;
  a.h = 520;
  const int cmin = counts.empty() ? 2 : counts.front(), cmax = counts.empty() ? 3 : counts.back();
  a.xmin = cmin - 0.5;
  a.xmax = std::max(cmin + 1, cmax) + 0.5;
  a.log_y = true;
  a.integer_x = true;
  if (hi > 0) {
    a.ymin = std::pow(10.0, std::floor(std::log10(lo)));
    a.ymax = std::pow(10.0, std::ceil(std::log10(hi)));
    if (a.ymax <= a.ymin) a.ymax = a.ymin * 10;
  } else {
    a.ymin = 1e-3;
    a.ymax = 1;
  }
  cairo_save(cr);
  cairo_rectangle(cr, a.x0, a.y0, a.w, a.h);
  cairo_clip(cr);
  for (size_t p = 0; p < names.size(); ++p) {
    const Rgb c = keyframe_colour(static_cast<int>(p));
    set_colour(cr, c);
    cairo_set_line_width(cr, 2);
    bool pen = false;
    for (size_t i = 0; i < counts.size(); ++i) {
      const double v = p < sigma[i].size() ? sigma[i][p] : std::nan("");
      if (!(std::isfinite(v) && v > 0)) {
        if (pen) cairo_stroke(cr);
        pen = false;
        continue;
      }
      if (pen)
        cairo_line_to(cr, a.X(counts[i]), a.Y(v));
      else
        cairo_move_to(cr, a.X(counts[i]), a.Y(v));
      pen = true;
    }
    if (pen) cairo_stroke(cr);
    for (size_t i = 0; i < counts.size(); ++i) {
      const double v = p < sigma[i].size() ? sigma[i][p] : std::nan("");
      if (std::isfinite(v) && v > 0) dot(cr, a.X(counts[i]), a.Y(v), 3.5);
    }
  }
  cairo_restore(cr);
  draw_axes(cr, a, "keyframes used", "sigma (log scale)");
  cairo_set_source_rgb(cr, 0, 0, 0);
  text(cr, 800, 100, "parameter: last sigma", 13, Align::kLeft, true);
  for (size_t p = 0; p < names.size(); ++p) {
    const double last = sigma.empty() || p >= sigma.back().size() ? std::nan("") : sigma.back()[p];
    legend_entry(cr, 800, 125 + p * 24.0, keyframe_colour(static_cast<int>(p)),
                 names[p] + ": " +
                     (std::isfinite(last) && last > 0 ? fmt("%.3g", last) : std::string("fixed")));
  }
}

void draw_fleet(cairo_t* cr, const FleetStrips& f) {
  white_background(cr);
  figure_title(cr, "Verdict and fleet position",
               "the quality gate's verdict, and this unit's intrinsics among " + f.group);
  // The verdict.
  const bool pass = f.verdict == "pass", fail = f.verdict == "fail";
  if (pass)
    cairo_set_source_rgb(cr, 0.10, 0.55, 0.20);
  else if (fail)
    cairo_set_source_rgb(cr, 0.80, 0.10, 0.10);
  else
    cairo_set_source_rgb(cr, 0.4, 0.4, 0.4);
  text(cr, 30, 110,
       pass   ? "PASS"
       : fail ? "FAIL"
              : "no verdict (the run had no quality specification)",
       pass || fail ? 30 : 18, Align::kLeft, true);
  cairo_set_source_rgb(cr, 0, 0, 0);
  double y = 138;
  if (fail && f.reasons.empty()) {
    text(cr, 30, y, "(no reason recorded)", 13);
    y += 20;
  }
  int shown = 0;
  for (const std::string& r : f.reasons) {
    for (const std::string& line : wrap(cr, "- " + r, 13, 930)) {
      if (shown++ == 6) {
        text(cr, 30, y, "...", 13);
        y += 20;
        break;
      }
      if (shown > 6) break;
      text(cr, 30, y, line, 13);
      y += 20;
    }
  }
  if (!f.position.empty()) {
    y += 6;
    for (const std::string& line : wrap(cr, f.position, 13, 930)) {
      text(cr, 30, y, line, 13, Align::kLeft, true);
      y += 20;
    }
  }
  y = std::max(y + 10, 200.0);
  // The strips.
  const double x0 = 130, x1 = 760;
  cairo_set_source_rgb(cr, 0, 0, 0);
  if (f.others.empty()) {
    text(cr, 30, y, "no other units of " + f.group + " in this store: this unit's values", 14,
         Align::kLeft, true);
  } else {
    text(cr, 30, y,
         std::to_string(f.others.size()) + " other unit" + (f.others.size() == 1 ? "" : "s") +
             " (grey) and this unit (red); each strip runs from the lowest to the highest value",
         14, Align::kLeft, true);
  }
  y += 16;
  const double row = std::min(48.0, (kH - 20 - y) / std::max<size_t>(1, f.names.size()));
  for (size_t p = 0; p < f.names.size(); ++p) {
    const double cy = y + row * (p + 0.6);
    const double v = p < f.unit.size() ? f.unit[p] : std::nan("");
    double lo = v, hi = v;
    for (const auto& o : f.others)
      if (p < o.size() && std::isfinite(o[p])) {
        lo = std::min(lo, o[p]);
        hi = std::max(hi, o[p]);
      }
    auto X = [&](double value) {
      return hi > lo ? x0 + (value - lo) / (hi - lo) * (x1 - x0) : (x0 + x1) / 2;
    };
    cairo_set_source_rgb(cr, 0, 0, 0);
    text(cr, x0 - 60, cy + 5, f.names[p], 14, Align::kRight, true);
    cairo_set_source_rgb(cr, 0.75, 0.75, 0.75);
    cairo_set_line_width(cr, 1);
    cairo_move_to(cr, x0, cy);
    cairo_line_to(cr, x1, cy);
    cairo_stroke(cr);
    cairo_set_source_rgb(cr, 0.35, 0.35, 0.35);
    if (!f.others.empty()) {
      text(cr, x0 - 6, cy + 4, fmt("%.4g", lo), 10, Align::kRight);
      text(cr, x1 + 6, cy + 4, fmt("%.4g", hi), 10);
    }
    cairo_set_source_rgba(cr, 0.45, 0.45, 0.45, 0.55);
    for (const auto& o : f.others)
      if (p < o.size() && std::isfinite(o[p])) dot(cr, X(o[p]), cy, 4.5);
    if (std::isfinite(v)) {
      const double x = X(v);
      cairo_set_source_rgb(cr, 0.85, 0.1, 0.1);
      cairo_move_to(cr, x, cy - 8);
      cairo_line_to(cr, x + 7, cy);
      cairo_line_to(cr, x, cy + 8);
      cairo_line_to(cr, x - 7, cy);
      cairo_close_path(cr);
      cairo_fill(cr);
    }
    cairo_set_source_rgb(cr, 0, 0, 0);
    text(cr, x1 + 70, cy + 5, std::isfinite(v) ? fmt("%.6g", v) : std::string("-"), 13);
  }
}

cairo_status_t append_bytes(void* closure, const unsigned char* data, unsigned int length) {
  static_cast<std::string*>(closure)->append(reinterpret_cast<const char*>(data), length);
  return CAIRO_STATUS_SUCCESS;
}

void check_cairo(cairo_status_t s, const char* what) {
  if (s != CAIRO_STATUS_SUCCESS)
    throw Error(ErrorCode::kInternal,
                std::string(what) + ": cairo failed: " + cairo_status_to_string(s));
}

}  // namespace

Figure coverage_figure(cv::Size image, const std::vector<KeyframeCorners>& keyframes) {
  return {"coverage", "Coverage of the image by the keyframes",
          [image, keyframes](_cairo* cr) { draw_coverage(cr, image, keyframes); }};
}

Figure residual_figure(cv::Size image, const std::vector<KeyframeCorners>& keyframes) {
  for (const KeyframeCorners& k : keyframes)
    if (k.reprojected.size() != k.observed.size())
      throw Error(ErrorCode::kInvalidArgument,
                  "residual figure: keyframe " + std::to_string(k.index) + " has " +
                      std::to_string(k.observed.size()) + " corners and " +
                      std::to_string(k.reprojected.size()) + " reprojections");
  return {"residuals", "Residual vectors per keyframe",
          [image, keyframes](_cairo* cr) { draw_residuals(cr, image, keyframes); }};
}

Figure distortion_figure(const CameraModel& model) {
  return {"distortion", "Lens distortion over the image",
          [model](_cairo* cr) { draw_distortion(cr, model); }};
}

Figure expected_error_figure(cv::Size image, const cv::Mat& map_px, double rms_px) {
  if (map_px.type() != CV_32F || map_px.rows < 2 || map_px.cols < 2)
    throw Error(ErrorCode::kInvalidArgument,
                "expected-error figure: the map must be CV_32F, 2x2 or more");
  const cv::Mat map = map_px.clone();
  return {"expected-error", "Expected projection error over the image",
          [image, map, rms_px](_cairo* cr) { draw_expected_error(cr, image, map, rms_px); }};
}

Figure sigma_figure(const std::vector<std::string>& names, const std::vector<int>& keyframe_counts,
                    const std::vector<std::vector<double>>& sigma) {
  if (sigma.size() != keyframe_counts.size())
    throw Error(ErrorCode::kInvalidArgument, "sigma figure: one row of sigma per keyframe count");
  return {"sigma", "Sigma of each parameter after each keyframe",
          [names, keyframe_counts, sigma](_cairo* cr) {
            draw_sigma(cr, names, keyframe_counts, sigma);
          }};
}

Figure fleet_figure(const FleetStrips& fleet) {
  return {"fleet", "Verdict and position in the fleet",
          [fleet](_cairo* cr) { draw_fleet(cr, fleet); }};
}

std::string figure_png(const Figure& figure) {
  std::unique_ptr<cairo_surface_t, decltype(&cairo_surface_destroy)> surface(
      cairo_image_surface_create(CAIRO_FORMAT_RGB24, kFigureWidth, kFigureHeight),
      &cairo_surface_destroy);
  check_cairo(cairo_surface_status(surface.get()), figure.id.c_str());
  cairo_t* cr = cairo_create(surface.get());
  figure.draw(cr);
  const cairo_status_t drawn = cairo_status(cr);
  cairo_destroy(cr);
  check_cairo(drawn, figure.id.c_str());
  std::string png;
  check_cairo(cairo_surface_write_to_png_stream(surface.get(), &append_bytes, &png),
              figure.id.c_str());
  return png;
}

std::string report_pdf(const std::string& title, const std::vector<std::string>& lines,
                       const std::vector<Figure>& figures) {
  std::string pdf;
  std::unique_ptr<cairo_surface_t, decltype(&cairo_surface_destroy)> surface(
      cairo_pdf_surface_create_for_stream(&append_bytes, &pdf, kW, kH), &cairo_surface_destroy);
  check_cairo(cairo_surface_status(surface.get()), "report PDF");
  cairo_pdf_surface_set_metadata(surface.get(), CAIRO_PDF_METADATA_TITLE, title.c_str());
  cairo_pdf_surface_set_metadata(surface.get(), CAIRO_PDF_METADATA_CREATOR, "posecal");
  cairo_t* cr = cairo_create(surface.get());
  // The title page.
  white_background(cr);
  cairo_set_source_rgb(cr, 0, 0, 0);
  text(cr, 50, 70, title, 26, Align::kLeft, true);
  double y = 115;
  for (const std::string& l : lines) {
    for (const std::string& w : wrap(cr, l, 14, kW - 100)) {
      if (y > kH - 30) break;
      text(cr, 50, y, w, 14);
      y += 22;
    }
  }
  cairo_show_page(cr);
  for (const Figure& f : figures) {
    cairo_save(cr);
    f.draw(cr);
    cairo_restore(cr);
    cairo_show_page(cr);
  }
  const cairo_status_t drawn = cairo_status(cr);
  cairo_destroy(cr);
  cairo_surface_finish(surface.get());
  check_cairo(drawn, "report PDF");
  check_cairo(cairo_surface_status(surface.get()), "report PDF");
  return pdf;
}

std::string base64_encode(const std::string& bytes) {
  static const char* const kAlphabet =
      "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
  std::string out;
  out.reserve((bytes.size() + 2) / 3 * 4);
  size_t i = 0;
  for (; i + 2 < bytes.size(); i += 3) {
    const uint32_t v = (uint32_t(uint8_t(bytes[i])) << 16) |
                       (uint32_t(uint8_t(bytes[i + 1])) << 8) | uint8_t(bytes[i + 2]);
    out += kAlphabet[v >> 18];
    out += kAlphabet[(v >> 12) & 63];
    out += kAlphabet[(v >> 6) & 63];
    out += kAlphabet[v & 63];
  }
  if (i < bytes.size()) {
    uint32_t v = uint32_t(uint8_t(bytes[i])) << 16;
    if (i + 1 < bytes.size()) v |= uint32_t(uint8_t(bytes[i + 1])) << 8;
    out += kAlphabet[v >> 18];
    out += kAlphabet[(v >> 12) & 63];
    out += i + 1 < bytes.size() ? kAlphabet[(v >> 6) & 63] : '=';
    out += '=';
  }
  return out;
}

}  // namespace posecal
