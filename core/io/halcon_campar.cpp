// HALCON's internal camera parameters for an area-scan camera with the polynomial distortion
// model (area_scan_polynomial), in the layout of a camera-parameter file (docs/formats.md).
//
// HALCON's polynomial works in the opposite direction to OpenCV's: it maps distorted image-plane
// coordinates (metres on the sensor) to undistorted ones, while posecal's opencv5 maps undistorted
// normalised coordinates to distorted ones. Both are the same Brown-Conrady polynomial form, but
// one is not the exact inverse of the other, so each conversion is a least-squares fit over the
// image, and is refused when its worst error over the image exceeds kMaxFitErrorPx.
#include <Eigen/Dense>
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <map>

#include "common/error.hpp"
#include "io/model_file_internal.hpp"

namespace posecal::model_io {

namespace {

// posecal does not know the sensor's pixel pitch: HALCON's projection depends only on Focus/Sx
// and Focus/Sy, and the coefficients are given for this Sx (scaling Sx by s scales K1 by 1/s^2,
// K2 by 1/s^4, K3 by 1/s^6, P1 and P2 by 1/s).
constexpr double kPixelSizeM = 5e-6;
// The largest difference between the two models' projections, anywhere in the image, that a
// conversion may leave. A fifth-order polynomial in one direction is not the exact inverse of
// one in the other (docs/formats.md has what it leaves on a few lenses). 0.1 px is below the
// expected error of a typical calibration (0.1-0.4 px) and keeps wide-angle lenses out; the
// file's second comment line states the difference of each conversion.
constexpr double kMaxFitErrorPx = 0.1;
// The fit samples 65 x 49 pixels edge to edge; the check 129 x 97.
constexpr int kFitCols = 64, kFitRows = 48, kCheckCols = 128, kCheckRows = 96;

// out = in (1 + a1 r^2 + a2 r^4 + a3 r^6) + (tx (r^2 + 2 x^2) + 2 ty x y,
//                                           ty (r^2 + 2 y^2) + 2 tx x y).
// HALCON's undistortion is this with (a, tx, ty) = (K1 K2 K3, P1, P2), in metres; OpenCV's
// distortion with (k1 k2 k3, p2, p1), in normalised coordinates.
struct Brown {
  double a1 = 0, a2 = 0, a3 = 0, tx = 0, ty = 0;
};

Eigen::Vector2d apply(const Brown& b, const Eigen::Vector2d& q) {
  const double x = q.x(), y = q.y(), r2 = x * x + y * y;
  const double radial = 1 + r2 * (b.a1 + r2 * (b.a2 + r2 * b.a3));
  return {x * radial + b.tx * (r2 + 2 * x * x) + 2 * b.ty * x * y,
          y * radial + b.ty * (r2 + 2 * y * y) + 2 * b.tx * x * y};
}

// The coefficients with apply(b, in[i]) closest to out[i], residuals weighted by `scale` (to
// pixels): least squares (the coefficients enter linearly; columns normalised for the solve, as
// r^6 is 1e-18 in metres), then Lawson's reweighting towards the smallest worst residual, the
// figure the conversion is judged by (it halves it: 0.29 -> 0.15 px for posecal's C525
// reference).
Brown fit(const std::vector<Eigen::Vector2d>& in, const std::vector<Eigen::Vector2d>& out,
          const Eigen::Vector2d& scale) {
  constexpr int kReweightings = 8;
  const Eigen::Index n = static_cast<Eigen::Index>(in.size());
  Eigen::MatrixXd A0(2 * n, 5);
  Eigen::VectorXd rhs0(2 * n);
  for (Eigen::Index i = 0; i < n; ++i) {
    const double x = in[i].x(), y = in[i].y(), r2 = x * x + y * y;
    A0.row(2 * i) << x * r2, x * r2 * r2, x * r2 * r2 * r2, r2 + 2 * x * x, 2 * x * y;
    A0.row(2 * i + 1) << y * r2, y * r2 * r2, y * r2 * r2 * r2, 2 * x * y, r2 + 2 * y * y;
    A0.row(2 * i) *= scale.x();
    A0.row(2 * i + 1) *= scale.y();
    rhs0(2 * i) = (out[i].x() - x) * scale.x();
    rhs0(2 * i + 1) = (out[i].y() - y) * scale.y();
  }
  Eigen::VectorXd weight = Eigen::VectorXd::Ones(n);
  Eigen::VectorXd z;
  for (int round = 0; round <= kReweightings; ++round) {
    Eigen::MatrixXd A = A0;
    Eigen::VectorXd rhs = rhs0;
    for (Eigen::Index i = 0; i < n; ++i) {
      A.middleRows(2 * i, 2) *= weight(i);
      rhs.segment(2 * i, 2) *= weight(i);
    }
    Eigen::VectorXd norms = A.colwise().norm().transpose();
    for (Eigen::Index c = 0; c < 5; ++c) {
      if (norms(c) == 0) norms(c) = 1;
      A.col(c) /= norms(c);
    }
    z = A.colPivHouseholderQr().solve(rhs).cwiseQuotient(norms);
    const Eigen::VectorXd residual = A0 * z - rhs0;
    for (Eigen::Index i = 0; i < n; ++i) {
      weight(i) *= std::sqrt(residual.segment(2 * i, 2).norm() + 1e-12);
    }
    weight *= static_cast<double>(n) / weight.sum();
  }
  return {z(0), z(1), z(2), z(3), z(4)};
}

struct HalconParams {
  double focus = 0, sx = 0, sy = 0, cx = 0, cy = 0;
  Brown poly;  // K1 K2 K3 P1 P2
  int width = 0, height = 0;

  // Pixel (column, row) -> the ray (x, y, 1) HALCON's model gives it.
  Eigen::Vector2d ray(const Eigen::Vector2d& px) const {
    return apply(poly, {(px.x() - cx) * sx, (px.y() - cy) * sy}) / focus;
  }
};

// Pixels (i (W-1)/cols, j (H-1)/rows), edge to edge.
std::vector<Eigen::Vector2d> grid(int width, int height, int cols, int rows) {
  std::vector<Eigen::Vector2d> g;
  for (int j = 0; j <= rows; ++j) {
    for (int i = 0; i <= cols; ++i) {
      g.emplace_back((width - 1) * static_cast<double>(i) / cols,
                     (height - 1) * static_cast<double>(j) / rows);
    }
  }
  return g;
}

// The largest distance between a pixel and posecal's projection of HALCON's ray through it, over
// the check grid (infinity where a ray does not project).
double worst_error_px(const CameraModel& model, const HalconParams& h) {
  double worst = 0;
  for (const Eigen::Vector2d& px : grid(h.width, h.height, kCheckCols, kCheckRows)) {
    const Eigen::Vector2d r = h.ray(px);
    Eigen::Vector2d uv;
    if (!model.project(Eigen::Vector3d(r.x(), r.y(), 1), &uv) || !uv.allFinite()) return INFINITY;
    worst = std::max(worst, (uv - px).norm());
  }
  return worst;
}

std::string fit_text(double px) {
  char buf[64];
  std::snprintf(buf, sizeof buf, "%.3g px", px);
  return buf;
}

std::string entry(const char* name, const char* abbr, const std::string& value, const char* type,
                  const char* description) {
  return std::string(name) + ":" + abbr + ":\t" + value + ";\n\t" + type + ";\n\t\"" + description +
         "\";\n\n";
}

// The camera-parameter file as statements ending in ';' ('#' lines are comments): "ParGroup:
// Camera: Parameter;" and its description, then per parameter "Name:abbr: value;", its type
// ("DOUBLE:min:max;", "INT:min:max;") and its description ("\"...\";").
std::map<std::string, std::pair<std::string, int>> parameters(const std::string& path,
                                                              std::string_view text) {
  std::vector<std::pair<std::string, int>> statements;  // text, line
  std::string current;
  int line = 1, start_line = 1;
  bool quoted = false, comment = false, line_start = true, blank = true;  // blank: `current`
  for (const char c : text) {
    if (c == '\n') {
      ++line, comment = false, line_start = true;
      if (quoted)
        bad_file(path, "line " + std::to_string(line - 1) + ": a string runs over the line's end");
      current.push_back(' ');
      continue;
    }
    if (comment) continue;
    const auto u = static_cast<unsigned char>(c);
    if (u < 0x20 && c != '\t' && c != '\r') {
      bad_file(path, "line " + std::to_string(line) + ": a control character");
    }
    if (line_start && c == '#' && !quoted) {
      comment = true;
      continue;
    }
    const bool space = c == ' ' || c == '\t' || c == '\r';
    if (!space) line_start = false;
    if (blank && !space) start_line = line, blank = false;
    if (c == '"') quoted = !quoted;
    if (c == ';' && !quoted) {
      statements.emplace_back(current, start_line);
      current.clear();
      blank = true;
      continue;
    }
    current.push_back(c);
  }
  if (!blank) {
    bad_file(path,
             "line " + std::to_string(start_line) + ": a statement without its ';' (cut short?)");
  }
  const auto trim = [](std::string s) {
    const size_t a = s.find_first_not_of(" \t\r"), b = s.find_last_not_of(" \t\r");
    return a == std::string::npos ? std::string() : s.substr(a, b - a + 1);
  };
  const auto where = [&](int l) { return "line " + std::to_string(l) + ": "; };
  std::map<std::string, std::pair<std::string, int>> out;
  const auto description = [&](size_t k, const std::string& of) {
    if (k >= statements.size() || trim(statements[k].first).rfind('"', 0) != 0) {
      bad_file(path, where(k < statements.size() ? statements[k].second : line) + of +
                         " has no description \"...\" (cut short?)");
    }
  };
  if (statements.empty() || trim(statements[0].first) != "ParGroup: Camera: Parameter") {
    bad_file(path,
             "not a HALCON camera-parameter file (it starts with 'ParGroup: Camera: Parameter;')");
  }
  description(1, "ParGroup");
  for (size_t i = 2; i < statements.size(); i += 3) {
    const std::string s = trim(statements[i].first);
    const int l = statements[i].second;
    const size_t c1 = s.find(':'), c2 = c1 == std::string::npos ? c1 : s.find(':', c1 + 1);
    if (c2 == std::string::npos) bad_file(path, where(l) + "expected 'Name:abbr: value'");
    const std::string name = s.substr(0, c1);
    if (out.count(name)) bad_file(path, where(l) + "parameter '" + name + "' appears twice");
    out[name] = {trim(s.substr(c2 + 1)), l};
    if (i + 1 >= statements.size()) {
      bad_file(path, where(l) + "parameter '" + name + "' has no type (cut short?)");
    }
    const std::string type = trim(statements[i + 1].first);
    if (type.rfind("DOUBLE", 0) != 0 && type.rfind("INT", 0) != 0 && type.rfind("STRING", 0) != 0) {
      bad_file(path, where(statements[i + 1].second) + "parameter '" + name +
                         "' has no type (DOUBLE, INT or STRING)");
    }
    description(i + 2, "parameter '" + name + "'");
  }
  return out;
}

}  // namespace

std::string compose_halcon(const std::string& path, const CameraModel& model) {
  const std::vector<double> d = model.distortion_coefficients();
  if (model.lens_model() != LensModel::kOpenCV5)
    cannot_hold(path, ModelFormat::kHalcon, model, "is not OpenCV's 5-coefficient model");
  HalconParams h;
  h.sx = kPixelSizeM;
  h.focus = model.fx() * h.sx;
  h.sy = h.focus / model.fy();
  h.cx = model.cx();
  h.cy = model.cy();
  h.width = model.width();
  h.height = model.height();
  std::vector<Eigen::Vector2d> in, out;
  for (const Eigen::Vector2d& px : grid(h.width, h.height, kFitCols, kFitRows)) {
    Eigen::Vector2d xn;
    if (!model.unproject(px, &xn)) {
      cannot_hold(path, ModelFormat::kHalcon, model,
                  "has no ray at pixel (" + number_text(px.x()) + ", " + number_text(px.y()) + ")");
    }
    in.emplace_back((px.x() - h.cx) * h.sx, (px.y() - h.cy) * h.sy);
    out.push_back(xn * h.focus);
  }
  h.poly = fit(in, out, {1 / h.sx, 1 / h.sy});
  const double worst = worst_error_px(model, h);
  if (!(worst <= kMaxFitErrorPx)) {
    cannot_hold(path, ModelFormat::kHalcon, model,
                "fits HALCON's polynomial only to " + fit_text(worst) +
                    " at the worst pixel; the limit is " + fit_text(kMaxFitErrorPx));
  }
  return "# INTERNAL CAMERA PARAMETERS\n# area_scan_polynomial, fitted by posecal to its lens "
         "model " +
         std::string(lens_model_name(model.lens_model())) + ": worst difference " +
         fit_text(worst) +
         " over the image\n\nParGroup: Camera: Parameter;\n\t\"Internal camera "
         "parameters\";\n\n" +
         entry("Focus", "foc", number_text(h.focus), "DOUBLE:0.0:", "Focal length of the lens") +
         entry("Poly1", "poly1", number_text(h.poly.a1),
               "DOUBLE::", "1st polynomial distortion coefficient") +
         entry("Poly2", "poly2", number_text(h.poly.a2),
               "DOUBLE::", "2nd polynomial distortion coefficient") +
         entry("Poly3", "poly3", number_text(h.poly.a3),
               "DOUBLE::", "3rd polynomial distortion coefficient") +
         entry("Poly4", "poly4", number_text(h.poly.tx),
               "DOUBLE::", "4th polynomial distortion coefficient") +
         entry("Poly5", "poly5", number_text(h.poly.ty),
               "DOUBLE::", "5th polynomial distortion coefficient") +
         entry("Sx", "sx", number_text(h.sx), "DOUBLE:0.0:", "Width of a cell on the sensor") +
         entry("Sy", "sy", number_text(h.sy), "DOUBLE:0.0:", "Height of a cell on the sensor") +
         entry("Cx", "cx", number_text(h.cx), "DOUBLE::", "X-coordinate of the image center") +
         entry("Cy", "cy", number_text(h.cy), "DOUBLE::", "Y-coordinate of the image center") +
         entry("ImageWidth", "imgw", std::to_string(h.width), "INT:1:32768",
               "Width of the images") +
         entry("ImageHeight", "imgh", std::to_string(h.height), "INT:1:32768",
               "Height of the images");
}

ModelFile parse_halcon(const std::string& path, std::string_view text) {
  const auto params = parameters(path, text);
  static const std::vector<std::string> kNames = {"Focus", "Poly1", "Poly2",      "Poly3",
                                                  "Poly4", "Poly5", "Sx",         "Sy",
                                                  "Cx",    "Cy",    "ImageWidth", "ImageHeight"};
  for (const auto& [name, value] : params) {
    if (name == "Camera") {  // "Camera:Type: \"area_scan_polynomial\";" in newer files
      if (value.first != "\"area_scan_polynomial\"") {
        bad_file(path, "line " + std::to_string(value.second) + ": camera type " + value.first +
                           " is not read: posecal reads area_scan_polynomial");
      }
      continue;
    }
    if (name == "Kappa") {
      bad_file(path,
               "line " + std::to_string(value.second) +
                   ": 'Kappa' is HALCON's division model; posecal reads the polynomial model");
    }
    if (std::find(kNames.begin(), kNames.end(), name) == kNames.end()) {
      bad_file(path, "line " + std::to_string(value.second) + ": unknown parameter '" + name + "'");
    }
  }
  const Fields f(path);
  const auto node = [&](const std::string& name) {
    const auto it = params.find(name);
    if (it == params.end()) bad_file(path, "has no parameter '" + name + "'");
    TextNode n;
    n.scalar = it->second.first;
    n.line = it->second.second;
    return n;
  };
  const auto number = [&](const std::string& name) {
    return f.number(node(name), "'" + name + "'");
  };
  const auto integer = [&](const std::string& name) {
    return f.integer(node(name), "'" + name + "'", 1, CameraModel::kMaxImageSide);
  };
  HalconParams h;
  h.focus = number("Focus");
  h.poly = {number("Poly1"), number("Poly2"), number("Poly3"), number("Poly4"), number("Poly5")};
  h.sx = number("Sx");
  h.sy = number("Sy");
  h.cx = number("Cx");
  h.cy = number("Cy");
  h.width = integer("ImageWidth");
  h.height = integer("ImageHeight");
  for (const auto& [name, v] :
       {std::pair<const char*, double>{"Focus", h.focus}, {"Sx", h.sx}, {"Sy", h.sy}}) {
    if (!(v > 0)) bad_file(path, std::string("'") + name + "' must be positive");
  }
  const double fx = h.focus / h.sx, fy = h.focus / h.sy;
  std::vector<Eigen::Vector2d> in, out;
  for (const Eigen::Vector2d& px : grid(h.width, h.height, kFitCols, kFitRows)) {
    in.push_back(h.ray(px));
    out.emplace_back((px.x() - h.cx) / fx, (px.y() - h.cy) / fy);
  }
  const Brown b = fit(in, out, {fx, fy});
  ModelFile file;
  file.format = ModelFormat::kHalcon;
  file.model = model_from_opencv(path, h.width, h.height, {fx, 0, h.cx, 0, fy, h.cy, 0, 0, 1},
                                 {b.a1, b.a2, b.ty, b.tx, b.a3}, "the polynomial");
  const double worst = worst_error_px(file.model, h);
  if (!(worst <= kMaxFitErrorPx)) {
    bad_file(path, "HALCON's polynomial fits posecal's lens model " +
                       std::string(lens_model_name(file.model.lens_model())) + " only to " +
                       fit_text(worst) + " at the worst pixel; the limit is " +
                       fit_text(kMaxFitErrorPx));
  }
  return file;
}

}  // namespace posecal::model_io
