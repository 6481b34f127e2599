// Camera abstraction: a manager that knows backends, cameras opened by URI, a configuration
// validated before use, and frames pulled with a timeout. Modelled on libcamera's
// CameraManager / Camera / CameraConfiguration, reduced to what calibration needs.
//
// Backends (one folder each, implementing CameraBackend):
//   aravis://<device-id | serial | IP>         aravis_source/  (GenICam GigE Vision / USB3 Vision)
//   v4l2://<stable id> | v4l2:///dev/videoN    v4l2_source/    (UVC webcams)
//   sim://?model=FILE&seed=N&operator=person|robot   core: synthetic camera + simulated operator
//   images://DIR                               core: replays a folder in name order
//   external                                   core: the host pushes frames
//
// Camera states, checked once for every backend by Camera's public calls (each throws
// Error(kState) naming the camera, the call and the state when the call is not allowed), which
// then call the backend's protected do_* hooks (libcamera's Camera / PipelineHandler split):
//
//   Opened --configure()--> Configured --start()--> Streaming --stop()--> Configured
//      |      (start() from Opened configures with the camera's current settings first)
//      +------------- disconnect (any state) ----> Disconnected (only info/state/stats/stop and
//                                                   the event callback are allowed; next_frame()
//                                                   returns kDisconnected; a backend that
//                                                   reconnects by itself returns to the state
//                                                   before the disconnect, so a streaming session
//                                                   resumes; Aravis does)
//
//   call                          Opened  Configured  Streaming  Disconnected
//   current_config, validate,      yes     yes         yes        kState
//   features, get/set_feature,
//   lock_for_calibration
//   configure                      yes     yes         kState     kState
//   start                          yes     yes         kState     kState
//   stop                           no-op   no-op       yes        no-op
//   next_frame                     kState  kState      yes        kDisconnected
//
// One queue-depth rule for every backend: validate() refuses queue_depth outside
// [1, Camera::kMaxQueueDepth]; a backend may then lower it to what it can buffer (Adjusted).
//
// Threading: a Camera is used from one thread at a time (the session's). Backends may run
// their own threads (Aravis' stream thread, libusb's hot-plug thread); the event callback is
// called from such a backend thread and must not call back into the camera. next_frame() is
// the only blocking call and never waits longer than its timeout.
#pragma once

#include <atomic>
#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <opencv2/core.hpp>
#include <optional>
#include <string>
#include <vector>

#include "lens/camera_model.hpp"
#include "common/error.hpp"
#include "device/guidance.hpp"
#include "lens/geometry.hpp"

namespace posecal {

struct Uri {
  std::string scheme;                        // "aravis", "v4l2", "sim", "images", "external"
  std::string path;                          // everything between "scheme://" and "?"
  std::map<std::string, std::string> query;  // decoded key=value pairs after "?"
  std::string text;                          // the original URI
  // Throws Error(kInvalidArgument) for a malformed URI.
  static Uri parse(const std::string& uri);
};

enum class PixelFormat {
  kMono8,
  kMono16,
  kBGR8,
  kRGB8,
  kBayerRG8,
  kBayerGR8,
  kBayerGB8,
  kBayerBG8,
  kYUYV,
  kMJPEG,
  kUnknown,
};
const char* pixel_format_name(PixelFormat f);
PixelFormat pixel_format_from_name(const std::string& name);  // kUnknown if not known

struct DeviceInfo {
  std::string uri;      // opens this camera again, e.g. "aravis://Aravis-Fake-GV01"
  std::string backend;  // "aravis", "v4l2", "sim", "images", "external"
  std::string id;       // backend-specific stable id
  std::string vendor;
  std::string model;
  std::string serial;
  std::string transport;  // "GigE Vision", "USB3 Vision", "USB UVC", "simulated", "files", "host"
};

// A frame handed to the engine: 8-bit grey (CV_8UC1) or BGR (CV_8UC3). `image` may reference
// backend memory kept alive by `hold` (no copy where the pixel format allows).
struct Frame {
  cv::Mat image;
  uint64_t frame_id = 0;
  int64_t timestamp_ns = 0;  // device timestamp where the device has one, else host monotonic
  PixelFormat source_format = PixelFormat::kUnknown;
  std::shared_ptr<void> hold;
};

// Requested settings. Unset fields keep the camera's current value. validate() adjusts a copy to
// what the camera can do (libcamera's Adjusted) or throws Error(kInvalidArgument/kUnsupported)
// naming the camera and the setting (libcamera's Invalid).
struct CameraConfig {
  std::optional<PixelFormat> pixel_format;
  std::optional<cv::Rect> roi;  // width/height (and offset where supported)
  std::optional<double> exposure_us;
  std::optional<double> gain_db;
  std::optional<double> frame_rate_hz;
  int queue_depth = 4;  // frames buffered before the oldest is dropped
};

// The type of a camera setting (GenICam feature node type, V4L2 control type).
enum class FeatureType { kInteger, kFloat, kBoolean, kEnumeration, kString, kCommand };
// "integer", "float", "boolean", "enumeration", "string", "command".
const char* feature_type_name(FeatureType t);

struct FeatureInfo {
  std::string name;
  FeatureType type = FeatureType::kString;
  std::string value;  // current value as text ("" if not readable)
  bool readable = true;
  bool writable = false;
  std::string unit;
  std::string min, max;              // for numbers, "" if none
  std::vector<std::string> options;  // for enumerations/menus
};

struct CameraStats {
  uint64_t frames_delivered = 0;
  uint64_t frames_dropped = 0;     // dropped by the bounded queue (oldest first)
  uint64_t frames_incomplete = 0;  // incomplete/corrupt buffers counted and never passed on
  uint64_t disconnects = 0;
};

enum class CameraState { kOpened, kConfigured, kStreaming, kDisconnected };
const char* camera_state_name(CameraState s);

// kEndOfStream: a finite source (images://) has no more frames.
enum class FrameStatus { kOk, kTimeout, kDisconnected, kEndOfStream };

struct CameraEvent {
  enum class Kind { kDisconnected, kReconnected, kError } kind;
  std::string message;
};
using CameraEventCallback = std::function<void(const CameraEvent&)>;

class Camera {
 public:
  static constexpr int kMaxQueueDepth = 64;

  virtual ~Camera() = default;
  Camera(const Camera&) = delete;
  Camera& operator=(const Camera&) = delete;

  const DeviceInfo& info() const { return info_; }
  CameraState state() const { return followed_ ? followed_->state() : state_.load(); }

  // Settings. validate() never changes the camera.
  CameraConfig current_config();
  CameraConfig validate(const CameraConfig& requested);
  void configure(const CameraConfig& config);

  // Generic feature access (GenICam feature, V4L2 control, ...). Throws Error(kNotFound) for an
  // unknown feature, Error(kInvalidArgument) for a read-only one or a bad value, naming both
  // the camera and the feature.
  std::vector<FeatureInfo> features();
  std::string get_feature(const std::string& name);
  void set_feature(const std::string& name, const std::string& value);

  // Calibration lock: turns automatic exposure/gain/focus off, fixes their current values and
  // returns what was locked (name -> value), recorded in the calibration result.
  std::map<std::string, std::string> lock_for_calibration();

  void start();
  void stop();

  // Waits at most timeout_ms (>= 0; 0: poll) for the next frame. Never blocks longer.
  FrameStatus next_frame(int timeout_ms, Frame* frame);

  CameraStats stats() const { return do_stats(); }
  // Called from a backend thread (disconnects, reconnects); must not call back into the camera.
  void set_event_callback(CameraEventCallback cb);

  // Guided cameras (sim://) receive the engine's current target; others ignore it.
  virtual void guide(const GuidanceInfo& /*guidance*/) {}
  // A guided camera that moves the board itself (a simulated robot) returns true once when it
  // has reached the current target; the session then reports "pose reached" to the engine.
  virtual bool take_pose_reached() { return false; }

 protected:
  // `label` names the camera in messages ("camera '<uri>'" if empty).
  explicit Camera(DeviceInfo info, std::string label = "");

  // The backend's hooks, called after the state check (see the table above).
  virtual CameraConfig do_current_config() = 0;
  // `requested` has a queue depth in [1, kMaxQueueDepth].
  virtual CameraConfig do_validate(const CameraConfig& requested) = 0;
  // `config` comes from validate().
  virtual void do_configure(const CameraConfig& config) = 0;
  virtual std::vector<FeatureInfo> do_features() { return {}; }
  virtual std::string do_get_feature(const std::string& name);                       // kNotFound
  virtual void do_set_feature(const std::string& name, const std::string& value);    // kNotFound
  virtual std::map<std::string, std::string> do_lock_for_calibration() { return {}; }
  virtual void do_start() = 0;
  virtual void do_stop() = 0;
  // stop() while disconnected: a backend that reconnects by itself must not resume streaming.
  virtual void do_stop_while_disconnected() {}
  virtual FrameStatus do_next_frame(int timeout_ms, Frame* frame) = 0;
  virtual CameraStats do_stats() const = 0;

  // For backends, from any thread. The camera is gone: true if it was not disconnected already.
  bool mark_disconnected();
  // The camera is back (a reconnecting backend): the state before the disconnect.
  void mark_reconnected(CameraState state);
  // Delivers an event to the callback (if any), outside the backend's locks.
  void emit_event(const CameraEvent& event) const;
  const std::string& label() const { return label_; }
  // A backend that learns its identity only once open (V4L2's QUERYCAP) sets it here, in its
  // constructor (and the label; empty: "camera '<uri>'").
  void set_info(DeviceInfo info, std::string label = "");
  // A camera that wraps another (a test's decorator) takes the inner camera's state: the checks
  // use it, and the inner camera's own calls make the transitions.
  void follow_state_of(const Camera* inner) { followed_ = inner; }

 private:
  void require(std::initializer_list<CameraState> allowed, const char* call) const;
  // Moves from one of `from` to `to`; throws Error(kDevice) if the camera disconnected meanwhile.
  void transition(std::initializer_list<CameraState> from, CameraState to, const char* call);

  DeviceInfo info_;
  std::string label_;
  std::atomic<CameraState> state_{CameraState::kOpened};
  const Camera* followed_ = nullptr;
  mutable std::mutex callback_mutex_;
  CameraEventCallback callback_;
};

class CameraBackend {
 public:
  virtual ~CameraBackend() = default;
  virtual std::string scheme() const = 0;  // URI scheme it serves
  // Lists cameras present now (an empty list, not an error, when there are none).
  virtual std::vector<DeviceInfo> enumerate() = 0;
  // Opens by URI. Throws Error(kNotFound) naming the URI if there is no such camera.
  virtual std::unique_ptr<Camera> open(const Uri& uri) = 0;
  // Hot-plug: the backend calls `added`/`removed` from its own thread when cameras come and go.
  using HotplugCallback = std::function<void(const DeviceInfo&, bool added)>;
  virtual void set_hotplug_callback(HotplugCallback /*cb*/) {}
};

class CameraManager {
 public:
  CameraManager();
  ~CameraManager();
  // Adds a backend; a later backend with the same scheme replaces the earlier one.
  void add_backend(std::shared_ptr<CameraBackend> backend);
  std::vector<std::string> schemes() const;
  // Cameras of every backend. A backend that fails to enumerate is skipped and its error
  // reported in *errors (if given).
  std::vector<DeviceInfo> list(std::vector<std::string>* errors = nullptr);
  // Throws Error(kInvalidArgument) for an unknown scheme, kNotFound for a missing camera.
  std::unique_ptr<Camera> open(const std::string& uri);
  // Hot-plug events of every backend.
  void set_hotplug_callback(CameraBackend::HotplugCallback cb);

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

// Converts a raw buffer of a camera pixel format to 8-bit grey or BGR for the engine. Mono8 and
// BGR8 are wrapped without copying (the caller keeps `data` alive); Mono16 is scaled by
// `mono16_shift` bits; Bayer is demosaiced; YUYV converted. MJPEG is decoded (returns an empty
// Mat for a corrupt JPEG). Throws Error(kUnsupported) for other formats.
cv::Mat convert_to_engine(PixelFormat format, const void* data, size_t bytes, int width, int height,
                          size_t stride_bytes, int mono16_shift = 8);

}  // namespace posecal
