// Camera sources built into core: images:// (replays a folder in name order) and external (the
// host pushes frames). sim:// lives in sim/sim_camera.hpp.
#pragma once

#include <memory>

#include "device/camera.hpp"

namespace posecal {

// Base for cameras without device settings: no exposure, gain, frame rate or ROI; Mono8 or BGR8;
// no features, nothing to lock. The state machine is Camera's.
class SimpleCamera : public Camera {
 protected:
  explicit SimpleCamera(DeviceInfo info) : Camera(std::move(info)) {}
  CameraConfig do_current_config() override { return config_; }
  CameraConfig do_validate(const CameraConfig& requested) override;
  void do_configure(const CameraConfig& config) override { config_ = config; }
  void do_start() override {}
  void do_stop() override {}
  CameraStats do_stats() const override { return stats_; }

  CameraConfig config_;
  CameraStats stats_;
};

// images://DIR: every regular file of DIR in name order, converted to 8-bit grey; unreadable
// files, images above kMaxImagePixels (checked from the header before decoding,
// common/image_file.hpp), files that are no longer regular files and images whose size differs
// from the first image are counted as incomplete and skipped.
// After the last file next_frame() returns kEndOfStream.
std::shared_ptr<CameraBackend> make_images_backend();

// external: frames come from the host. push() may be called from any thread; the queue holds
// queue_depth frames and drops the oldest.
class ExternalCamera : public SimpleCamera {
 public:
  virtual void push(const cv::Mat& image, int64_t timestamp_ns = 0) = 0;

 protected:
  using SimpleCamera::SimpleCamera;
};
std::shared_ptr<CameraBackend> make_external_backend();

}  // namespace posecal
