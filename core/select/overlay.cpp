// The guidance overlay: the target board drawn over the camera image with the current intrinsics
// and distortion, the detected corners and the guidance text.
#include <cmath>
#include <opencv2/imgproc.hpp>

#include "common/error.hpp"
#include "select/engine_internal.hpp"

namespace posecal {

void CalibrationEngine::draw_overlay(cv::Mat& image) const {
  const Impl& s = *impl_;
  if (image.empty() || image.depth() != CV_8U || (image.channels() != 1 && image.channels() != 3)) {
    throw Error(ErrorCode::kInvalidArgument, "overlay: image must be 8-bit grey or BGR");
  }
  if (image.size() != s.size) throw Error(ErrorCode::kInvalidArgument, "overlay: image size differs from the camera's");
  const bool color = image.channels() == 3;
  const cv::Scalar target_col = color ? cv::Scalar(255, 160, 0) : cv::Scalar(255);
  const cv::Scalar corner_col = color ? cv::Scalar(0, 220, 0) : cv::Scalar(0);
  const cv::Scalar text_col = color ? cv::Scalar(0, 255, 255) : cv::Scalar(255);
  if (s.target) {
    // The target board, projected with the current intrinsics and distortion: a translucent
    // sheet plus its square grid (lines sampled densely so distortion bends them).
    const auto outline = projected_outline(s.estimate, s.board, s.target->T_cam_board, 24);
    if (!outline.empty()) {
      std::vector<cv::Point> poly;
      for (const auto& p : outline) poly.emplace_back(cvRound(p.x), cvRound(p.y));
      cv::Mat layer = image.clone();
      cv::fillPoly(layer, std::vector<std::vector<cv::Point>>{poly}, target_col, cv::LINE_AA);
      cv::addWeighted(layer, 0.35, image, 0.65, 0, image);
      const cv::Size2d bs = s.board.board_size_m();
      const double sq = s.board.spec().square_length_m;
      const int nx = static_cast<int>(std::lround(bs.width / sq)), ny = static_cast<int>(std::lround(bs.height / sq));
      auto line3d = [&](cv::Point3d a, cv::Point3d b) {
        std::vector<cv::Point3d> pts;
        for (int k = 0; k <= 16; ++k) pts.push_back(a + (b - a) * (k / 16.0));
        const auto pr = project_points(s.estimate, s.target->T_cam_board, pts);
        std::vector<cv::Point> pl;
        for (const auto& p : pr)
          if (std::isfinite(p.x)) pl.emplace_back(cvRound(p.x), cvRound(p.y));
        if (pl.size() > 1) cv::polylines(image, std::vector<std::vector<cv::Point>>{pl}, false, target_col, 1, cv::LINE_AA);
      };
      for (int i = 0; i <= nx; ++i) line3d({i * sq, 0, 0}, {i * sq, bs.height, 0});
      for (int j = 0; j <= ny; ++j) line3d({0, j * sq, 0}, {bs.width, j * sq, 0});
    }
  }
  for (const auto& p : s.previous.image_points) cv::circle(image, cv::Point(cvRound(p.x), cvRound(p.y)), 3, corner_col, 1, cv::LINE_AA);
  const double scale = std::max(0.5, s.size.width / 1280.0);
  const std::string status = std::string(engine_state_name(s.state)) + "  keyframes " + std::to_string(s.keyframes.size()) +
                             (s.last.target_parameter.empty() ? "" : "  target " + s.last.target_parameter) +
                             (s.last.jaccard >= 0 ? "  J " + std::to_string(s.last.jaccard).substr(0, 4) : "");
  cv::putText(image, status, cv::Point(10, static_cast<int>(30 * scale)), cv::FONT_HERSHEY_SIMPLEX, 0.7 * scale, text_col, 2, cv::LINE_AA);
  cv::putText(image, s.last.guidance, cv::Point(10, static_cast<int>(62 * scale)), cv::FONT_HERSHEY_SIMPLEX, 0.8 * scale, text_col, 2, cv::LINE_AA);
}

}  // namespace posecal
