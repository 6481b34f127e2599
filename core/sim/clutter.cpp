#include "sim/clutter.hpp"

#include <opencv2/imgproc.hpp>

#include "common/error.hpp"

namespace posecal {

namespace {

cv::Mat blurred(cv::Mat img, double sigma) {
  if (sigma > 0) cv::GaussianBlur(img, img, cv::Size(0, 0), sigma);
  return img;
}

void check_size(cv::Size size, int a, int b, const char* what) {
  if (size.width <= 0 || size.height <= 0 || a <= 0 || b <= 0) {
    throw Error(ErrorCode::kInvalidArgument, std::string(what) + ": sizes must be positive");
  }
}

}  // namespace

cv::Mat checkerboard_clutter(cv::Size size, int square_px, double blur_sigma_px) {
  check_size(size, square_px, 1, "checkerboard_clutter");
  cv::Mat img(size, CV_8U);
  for (int y = 0; y < size.height; ++y) {
    auto* row = img.ptr<uchar>(y);
    for (int x = 0; x < size.width; ++x) row[x] = (x / square_px + y / square_px) % 2 ? 255 : 0;
  }
  return blurred(img, blur_sigma_px);
}

cv::Mat dot_grid_clutter(cv::Size size, int dot_px, int gap_px, double blur_sigma_px) {
  check_size(size, dot_px, gap_px, "dot_grid_clutter");
  const int pitch = dot_px + gap_px;
  cv::Mat img(size, CV_8U);
  for (int y = 0; y < size.height; ++y) {
    auto* row = img.ptr<uchar>(y);
    for (int x = 0; x < size.width; ++x)
      row[x] = x % pitch < dot_px && y % pitch < dot_px ? 0 : 255;
  }
  return blurred(img, blur_sigma_px);
}

cv::Mat render_in_front_of(SyntheticCamera& camera, const Pose& T_cam_board,
                           const cv::Mat& background) {
  const cv::Size size = camera.model().size();
  if (background.size() != size || background.type() != CV_8UC1) {
    throw Error(ErrorCode::kInvalidArgument,
                "render_in_front_of: the background must be 8-bit grey of the camera's size");
  }
  const RenderOptions saved = camera.options();
  RenderOptions o = saved;
  o.background_texture = 0;
  o.background = 0;
  camera.set_options(o);
  cv::Mat over_black, over_white;
  camera.render(T_cam_board).convertTo(over_black, CV_32F);
  o.background = 255;
  camera.set_options(o);
  camera.render(T_cam_board).convertTo(over_white, CV_32F);
  camera.set_options(saved);
  cv::Mat share = (over_white - over_black) / 255.0, bg, out;
  background.convertTo(bg, CV_32F);
  cv::Mat composed = over_black + share.mul(bg);
  composed.convertTo(out, CV_8U);  // rounds and saturates
  return out;
}

}  // namespace posecal
