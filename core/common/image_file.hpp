// Image files, checked before they are decoded: the dimensions come from the file's header, so
// a small file that would decode into gigabytes (a 424 KB PNG of 20000 x 20000 black pixels took
// 99.5 s and 2.4 GB to decode) is refused at the cost of reading a few bytes, and a file that is
// not a regular file (a FIFO, a device) is refused without blocking on it. Used by the images://
// camera (device/sources.cpp) and offline calibration (calib/offline.cpp).
#pragma once

#include <cstddef>
#include <cstdint>
#include <functional>
#include <opencv2/core.hpp>
#include <optional>
#include <string>

namespace posecal {

// The largest image posecal decodes from a file: 50 megapixels (8192 x 6104; a 48 MP sensor's
// 8000 x 6000 fits). Detection is bounded for frames up to this size (docs/performance.md).
inline constexpr int64_t kMaxImagePixels = 50'000'000;

struct ImageFileInfo {
  std::string format;  // "PNG", "JPEG", "BMP", "PNM", "PAM", "PFM", "TIFF", "WebP", "Sun raster"
  int64_t width = 0;
  int64_t height = 0;
};

// Reads up to `n` bytes at `offset` into `buf`; returns how many were read (fewer at the end).
using ByteReader = std::function<size_t(uint64_t offset, void* buf, size_t n)>;

// The format and dimensions from an image file's header (recognised by content, as cv::imread
// does: PNG, JPEG, BMP, PNM/PAM/PFM, TIFF and BigTIFF, WebP, Sun raster). nullopt if the bytes
// are none of these; Error(kInvalidArgument) if they start like one but the header is broken.
std::optional<ImageFileInfo> parse_image_header(const ByteReader& read);

// Opens `path` without blocking (O_NONBLOCK) and reads its header: Error(kNotFound) if it does
// not exist, kInvalidArgument if it is not a regular file (a FIFO, a device, a directory) or its
// header is broken, kUnsupported if it is not an image format listed above, kIo if it cannot be
// read. Then refuses an image of more than `max_pixels` pixels: Error(kInvalidArgument) naming
// the size and the limit.
ImageFileInfo check_image_file(const std::string& path, int64_t max_pixels = kMaxImagePixels);

// check_image_file, then decodes the image as 8-bit grey (cv::imread, IMREAD_GRAYSCALE).
// Error(kInvalidArgument) "not a readable image" if the decoder fails.
cv::Mat read_grey_image(const std::string& path, int64_t max_pixels = kMaxImagePixels);

}  // namespace posecal
