// The pictures of a calibration report (issue 15, item 5; `posecal report`): pure functions from
// data to a Figure, a drawing that renders to a PNG or to a page of a PDF, drawn with cairo.
// Nothing here reads a record or solves anything: the caller (plugin/src/report_abi.cpp) hands
// in the keyframes' corners, the reprojections, the σ after each keyframe, the fleet's values.
//
// Every figure is kFigureWidth x kFigureHeight units (pixels in a PNG, points on a PDF page),
// with a title, axes with their units and a legend or colour bar where colours carry meaning.
#pragma once

#include <functional>
#include <opencv2/core.hpp>
#include <string>
#include <vector>

#include "lens/camera_model.hpp"

struct _cairo;  // cairo_t, without cairo.h in a public header

namespace posecal {

inline constexpr int kFigureWidth = 1000;
inline constexpr int kFigureHeight = 700;

struct Figure {
  std::string id;     // stable, e.g. "coverage" (the HTML's <img id="plot-coverage">)
  std::string title;  // what the figure shows, one line
  std::function<void(_cairo*)> draw;  // draws into a kFigureWidth x kFigureHeight area
};

// One keyframe's corners: where they were detected and, for the residuals, where the final
// calibration and the keyframe's pose reproject them (same order; empty for the coverage).
struct KeyframeCorners {
  int index = 0;  // 1-based, as the record numbers keyframes
  std::vector<cv::Point2d> observed;
  std::vector<cv::Point2d> reprojected;
};

// The image rectangle, each keyframe's board outline (the convex hull of its corners) and its
// corners, one colour per keyframe, numbered.
Figure coverage_figure(cv::Size image, const std::vector<KeyframeCorners>& keyframes);

// Residual vectors observed - reprojected per keyframe, scaled up (the scale is on the plot),
// and the RMS per keyframe beside it. Throws Error(kInvalidArgument) if a keyframe's
// reprojections do not match its corners.
Figure residual_figure(cv::Size image, const std::vector<KeyframeCorners>& keyframes);

// The lens distortion's displacement over the image: its magnitude in px as a colour map with a
// colour bar, and arrows on a grid from where a pinhole camera would see a ray to where the lens
// puts it (scaled, the scale on the plot).
Figure distortion_figure(const CameraModel& model);

// A map of the expected projection error (expected_error_map: rows x cols CV_32F, px, NaN where
// the ray does not exist, grid edge to edge over `image`) as a colour map with a colour bar.
// `rms_px` is the figure the map's RMS gives (printed on the plot).
Figure expected_error_figure(cv::Size image, const cv::Mat& map_px, double rms_px);

// σ of each intrinsic after each keyframe, log scale: keyframe_counts[i] keyframes gave
// sigma[i][p] for parameter p (NaN: no solution for that prefix, or the parameter is fixed).
Figure sigma_figure(const std::vector<std::string>& names, const std::vector<int>& keyframe_counts,
                    const std::vector<std::vector<double>>& sigma);

// The verdict with its reasons, and where this unit's intrinsics lie among other units of the
// same camera model and lens: one strip per parameter from the lowest to the highest value of
// all units, the others grey, this one highlighted ("no other units" when `others` is empty).
struct FleetStrips {
  std::string verdict;               // "pass", "fail" or "" (no quality specification)
  std::vector<std::string> reasons;  // why it failed
  std::string group;                 // e.g. "camera model C525, lens id 3.6mm"
  std::vector<std::string> names;
  std::vector<double> unit;                 // this unit's intrinsics (names' order)
  std::vector<std::vector<double>> others;  // each other unit's
  // The outlier test's line (records/fleet.hpp: distance, bound, parameters responsible), or
  // why there is none; "" to leave it out.
  std::string position;
};
Figure fleet_figure(const FleetStrips& fleet);

// The figure as PNG bytes (cairo's image surface and PNG writer). Throws Error(kInternal) naming
// cairo's status if cairo fails.
std::string figure_png(const Figure& figure);

// A PDF: a title page (`title`, then `lines`, one a line, long ones wrapped) and one page per
// figure, each with its title. Throws Error(kInternal) naming cairo's status if cairo fails.
std::string report_pdf(const std::string& title, const std::vector<std::string>& lines,
                       const std::vector<Figure>& figures);

// RFC 4648 base64 (for data: URIs).
std::string base64_encode(const std::string& bytes);

}  // namespace posecal
