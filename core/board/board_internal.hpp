// Internal to board/: OpenCV's ChArUco objects behind a Board, shared by detection (board.cpp)
// and the printable board (printable.cpp).
#pragma once

#include <opencv2/aruco/charuco.hpp>

#include "board/board.hpp"

namespace posecal {

struct Board::Impl {
  cv::Ptr<cv::aruco::Dictionary> dictionary;
  cv::Ptr<cv::aruco::CharucoBoard> board;
  cv::Ptr<cv::aruco::DetectorParameters> params;
};

}  // namespace posecal
