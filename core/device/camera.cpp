#include "device/camera.hpp"

#include <mutex>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

namespace posecal {

namespace {

int hex_value(char c) {
  if (c >= '0' && c <= '9') return c - '0';
  if (c >= 'a' && c <= 'f') return c - 'a' + 10;
  if (c >= 'A' && c <= 'F') return c - 'A' + 10;
  return -1;
}

std::string percent_decode(const std::string& in, const std::string& uri) {
  std::string out;
  for (size_t i = 0; i < in.size(); ++i) {
    if (in[i] == '%') {
      if (i + 2 >= in.size() || hex_value(in[i + 1]) < 0 || hex_value(in[i + 2]) < 0) {
        throw Error(ErrorCode::kInvalidArgument, "camera URI '" + uri + "': bad percent escape");
      }
      out.push_back(static_cast<char>(hex_value(in[i + 1]) * 16 + hex_value(in[i + 2])));
      i += 2;
    } else {
      out.push_back(in[i]);
    }
  }
  return out;
}

}  // namespace

Uri Uri::parse(const std::string& text) {
  Uri u;
  u.text = text;
  if (text.empty()) throw Error(ErrorCode::kInvalidArgument, "camera URI is empty");
  for (char c : text) {
    if (static_cast<unsigned char>(c) < 0x20) {
      throw Error(ErrorCode::kInvalidArgument, "camera URI contains a control character");
    }
  }
  const size_t sep = text.find("://");
  std::string rest;
  if (sep == std::string::npos) {
    // Scheme-only URIs ("external").
    if (text.find_first_of(":/?") != std::string::npos) {
      throw Error(ErrorCode::kInvalidArgument,
                  "camera URI '" + text + "' is malformed (expected scheme://...)");
    }
    u.scheme = text;
    return u;
  }
  u.scheme = text.substr(0, sep);
  if (u.scheme.empty())
    throw Error(ErrorCode::kInvalidArgument, "camera URI '" + text + "' has no scheme");
  for (char c : u.scheme) {
    if (!std::isalnum(static_cast<unsigned char>(c)) && c != '+' && c != '-' && c != '.') {
      throw Error(ErrorCode::kInvalidArgument, "camera URI '" + text + "' has an invalid scheme");
    }
  }
  rest = text.substr(sep + 3);
  const size_t q = rest.find('?');
  u.path = percent_decode(rest.substr(0, q), text);
  if (q != std::string::npos) {
    std::string query = rest.substr(q + 1);
    size_t start = 0;
    while (start <= query.size()) {
      size_t amp = query.find('&', start);
      if (amp == std::string::npos) amp = query.size();
      const std::string pair = query.substr(start, amp - start);
      if (!pair.empty()) {
        const size_t eq = pair.find('=');
        const std::string key = percent_decode(pair.substr(0, eq), text);
        const std::string value =
            eq == std::string::npos ? "" : percent_decode(pair.substr(eq + 1), text);
        if (key.empty())
          throw Error(ErrorCode::kInvalidArgument,
                      "camera URI '" + text + "' has an empty query key");
        if (u.query.count(key)) {
          throw Error(ErrorCode::kInvalidArgument,
                      "camera URI '" + text + "' repeats '" + key + "'");
        }
        u.query[key] = value;
      }
      start = amp + 1;
    }
  }
  return u;
}

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

const char* camera_state_name(CameraState s) {
  switch (s) {
    case CameraState::kOpened:
      return "opened";
    case CameraState::kConfigured:
      return "configured";
    case CameraState::kStreaming:
      return "streaming";
    case CameraState::kDisconnected:
      return "disconnected";
  }
  return "unknown";
}

struct CameraManager::Impl {
  mutable std::mutex mutex;
  std::vector<std::shared_ptr<CameraBackend>> backends;
  CameraBackend::HotplugCallback hotplug;
};

CameraManager::CameraManager() : impl_(std::make_unique<Impl>()) {}
CameraManager::~CameraManager() {
  // Detach hot-plug callbacks before the backends go away.
  for (auto& b : impl_->backends) b->set_hotplug_callback(nullptr);
}

void CameraManager::add_backend(std::shared_ptr<CameraBackend> backend) {
  if (!backend) throw Error(ErrorCode::kInvalidArgument, "add_backend: null backend");
  std::lock_guard<std::mutex> lock(impl_->mutex);
  for (auto& b : impl_->backends) {
    if (b->scheme() == backend->scheme()) {
      b = backend;
      return;
    }
  }
  impl_->backends.push_back(backend);
  if (impl_->hotplug) backend->set_hotplug_callback(impl_->hotplug);
}

std::vector<std::string> CameraManager::schemes() const {
  std::lock_guard<std::mutex> lock(impl_->mutex);
  std::vector<std::string> out;
  for (const auto& b : impl_->backends) out.push_back(b->scheme());
  return out;
}

std::vector<DeviceInfo> CameraManager::list(std::vector<std::string>* errors) {
  std::vector<std::shared_ptr<CameraBackend>> backends;
  {
    std::lock_guard<std::mutex> lock(impl_->mutex);
    backends = impl_->backends;
  }
  std::vector<DeviceInfo> out;
  for (const auto& b : backends) {
    try {
      auto devices = b->enumerate();
      out.insert(out.end(), devices.begin(), devices.end());
    } catch (const std::exception& e) {
      if (errors) errors->push_back(b->scheme() + ": " + e.what());
    }
  }
  return out;
}

std::unique_ptr<Camera> CameraManager::open(const std::string& uri_text) {
  const Uri uri = Uri::parse(uri_text);
  std::shared_ptr<CameraBackend> backend;
  {
    std::lock_guard<std::mutex> lock(impl_->mutex);
    for (const auto& b : impl_->backends) {
      if (b->scheme() == uri.scheme) backend = b;
    }
  }
  if (!backend) {
    std::string known;
    for (const auto& s : schemes()) known += (known.empty() ? "" : ", ") + s;
    throw Error(ErrorCode::kInvalidArgument, "camera URI '" + uri_text + "': unknown scheme '" +
                                                 uri.scheme + "' (known: " + known + ")");
  }
  return backend->open(uri);
}

void CameraManager::set_hotplug_callback(CameraBackend::HotplugCallback cb) {
  std::lock_guard<std::mutex> lock(impl_->mutex);
  impl_->hotplug = cb;
  for (auto& b : impl_->backends) b->set_hotplug_callback(cb);
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
