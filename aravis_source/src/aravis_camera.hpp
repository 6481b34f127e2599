// One open Aravis camera. Three kinds of threads touch it:
//   - the session thread: every Camera method (one at a time, as camera.hpp requires);
//   - the pump thread (while streaming): pops buffers from the ArvStream into the frame queue;
//   - the supervisor thread (whole lifetime): liveness probes, disconnect handling, reconnection,
//     event callbacks; plus short-lived reaper threads that release a vanished camera's Aravis
//     objects (which blocks for Aravis' fixed GVCP timeouts).
// Aravis' own stream and heartbeat threads run underneath. Locks, always taken in this order:
//   device_mutex_  the ArvCamera/ArvStream and the configuration (session, supervisor);
//   queue_mutex_   the frame queue (session, pump, supervisor);
//   BufferPool's   a stream's buffer return path (anyone releasing a frame).
// next_frame() takes only queue_mutex_, so it never waits on a slow GVCP transaction.
#pragma once

#include <atomic>
#include <condition_variable>
#include <deque>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include "aravis_util.hpp"
#include "posecal/aravis_backend.hpp"

namespace posecal::aravis {

// How to find the camera again after it vanished.
struct Locator {
  std::string device_id;  // Aravis device id ("" if opened by address and not discovered)
  std::string serial;
  std::string address;  // IPv4 of a GigE Vision camera
  bool gige = false;
};

// The buffers of one ArvStream. A buffer popped from the stream is owned by whoever holds it and
// comes back here: pushed to the stream while the stream is active, freed after it was retired.
class BufferPool {
 public:
  explicit BufferPool(ArvStream* stream) : stream_(stream) {}
  void give_back(ArvBuffer* buffer);
  void retire();  // after this no buffer goes back to the stream (it is about to be released)
  std::atomic<int> lent{0};

 private:
  std::mutex mutex_;
  ArvStream* stream_;  // not owned; valid until retire()
};

// Wakes the supervisor. Shared with the "control-lost" signal closure, which Aravis may run (from
// its heartbeat thread) until the closure is destroyed, possibly after the camera object.
struct SupervisorWakeup {
  std::mutex mutex;
  std::condition_variable cv;
  bool wake = false;
  bool quit = false;
  std::atomic<bool> control_lost{false};
};

class AravisCameraImpl final : public AravisCamera {
 public:
  AravisCameraImpl(GPtr<ArvCamera> camera, DeviceInfo info, Locator locator,
                   const AravisBackendOptions& options);
  ~AravisCameraImpl() override;
  AravisCameraImpl(const AravisCameraImpl&) = delete;
  AravisCameraImpl& operator=(const AravisCameraImpl&) = delete;

  AravisTransportStats transport_stats() override;

 protected:
  CameraConfig do_current_config() override;
  CameraConfig do_validate(const CameraConfig& requested) override;
  void do_configure(const CameraConfig& config) override;
  std::vector<FeatureInfo> do_features() override;
  std::string do_get_feature(const std::string& name) override;
  void do_set_feature(const std::string& name, const std::string& value) override;
  std::map<std::string, std::string> do_lock_for_calibration() override;
  void do_start() override;
  void do_stop() override;
  void do_stop_while_disconnected() override;
  FrameStatus do_next_frame(int timeout_ms, Frame* frame) override;
  CameraStats do_stats() const override;

 private:
  // What the session asked for, replayed on a reconnected camera in the original order.
  struct Setting {
    std::optional<CameraConfig> config;  // configure(), or else set_feature(name, value)
    std::string name, value;
  };
  struct Queued {
    ArvBuffer* buffer;
    std::shared_ptr<BufferPool> pool;
  };

  // --- with device_mutex_ held ---
  void attach_locked(GPtr<ArvCamera> camera);
  GPtr<ArvCamera> detach_locked();
  CameraConfig read_config_locked();
  CameraConfig validate_locked(const CameraConfig& requested);
  std::optional<PixelFormat> validate_pixel_format_locked(const std::optional<PixelFormat>& requested);
  cv::Rect validate_roi_locked(const cv::Rect& requested);
  std::optional<double> clamp_setting_locked(const std::optional<double>& value, const char* what, const char* unit,
                                             bool (*is_available)(ArvCamera*),
                                             void (*bounds)(ArvCamera*, double*, double*, GError**));
  void check_read(const GErr& err, const std::string& what) const;
  void apply_config_locked(const CameraConfig& config);
  void write_feature_locked(const std::string& name, const std::string& value);
  void record_locked(Setting setting);
  void start_locked();
  GPtr<ArvStream> stop_locked(bool talk_to_camera);
  // --- threads ---
  void pump(std::shared_ptr<BufferPool> pool, ArvStream* stream);
  void supervise();
  Locator locator() const;
  bool probe();
  void declare_disconnected(const std::string& why);
  bool try_reconnect(int attempt);
  std::string find_again(int attempt) const;
  GPtr<ArvCamera> reopen(const std::string& target) const;
  std::vector<std::string> restore_settings_locked();
  void reap(GPtr<ArvStream> stream, GPtr<ArvCamera> camera);
  void emit(CameraEvent::Kind kind, const std::string& message);
  FrameStatus deliver(Queued item, Frame* frame);

  const AravisBackendOptions options_;
  const std::string label_;  // "camera 'aravis://...'", Camera::label()

  mutable std::mutex device_mutex_;
  mutable std::mutex locator_mutex_;  // locator_ alone: the probe must not wait on GVCP calls
  Locator locator_;
  GPtr<ArvCamera> camera_;
  ArvDevice* device_ = nullptr;  // owned by camera_
  gulong control_lost_handler_ = 0;
  GPtr<ArvStream> stream_;
  std::shared_ptr<BufferPool> pool_;
  std::thread pump_thread_;
  std::atomic<bool> pump_quit_{false};
  std::vector<Setting> settings_;
  bool configured_ = false;      // configure() succeeded at least once
  bool want_streaming_ = false;  // start() succeeded and stop() was not called since
  std::atomic<int> queue_depth_{4};

  std::mutex queue_mutex_;
  std::condition_variable queue_cv_;
  std::deque<Queued> queue_;

  std::atomic<uint64_t> delivered_{0}, dropped_{0}, incomplete_{0}, disconnects_{0}, reconnects_{0},
      zero_copy_{0}, copied_{0};
  std::atomic<int64_t> last_buffer_ns_{0};
  int64_t discard_until_ns_ = 0;  // frames before this (steady clock) are discarded (pump only)

  std::shared_ptr<SupervisorWakeup> wakeup_;
  std::thread supervisor_;

  struct Reaper {
    std::thread thread;
    std::shared_ptr<std::atomic<bool>> done;
  };
  std::mutex reaper_mutex_;
  std::vector<Reaper> reapers_;
};

}  // namespace posecal::aravis
