#include "device/sources.hpp"

#include <chrono>
#include <condition_variable>
#include <deque>
#include <filesystem>
#include <mutex>
#include <opencv2/imgproc.hpp>

#include "calib/offline.hpp"
#include "common/clock.hpp"
#include "common/error.hpp"
#include "common/image_file.hpp"

namespace posecal {

CameraConfig SimpleCamera::do_validate(const CameraConfig& requested) {
  auto unsupported = [&](const char* what) {
    throw Error(ErrorCode::kUnsupported, label() + " has no " + what + " setting");
  };
  if (requested.exposure_us) unsupported("exposure");
  if (requested.gain_db) unsupported("gain");
  if (requested.frame_rate_hz) unsupported("frame rate");
  if (requested.roi) unsupported("ROI");
  if (requested.pixel_format && *requested.pixel_format != PixelFormat::kMono8 &&
      *requested.pixel_format != PixelFormat::kBGR8) {
    throw Error(ErrorCode::kUnsupported, label() + " delivers Mono8 or BGR8, not " +
                                             pixel_format_name(*requested.pixel_format));
  }
  return requested;
}

namespace {

class ImagesCamera final : public SimpleCamera {
 public:
  ImagesCamera(DeviceInfo info, std::vector<std::string> files)
      : SimpleCamera(std::move(info)), files_(std::move(files)) {}

 protected:
  FrameStatus do_next_frame(int /*timeout_ms*/, Frame* frame) override {
    while (next_ < files_.size()) {
      const std::string& file = files_[next_++];
      cv::Mat img;
      try {
        // Header first: images above kMaxImagePixels and non-regular files are skipped undecoded.
        img = read_grey_image(file);
      } catch (const Error&) {
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

DeviceInfo external_info() {
  DeviceInfo info;
  info.uri = "external";
  info.backend = "external";
  info.id = "external";
  info.model = "host-fed frames";
  info.transport = "host";
  return info;
}

class ExternalCameraImpl final : public ExternalCamera {
 public:
  ExternalCameraImpl() : ExternalCamera(external_info()) {}

  void push(const cv::Mat& image, int64_t timestamp_ns) override {
    if (image.empty() || image.depth() != CV_8U ||
        (image.channels() != 1 && image.channels() != 3)) {
      throw Error(ErrorCode::kInvalidArgument,
                  "camera 'external': frames must be 8-bit grey or BGR");
    }
    if (state() != CameraState::kStreaming)
      throw Error(ErrorCode::kState, "camera 'external': push() while not streaming");
    Frame f;
    f.image = image.clone();
    std::lock_guard<std::mutex> lock(mutex_);
    f.frame_id = next_id_++;
    f.timestamp_ns = timestamp_ns ? timestamp_ns : monotonic_ns();
    f.source_format = image.channels() == 1 ? PixelFormat::kMono8 : PixelFormat::kBGR8;
    queue_.push_back(std::move(f));
    while (static_cast<int>(queue_.size()) > depth_) {
      queue_.pop_front();
      ++stats_.frames_dropped;
    }
    cv_.notify_one();
  }

 protected:
  void do_configure(const CameraConfig& c) override {
    std::lock_guard<std::mutex> lock(mutex_);
    config_ = c;
    depth_ = c.queue_depth;
  }
  void do_stop() override {
    std::lock_guard<std::mutex> lock(mutex_);
    queue_.clear();
  }
  FrameStatus do_next_frame(int timeout_ms, Frame* frame) override {
    std::unique_lock<std::mutex> lock(mutex_);
    if (!cv_.wait_for(lock, std::chrono::milliseconds(timeout_ms), [&] { return !queue_.empty(); })) {
      return FrameStatus::kTimeout;
    }
    *frame = std::move(queue_.front());
    queue_.pop_front();
    ++stats_.frames_delivered;
    return FrameStatus::kOk;
  }
  CameraStats do_stats() const override {
    std::lock_guard<std::mutex> lock(mutex_);
    return stats_;
  }

 private:
  mutable std::mutex mutex_;
  std::condition_variable cv_;
  std::deque<Frame> queue_;
  int depth_ = CameraConfig{}.queue_depth;
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
