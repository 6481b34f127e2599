// Frames of fuzz_session_feed's inputs as the C ABI hands them to the detector, for the tests and
// benchmarks that replay its slow inputs (tests/fuzz/crashes/fuzz_session_feed/slow-*).
#pragma once

#include <fstream>
#include <iterator>
#include <opencv2/imgproc.hpp>
#include <string>
#include <vector>

namespace posecal::testing_support {

// The input's frame (tests/fuzz/fuzz_session_feed.cpp: bytes 0-1 width - 1, 2-3 height - 1, each
// modulo 256; byte 4 the pixel format mod 3, MONO8, BGR8 or RGB8; byte 5 extra stride bytes mod
// 8; byte 6 the frame count; then the pixels, repeated to fill the rows and their stride), grey
// or BGR as session_abi.cpp passes it on (an RGB frame converted to BGR). Empty if the file is
// shorter than its header.
inline cv::Mat fuzz_session_frame(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  const std::vector<unsigned char> b((std::istreambuf_iterator<char>(in)),
                                     std::istreambuf_iterator<char>());
  if (b.size() < 7) return {};
  const int w = 1 + ((b[0] | b[1] << 8) % 256), h = 1 + ((b[2] | b[3] << 8) % 256);
  const int format = b[4] % 3, extra = b[5] % 8, channels = format == 0 ? 1 : 3;
  const size_t stride = static_cast<size_t>(w * channels + extra), npx = b.size() - 7;
  cv::Mat frame(h, w, CV_8UC(channels));
  for (int y = 0; y < h; ++y) {
    for (int x = 0; x < w * channels; ++x) {
      const size_t i = static_cast<size_t>(y) * stride + static_cast<size_t>(x);
      frame.ptr<unsigned char>(y)[x] = npx > 0 ? b[7 + i % npx] : 0;
    }
  }
  if (format == 2) cv::cvtColor(frame, frame, cv::COLOR_RGB2BGR);
  return frame;
}

}  // namespace posecal::testing_support
