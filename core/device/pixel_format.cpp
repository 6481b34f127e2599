// Camera pixel formats and their conversion to the engine's 8-bit grey or BGR.
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "common/error.hpp"
#include "device/camera.hpp"

namespace posecal {

const char* pixel_format_name(PixelFormat f) {
  switch (f) {
    case PixelFormat::kMono8:
      return "Mono8";
    case PixelFormat::kMono16:
      return "Mono16";
    case PixelFormat::kBGR8:
      return "BGR8";
    case PixelFormat::kRGB8:
      return "RGB8";
    case PixelFormat::kBayerRG8:
      return "BayerRG8";
    case PixelFormat::kBayerGR8:
      return "BayerGR8";
    case PixelFormat::kBayerGB8:
      return "BayerGB8";
    case PixelFormat::kBayerBG8:
      return "BayerBG8";
    case PixelFormat::kYUYV:
      return "YUYV";
    case PixelFormat::kMJPEG:
      return "MJPEG";
    case PixelFormat::kUnknown:
      return "Unknown";
  }
  return "Unknown";
}

PixelFormat pixel_format_from_name(const std::string& name) {
  for (PixelFormat f :
       {PixelFormat::kMono8, PixelFormat::kMono16, PixelFormat::kBGR8, PixelFormat::kRGB8,
        PixelFormat::kBayerRG8, PixelFormat::kBayerGR8, PixelFormat::kBayerGB8,
        PixelFormat::kBayerBG8, PixelFormat::kYUYV, PixelFormat::kMJPEG}) {
    if (name == pixel_format_name(f)) return f;
  }
  return PixelFormat::kUnknown;
}

cv::Mat convert_to_engine(PixelFormat format, const void* data, size_t bytes, int width, int height,
                          size_t stride_bytes, int mono16_shift) {
  if (data == nullptr || width <= 0 || height <= 0) {
    throw Error(ErrorCode::kInvalidArgument, "frame conversion: empty buffer or size");
  }
  auto need = [&](size_t bpp) {
    const size_t stride = stride_bytes ? stride_bytes : static_cast<size_t>(width) * bpp;
    if (stride < static_cast<size_t>(width) * bpp ||
        bytes < stride * static_cast<size_t>(height - 1) + static_cast<size_t>(width) * bpp) {
      throw Error(ErrorCode::kInvalidArgument,
                  std::string("frame conversion: buffer too small for ") +
                      pixel_format_name(format) + " " + std::to_string(width) + "x" +
                      std::to_string(height));
    }
    return stride;
  };
  void* p = const_cast<void*>(data);
  switch (format) {
    case PixelFormat::kMono8:
      return cv::Mat(height, width, CV_8UC1, p, need(1));
    case PixelFormat::kBGR8:
      return cv::Mat(height, width, CV_8UC3, p, need(3));
    case PixelFormat::kRGB8: {
      cv::Mat out;
      cv::cvtColor(cv::Mat(height, width, CV_8UC3, p, need(3)), out, cv::COLOR_RGB2BGR);
      return out;
    }
    case PixelFormat::kMono16: {
      cv::Mat out;
      cv::Mat(height, width, CV_16UC1, p, need(2)).convertTo(out, CV_8U, 1.0 / (1 << mono16_shift));
      return out;
    }
    case PixelFormat::kBayerRG8:
    case PixelFormat::kBayerGR8:
    case PixelFormat::kBayerGB8:
    case PixelFormat::kBayerBG8: {
      // GenICam names the first two pixels of the first row; OpenCV names those of the second
      // row, so RG <-> BG and GR <-> GB swap.
      int code = cv::COLOR_BayerBG2BGR;
      if (format == PixelFormat::kBayerGR8) code = cv::COLOR_BayerGB2BGR;
      if (format == PixelFormat::kBayerGB8) code = cv::COLOR_BayerGR2BGR;
      if (format == PixelFormat::kBayerBG8) code = cv::COLOR_BayerRG2BGR;
      cv::Mat out;
      cv::cvtColor(cv::Mat(height, width, CV_8UC1, p, need(1)), out, code);
      return out;
    }
    case PixelFormat::kYUYV: {
      if (width % 2 != 0) throw Error(ErrorCode::kInvalidArgument, "YUYV frame width must be even");
      cv::Mat out;
      cv::cvtColor(cv::Mat(height, width, CV_8UC2, p, need(2)), out, cv::COLOR_YUV2BGR_YUYV);
      return out;
    }
    case PixelFormat::kMJPEG: {
      // A JPEG must start with SOI (FFD8) and end with EOI (FFD9, possibly followed by padding);
      // libjpeg would otherwise return a silently truncated image.
      const auto* b = static_cast<const unsigned char*>(data);
      if (bytes < 4 || b[0] != 0xFF || b[1] != 0xD8) return {};
      size_t end = bytes;
      while (end > 2 && b[end - 1] == 0x00) --end;
      if (!(b[end - 2] == 0xFF && b[end - 1] == 0xD9)) return {};
      cv::Mat out;
      try {
        out = cv::imdecode(cv::Mat(1, static_cast<int>(bytes), CV_8UC1, p), cv::IMREAD_COLOR);
      } catch (const cv::Exception&) {
        return {};
      }
      if (!out.empty() && (out.cols != width || out.rows != height)) return {};
      return out;
    }
    case PixelFormat::kUnknown:
      break;
  }
  throw Error(ErrorCode::kUnsupported,
              std::string("pixel format ") + pixel_format_name(format) + " is not supported");
}

}  // namespace posecal
