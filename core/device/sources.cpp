#include "device/sources.hpp"

#include <chrono>
#include <condition_variable>
#include <deque>
#include <filesystem>
#include <mutex>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "calib/offline.hpp"

namespace posecal {

namespace {

int64_t monotonic_ns() {
  return std::chrono::duration_cast<std::chrono::nanoseconds>(
             std::chrono::steady_clock::now().time_since_epoch())
      .count();
}

}  // namespace

CameraConfig SimpleCamera::validate(const CameraConfig& requested) {
  CameraConfig out = requested;
  auto unsupported = [&](const char* what) {
    throw Error(ErrorCode::kUnsupported, "camera '" + info_.uri + "' has no " + what + " setting");
  };
  if (requested.exposure_us) unsupported("exposure");
  if (requested.gain_db) unsupported("gain");
  if (requested.frame_rate_hz) unsupported("frame rate");
  if (requested.roi) unsupported("ROI");
  if (requested.pixel_format && *requested.pixel_format != PixelFormat::kMono8 &&
      *requested.pixel_format != PixelFormat::kBGR8) {
    throw Error(ErrorCode::kUnsupported, "camera '" + info_.uri + "' delivers Mono8 or BGR8, not " +
                                             pixel_format_name(*requested.pixel_format));
  }
  if (out.queue_depth < 1 || out.queue_depth > 64) {
    throw Error(ErrorCode::kInvalidArgument,
                "camera '" + info_.uri + "': queue depth must be 1..64");
  }
  return out;
}

void SimpleCamera::configure(const CameraConfig& config) {
  if (state_ == CameraState::kStreaming) {
    throw Error(ErrorCode::kState, "camera '" + info_.uri + "': configure() while streaming");
  }
  if (state_ == CameraState::kDisconnected) {
    throw Error(ErrorCode::kState, "camera '" + info_.uri + "': configure() after disconnect");
  }
  config_ = validate(config);
  state_ = CameraState::kConfigured;
}

std::string SimpleCamera::get_feature(const std::string& name) {
  throw Error(ErrorCode::kNotFound, "camera '" + info_.uri + "' has no feature '" + name + "'");
}

void SimpleCamera::set_feature(const std::string& name, const std::string&) {
  throw Error(ErrorCode::kNotFound, "camera '" + info_.uri + "' has no feature '" + name + "'");
}

void SimpleCamera::start() {
  if (state_ == CameraState::kDisconnected) {
    throw Error(ErrorCode::kState, "camera '" + info_.uri + "': start() after disconnect");
  }
  if (state_ == CameraState::kOpened) configure(config_);
  state_ = CameraState::kStreaming;
}

void SimpleCamera::stop() {
  if (state_ == CameraState::kStreaming) state_ = CameraState::kConfigured;
}

void SimpleCamera::require_streaming(const char* call) const {
  if (state_ != CameraState::kStreaming) {
    throw Error(ErrorCode::kState, "camera '" + info_.uri + "': " + call + " while " +
                                       camera_state_name(state_) + " (start() first)");
  }
}

namespace {

class ImagesCamera final : public SimpleCamera {
 public:
  ImagesCamera(DeviceInfo info, std::vector<std::string> files)
      : SimpleCamera(std::move(info)), files_(std::move(files)) {}

  FrameStatus next_frame(int /*timeout_ms*/, Frame* frame) override {
    require_streaming("next_frame()");
    while (next_ < files_.size()) {
      const std::string& file = files_[next_++];
      cv::Mat img;
      try {
        img = cv::imread(file, cv::IMREAD_GRAYSCALE);
      } catch (const cv::Exception&) {
        img.release();
      }
      if (img.empty() || (!size_.empty() && img.size() != size_)) {
        ++stats_.frames_incomplete;
        continue;
      }
      size_ = img.size();
      frame->image = img;
      frame->frame_id = next_ - 1;
      frame->timestamp_ns = monotonic_ns();
      frame->source_format = PixelFormat::kMono8;
      frame->hold.reset();
      ++stats_.frames_delivered;
      return FrameStatus::kOk;
    }
    return FrameStatus::kEndOfStream;
  }

 private:
  std::vector<std::string> files_;
  size_t next_ = 0;
  cv::Size size_;
};

class ImagesBackend final : public CameraBackend {
 public:
  std::string scheme() const override { return "images"; }
  std::vector<DeviceInfo> enumerate() override { return {}; }  // folders are not discoverable
  std::unique_ptr<Camera> open(const Uri& uri) override {
    if (uri.path.empty())
      throw Error(ErrorCode::kInvalidArgument, "camera URI '" + uri.text + "': no folder");
    if (!uri.query.empty()) {
      throw Error(ErrorCode::kInvalidArgument,
                  "camera URI '" + uri.text + "': images:// takes no options");
    }
    std::vector<std::string> files;
    try {
      files = list_files_sorted(uri.path);
    } catch (const Error& e) {
      throw Error(e.code(), "camera '" + uri.text + "': " + e.what());
    }
    DeviceInfo info;
    info.uri = uri.text;
    info.backend = "images";
    info.id = std::filesystem::path(uri.path).filename().string();
    info.model = "image folder";
    info.transport = "files";
    return std::make_unique<ImagesCamera>(info, std::move(files));
  }
};

class ExternalCameraImpl final : public ExternalCamera {
 public:
  ExternalCameraImpl() {
    info_.uri = "external";
    info_.backend = "external";
    info_.id = "external";
    info_.model = "host-fed frames";
    info_.transport = "host";
  }
  const DeviceInfo& info() const override { return info_; }
  CameraState state() const override {
    std::lock_guard<std::mutex> lock(mutex_);
    return state_;
  }
  CameraConfig current_config() override { return config_; }
  CameraConfig validate(const CameraConfig& requested) override {
    if (requested.queue_depth < 1 || requested.queue_depth > 64) {
      throw Error(ErrorCode::kInvalidArgument, "camera 'external': queue depth must be 1..64");
    }
    if (requested.exposure_us || requested.gain_db || requested.frame_rate_hz || requested.roi) {
      throw Error(ErrorCode::kUnsupported, "camera 'external' has no device settings");
    }
    return requested;
  }
  void configure(const CameraConfig& c) override {
    std::lock_guard<std::mutex> lock(mutex_);
    if (state_ == CameraState::kStreaming)
      throw Error(ErrorCode::kState, "camera 'external': configure() while streaming");
    config_ = validate(c);
    state_ = CameraState::kConfigured;
  }
  std::vector<FeatureInfo> features() override { return {}; }
  std::string get_feature(const std::string& n) override {
    throw Error(ErrorCode::kNotFound, "camera 'external' has no feature '" + n + "'");
  }
  void set_feature(const std::string& n, const std::string&) override {
    throw Error(ErrorCode::kNotFound, "camera 'external' has no feature '" + n + "'");
  }
  std::map<std::string, std::string> lock_for_calibration() override { return {}; }
  void start() override {
    std::lock_guard<std::mutex> lock(mutex_);
    state_ = CameraState::kStreaming;
  }
  void stop() override {
    std::lock_guard<std::mutex> lock(mutex_);
    if (state_ == CameraState::kStreaming) state_ = CameraState::kConfigured;
    queue_.clear();
  }
  void push(const cv::Mat& image, int64_t timestamp_ns) override {
    if (image.empty() || image.depth() != CV_8U ||
        (image.channels() != 1 && image.channels() != 3)) {
      throw Error(ErrorCode::kInvalidArgument,
                  "camera 'external': frames must be 8-bit grey or BGR");
    }
    std::lock_guard<std::mutex> lock(mutex_);
    if (state_ != CameraState::kStreaming)
      throw Error(ErrorCode::kState, "camera 'external': push() while not streaming");
    Frame f;
    f.image = image.clone();
    f.frame_id = next_id_++;
    f.timestamp_ns = timestamp_ns ? timestamp_ns : monotonic_ns();
    f.source_format = image.channels() == 1 ? PixelFormat::kMono8 : PixelFormat::kBGR8;
    queue_.push_back(std::move(f));
    while (static_cast<int>(queue_.size()) > config_.queue_depth) {
      queue_.pop_front();
      ++stats_.frames_dropped;
    }
    cv_.notify_one();
  }
  FrameStatus next_frame(int timeout_ms, Frame* frame) override {
    std::unique_lock<std::mutex> lock(mutex_);
    if (state_ != CameraState::kStreaming)
      throw Error(ErrorCode::kState, "camera 'external': next_frame() while not streaming");
    if (!cv_.wait_for(lock, std::chrono::milliseconds(std::max(0, timeout_ms)),
                      [&] { return !queue_.empty(); })) {
      return FrameStatus::kTimeout;
    }
    *frame = std::move(queue_.front());
    queue_.pop_front();
    ++stats_.frames_delivered;
    return FrameStatus::kOk;
  }
  CameraStats stats() const override {
    std::lock_guard<std::mutex> lock(mutex_);
    return stats_;
  }
  void set_event_callback(CameraEventCallback) override {}

 private:
  DeviceInfo info_;
  mutable std::mutex mutex_;
  std::condition_variable cv_;
  CameraState state_ = CameraState::kOpened;
  CameraConfig config_;
  CameraStats stats_;
  std::deque<Frame> queue_;
  uint64_t next_id_ = 0;
};

class ExternalBackend final : public CameraBackend {
 public:
  std::string scheme() const override { return "external"; }
  std::vector<DeviceInfo> enumerate() override { return {}; }
  std::unique_ptr<Camera> open(const Uri& uri) override {
    if (!uri.path.empty() || !uri.query.empty()) {
      throw Error(ErrorCode::kInvalidArgument,
                  "camera URI '" + uri.text + "': use plain 'external'");
    }
    return std::make_unique<ExternalCameraImpl>();
  }
};

}  // namespace

std::shared_ptr<CameraBackend> make_images_backend() { return std::make_shared<ImagesBackend>(); }
std::shared_ptr<CameraBackend> make_external_backend() {
  return std::make_shared<ExternalBackend>();
}

}  // namespace posecal
