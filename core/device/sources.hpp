// Camera sources built into core: images:// (replays a folder in name order) and external (the
// host pushes frames). sim:// lives in simulation.hpp.
#pragma once

#include <memory>

#include "device/camera.hpp"

namespace posecal {

// images://DIR: every regular file of DIR in name order, converted to 8-bit grey; unreadable
// files and files whose size differs from the first image are counted as incomplete and skipped.
// After the last file next_frame() returns kEndOfStream.
std::shared_ptr<CameraBackend> make_images_backend();

// external: frames come from the host. push() may be called from any thread; the queue holds
// queue_depth frames and drops the oldest.
class ExternalCamera : public Camera {
 public:
  virtual void push(const cv::Mat& image, int64_t timestamp_ns = 0) = 0;
};
std::shared_ptr<CameraBackend> make_external_backend();

// Common base for cameras without device settings: the state machine of camera.hpp, no
// features, nothing to lock.
class SimpleCamera : public Camera {
 public:
  explicit SimpleCamera(DeviceInfo info) : info_(std::move(info)) {}
  const DeviceInfo& info() const override { return info_; }
  CameraState state() const override { return state_; }
  CameraConfig current_config() override { return config_; }
  CameraConfig validate(const CameraConfig& requested) override;
  void configure(const CameraConfig& config) override;
  std::vector<FeatureInfo> features() override { return {}; }
  std::string get_feature(const std::string& name) override;
  void set_feature(const std::string& name, const std::string& value) override;
  std::map<std::string, std::string> lock_for_calibration() override { return {}; }
  void start() override;
  void stop() override;
  CameraStats stats() const override { return stats_; }
  void set_event_callback(CameraEventCallback cb) override { event_cb_ = std::move(cb); }

 protected:
  // Throws Error(kState) naming the call unless the camera is streaming.
  void require_streaming(const char* call) const;

  DeviceInfo info_;
  CameraState state_ = CameraState::kOpened;
  CameraConfig config_;
  CameraStats stats_;
  CameraEventCallback event_cb_;
};

}  // namespace posecal
