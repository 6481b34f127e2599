// The operator view (issue 18, item 1): what the CLI window, render_overlay and the web view
// show over the camera image. The target board drawn with the current intrinsics and
// distortion; the detected corners; an arrow from where the board is to where it should go and
// a distance gauge; a panel in plain words (what is happening, what to do, keyframes and the
// expected error); a chip per parameter (converged, being improved, open); a green frame when a
// keyframe is captured; and when the calibration has finished, the result panel with the
// keyframes' coverage of the image. Every size scales with the image (1280 px wide: 1).
#include <algorithm>
#include <cctype>
#include <cmath>
#include <cstdio>
#include <opencv2/imgproc.hpp>

#include "common/error.hpp"
#include "select/engine_internal.hpp"

namespace posecal {

namespace {

const cv::Scalar kPanel(30, 30, 30);
const cv::Scalar kWhite(255, 255, 255);
const cv::Scalar kYellow(0, 230, 255);
const cv::Scalar kGreen(60, 200, 60);
const cv::Scalar kOrange(0, 150, 255);
const cv::Scalar kGrey(140, 140, 140);
const cv::Scalar kTarget(255, 160, 0);  // the target board (blue in BGR)

// A grey image gets the grey level of a colour (its luma).
cv::Scalar ink(const cv::Mat& image, const cv::Scalar& bgr) {
  if (image.channels() == 3) return bgr;
  return cv::Scalar(0.114 * bgr[0] + 0.587 * bgr[1] + 0.299 * bgr[2]);
}

// A dark translucent box behind text.
void backing(cv::Mat& image, cv::Rect r, double alpha = 0.6) {
  r &= cv::Rect(0, 0, image.cols, image.rows);
  if (r.area() <= 0) return;
  cv::Mat roi = image(r);
  cv::Mat dark(roi.size(), roi.type(), ink(image, kPanel));
  cv::addWeighted(dark, alpha, roi, 1 - alpha, 0, roi);
}

struct Line {
  std::string text;
  double size;  // font scale at 1280 px
  cv::Scalar colour;
};

// Lines of text on one backing box at `origin` (top left); returns the box.
cv::Rect text_panel(cv::Mat& image, const std::vector<Line>& lines, cv::Point origin, double k) {
  const int pad = static_cast<int>(std::lround(10 * k));
  int width = 0, height = pad;
  std::vector<cv::Size> sizes;
  std::vector<int> bases;
  for (const Line& l : lines) {
    int base = 0;
    const int thick = std::max(1, static_cast<int>(std::lround(2 * k * l.size)));
    sizes.push_back(cv::getTextSize(l.text, cv::FONT_HERSHEY_SIMPLEX, l.size * k, thick, &base));
    bases.push_back(base);
    width = std::max(width, sizes.back().width);
    height += sizes.back().height + base + pad / 2;
  }
  const cv::Rect box(origin.x, origin.y, width + 2 * pad, height + pad / 2);
  backing(image, box);
  int y = origin.y + pad;
  for (size_t i = 0; i < lines.size(); ++i) {
    y += sizes[i].height;
    const int thick = std::max(1, static_cast<int>(std::lround(2 * k * lines[i].size)));
    cv::putText(image, lines[i].text, cv::Point(origin.x + pad, y), cv::FONT_HERSHEY_SIMPLEX,
                lines[i].size * k, ink(image, lines[i].colour), thick, cv::LINE_AA);
    y += bases[i] + pad / 2;
  }
  return box;
}

// What a parameter is, in words an operator knows.
std::string plain_name(const std::string& p) {
  if (p == "fx" || p == "fy") return "focal length (" + p + ")";
  if (p == "cx" || p == "cy") return "image centre (" + p + ")";
  if (p == "p1" || p == "p2") return "decentring (" + p + ")";
  return "lens distortion (" + p + ")";
}

std::string headline(EngineState state, const std::string& target_parameter) {
  switch (state) {
    case EngineState::kWaitingForBoard:
      return "Show the board";
    case EngineState::kBootstrapping:
      return "Getting started: a first view of the board";
    case EngineState::kInitialPose1:
      return "Start pose 1 of 2";
    case EngineState::kInitialPose2:
      return "Start pose 2 of 2";
    case EngineState::kRefining:
      return target_parameter.empty() ? "Refining"
                                      : "Improving the " + plain_name(target_parameter);
    case EngineState::kConverged:
      return "Calibration converged";
    case EngineState::kFailed:
      return "Calibration stopped";
  }
  return "";
}

std::string number(const char* format, double v) {
  char buf[64];
  std::snprintf(buf, sizeof buf, format, v);
  return buf;
}

cv::Point pixel(const cv::Point2d& p) { return {cvRound(p.x), cvRound(p.y)}; }

}  // namespace

void CalibrationEngine::draw_overlay(cv::Mat& image) const {
  const Impl& s = *impl_;
  if (image.empty() || image.depth() != CV_8U || (image.channels() != 1 && image.channels() != 3)) {
    throw Error(ErrorCode::kInvalidArgument, "overlay: image must be 8-bit grey or BGR");
  }
  if (image.size() != s.size) {
    throw Error(ErrorCode::kInvalidArgument, "overlay: image size differs from the camera's");
  }
  const double k = std::max(0.4, s.size.width / 1280.0);
  const auto thick = [&](double t) { return std::max(1, static_cast<int>(std::lround(t * k))); };
  const bool finished = s.state == EngineState::kConverged || s.state == EngineState::kFailed;

  // The target board, projected with the current intrinsics and distortion: a translucent sheet
  // plus its square grid (lines sampled densely so distortion bends them).
  if (s.target && !finished) {
    const auto outline = projected_outline(s.estimate, s.board, s.target->T_cam_board, 24);
    if (!outline.empty()) {
      std::vector<cv::Point> poly;
      for (const auto& p : outline) poly.push_back(pixel(p));
      cv::Mat layer = image.clone();
      cv::fillPoly(layer, std::vector<std::vector<cv::Point>>{poly}, ink(image, kTarget),
                   cv::LINE_AA);
      cv::addWeighted(layer, 0.35, image, 0.65, 0, image);
      const cv::Size2d bs = s.board.board_size_m();
      const double sq = s.board.spec().square_length_m;
      const int nx = static_cast<int>(std::lround(bs.width / sq));
      const int ny = static_cast<int>(std::lround(bs.height / sq));
      auto line3d = [&](cv::Point3d a, cv::Point3d b) {
        std::vector<cv::Point3d> pts;
        for (int i = 0; i <= 16; ++i) pts.push_back(a + (b - a) * (i / 16.0));
        std::vector<cv::Point> pl;
        for (const auto& p : project_points(s.estimate, s.target->T_cam_board, pts))
          if (std::isfinite(p.x) && std::isfinite(p.y)) pl.push_back(pixel(p));
        if (pl.size() > 1) {
          cv::polylines(image, std::vector<std::vector<cv::Point>>{pl}, false, ink(image, kTarget),
                        1, cv::LINE_AA);
        }
      };
      for (int i = 0; i <= nx; ++i) line3d({i * sq, 0, 0}, {i * sq, bs.height, 0});
      for (int j = 0; j <= ny; ++j) line3d({0, j * sq, 0}, {bs.width, j * sq, 0});
    }
  }

  // The result: every keyframe's board (its corners' hull), so the coverage of the image shows.
  if (finished) {
    for (const Observation& o : s.keyframes) {
      std::vector<cv::Point> pts, hull;
      for (const auto& p : o.image_points) pts.push_back(pixel(p));
      if (pts.size() < 3) continue;
      cv::convexHull(pts, hull);
      cv::polylines(image, std::vector<std::vector<cv::Point>>{hull}, true, ink(image, kWhite),
                    thick(2), cv::LINE_AA);
    }
  }

  for (const auto& p : s.previous.image_points)
    cv::circle(image, pixel(p), thick(3), ink(image, kGreen), 1, cv::LINE_AA);

  // Where the board should go: the detected corners against the same corners on the target.
  // An arrow from their centre to the target's when it is off by more than the guidance's
  // tolerance, and a gauge of the board's size against the target's (distance).
  if (s.target && !finished && !s.previous.empty() && !s.opt.robot) {
    const auto want = project_points(s.estimate, s.target->T_cam_board, s.previous.board_points);
    std::vector<cv::Point2f> a, b;
    for (size_t i = 0; i < want.size(); ++i) {
      if (!std::isfinite(want[i].x) || !std::isfinite(want[i].y)) continue;
      a.emplace_back(s.previous.image_points[i]);
      b.emplace_back(want[i]);
    }
    if (a.size() >= 4) {
      cv::Point2d ca(0, 0), cb(0, 0);
      for (size_t i = 0; i < a.size(); ++i) {
        ca += cv::Point2d(a[i]);
        cb += cv::Point2d(b[i]);
      }
      ca /= static_cast<double>(a.size());
      cb /= static_cast<double>(b.size());
      const double tol = 0.04 * std::max(s.size.width, s.size.height);
      if (cv::norm(cb - ca) > tol) {
        cv::arrowedLine(image, pixel(ca), pixel(cb), ink(image, kOrange), thick(6), cv::LINE_AA, 0,
                        std::min(0.3, 40 * k / cv::norm(cb - ca)));
      }
      std::vector<cv::Point2f> ha, hb;
      cv::convexHull(a, ha);
      cv::convexHull(b, hb);
      const double area_a = cv::contourArea(ha), area_b = cv::contourArea(hb);
      if (area_a > 0 && area_b > 0) {
        // log2 of the size ratio over [-1, 1]: half (far away) to twice (too close) the target.
        const double r = std::clamp(0.5 * std::log2(area_a / area_b), -1.0, 1.0);
        const int h = static_cast<int>(240 * k), w = static_cast<int>(22 * k);
        const int x = s.size.width - w - static_cast<int>(24 * k);
        const int y0 = (s.size.height - h) / 2;
        backing(image, cv::Rect(x - thick(6), y0 - thick(30), w + thick(12), h + thick(60)), 0.5);
        cv::rectangle(image, cv::Rect(x, y0, w, h), ink(image, kGrey), 1);
        const double zone = std::log2(1.07);  // the guidance's "closer" / "further" bounds
        const int zy = static_cast<int>(h / 2 * (1 - zone)), zh = static_cast<int>(h * zone);
        cv::rectangle(image, cv::Rect(x + 1, y0 + zy, w - 2, std::max(2, zh)), ink(image, kGreen),
                      cv::FILLED);
        const int my = y0 + static_cast<int>(h / 2.0 * (1 - r));
        cv::line(image, {x - thick(6), my}, {x + w + thick(6), my}, ink(image, kYellow), thick(4));
        cv::putText(image, "near", {x - thick(8), y0 - thick(10)}, cv::FONT_HERSHEY_SIMPLEX,
                    0.5 * k, ink(image, kWhite), thick(1), cv::LINE_AA);
        cv::putText(image, "far", {x - thick(2), y0 + h + thick(22)}, cv::FONT_HERSHEY_SIMPLEX,
                    0.5 * k, ink(image, kWhite), thick(1), cv::LINE_AA);
      }
    }
  }

  // A keyframe captured: a green frame round the image.
  if (s.last.captured && !finished) {
    cv::rectangle(image, cv::Rect(0, 0, s.size.width, s.size.height), ink(image, kGreen),
                  thick(14));
  }

  // The panel: what is happening, what to do, the progress.
  const int margin = static_cast<int>(std::lround(12 * k));
  std::string progress =
      std::to_string(s.keyframes.size()) + (s.keyframes.size() == 1 ? " keyframe" : " keyframes");
  if (s.expected && std::isfinite(s.expected->rms_px)) {
    progress += number(", expected error %.2f px", s.expected->rms_px);
    if (std::isfinite(s.expected->p90_px))
      progress += number(" (9 in 10 within %.2f px)", s.expected->p90_px);
  }
  if (s.opt.accuracy_px) progress += number(", goal %.2f px", *s.opt.accuracy_px);
  if (!finished) {
    std::vector<Line> lines = {{headline(s.state, s.last.target_parameter), 0.8, kWhite}};
    if (!s.last.guidance.empty()) {
      std::string g = s.last.guidance;
      if (!g.empty()) g[0] = static_cast<char>(std::toupper(static_cast<unsigned char>(g[0])));
      lines.push_back({g, 1.1, s.last.captured ? kGreen : kYellow});
    }
    lines.push_back({progress, 0.6, kWhite});
    text_panel(image, lines, {margin, margin}, k);
  } else {
    std::vector<Line> lines = {{headline(s.state, s.last.target_parameter), 1.2,
                                s.state == EngineState::kConverged ? kGreen : kOrange}};
    if (s.state == EngineState::kFailed && !s.failure.empty())
      lines.push_back({s.failure, 0.6, kWhite});
    lines.push_back({progress, 0.7, kWhite});
    lines.push_back({"White: the boards of the keyframes (coverage of the image)", 0.55, kWhite});
    text_panel(image, lines, {margin, margin}, k);
  }

  // A chip per parameter: green converged, orange being improved, grey still open; fixed ones
  // are not shown.
  const auto names = s.estimate.param_names();
  const std::vector<bool>* fixed = s.result ? &s.result->fixed : nullptr;
  int x = margin;
  const int chip_h = static_cast<int>(std::lround(30 * k));
  const int y = s.size.height - margin - chip_h;
  std::vector<std::pair<std::string, cv::Scalar>> chips;
  for (size_t i = 0; i < names.size() && i < s.param_converged.size(); ++i) {
    if (fixed && i < fixed->size() && (*fixed)[i]) continue;
    const bool target = s.state == EngineState::kRefining && static_cast<int>(i) == s.target_param;
    chips.emplace_back(names[i], s.param_converged[i] ? kGreen : target ? kOrange : kGrey);
  }
  if (!chips.empty()) {
    int base = 0;
    const cv::Size t = cv::getTextSize("fx", cv::FONT_HERSHEY_SIMPLEX, 0.6 * k, thick(2), &base);
    const int chip_w = t.width + static_cast<int>(24 * k);
    const int gap = static_cast<int>(6 * k);
    backing(image, cv::Rect(x - gap, y - gap, static_cast<int>(chips.size()) * (chip_w + gap) + gap,
                            chip_h + 2 * gap));
    for (const auto& [name, colour] : chips) {
      cv::rectangle(image, cv::Rect(x, y, chip_w, chip_h), ink(image, colour), cv::FILLED);
      cv::putText(image, name, {x + static_cast<int>(12 * k), y + (chip_h + t.height) / 2},
                  cv::FONT_HERSHEY_SIMPLEX, 0.6 * k, ink(image, kWhite), thick(2), cv::LINE_AA);
      x += chip_w + gap;
    }
  }
}

}  // namespace posecal
