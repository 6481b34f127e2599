// Internal to v4l2_source: the V4l2Camera implementation, shared by the files that implement it:
//   camera.cpp     opening the node, identity, settings (validate/configure), disconnects
//   formats.cpp    pixel formats, frame sizes and intervals
//   controls.cpp   controls as features, the calibration lock
//   streaming.cpp  buffers (mmap or read()), start/stop and frames
//
// Follows the V4L2 specification's "Video Capture Interface" and "Streaming I/O (Memory
// Mapping)": QUERYCAP, ENUM_FMT/ENUM_FRAMESIZES/ENUM_FRAMEINTERVALS, TRY_FMT/S_FMT/G_FMT,
// G_PARM/S_PARM, REQBUFS/QUERYBUF/mmap/QBUF/STREAMON, poll + DQBUF, STREAMOFF/REQBUFS(0); read()
// for drivers without V4L2_CAP_STREAMING. Controls through QUERY_EXT_CTRL (QUERYCTRL on older
// drivers), QUERYMENU and G/S_EXT_CTRLS (G/S_CTRL where extended controls are missing).
//
// Resource rule: every mapping and the descriptor are released on stop(), on a disconnect
// (ENODEV anywhere, EIO while streaming) and in the destructor; a failed start() releases what
// it had acquired before it throws.
#pragma once

#include <chrono>
#include <map>
#include <optional>
#include <string>
#include <vector>

#include "v4l2_internal.hpp"

namespace posecal::v4l2 {


using Clock = std::chrono::steady_clock;

constexpr int kMinBuffers = 2;
constexpr int kMaxBuffers = 32;
constexpr int kMaxEnumerations = 1024;  // guards every driver enumeration loop

struct Control {
  uint32_t id = 0;
  uint32_t type = 0;
  std::string name;   // normalised, e.g. "focus_absolute"
  std::string label;  // the driver's, e.g. "Focus, Absolute"
  int64_t minimum = 0, maximum = 0, default_value = 0;
  uint64_t step = 1;
  uint32_t flags = 0;
  std::vector<std::pair<int64_t, std::string>> menu;  // index -> item text
};

struct Mapping {
  void* addr = nullptr;
  size_t length = 0;
};

class V4l2CameraImpl final : public V4l2Camera {
 public:
  V4l2CameraImpl(std::shared_ptr<V4l2Io> io, const V4l2NodeIdentity& identity,
                 const std::string& uri_text);
  ~V4l2CameraImpl() override;

  const std::string& device_path() const override { return dev_path_; }
  const std::vector<V4l2Format>& formats() const override { return formats_; }
  bool uses_read_io() const override { return read_io_; }

 protected:
  // camera.cpp
  CameraConfig do_current_config() override;
  CameraConfig do_validate(const CameraConfig& requested) override;
  void do_configure(const CameraConfig& config) override;
  CameraStats do_stats() const override { return stats_; }
  // controls.cpp
  std::vector<FeatureInfo> do_features() override;
  std::string do_get_feature(const std::string& name) override;
  void do_set_feature(const std::string& name, const std::string& value) override;
  std::map<std::string, std::string> do_lock_for_calibration() override;
  // streaming.cpp
  void do_start() override;
  void do_stop() override;
  FrameStatus do_next_frame(int timeout_ms, Frame* frame) override;

 private:
  std::string who() const { return label(); }
  void name_camera(DeviceInfo info);  // sets the info and the label "v4l2 camera 'MODEL' (PATH)"
  int ioctl(unsigned long request, void* arg) { return xioctl(*io_, fd_, request, arg); }
  // An ioctl failed: a vanished device disconnects the camera; either way throws Error.
  [[noreturn]] void fail(const std::string& what, int err, ErrorCode code = ErrorCode::kDevice);
  void disconnect(int err, const std::string& during);

  void open_node();
  void enumerate_formats();
  void frame_intervals(uint32_t fourcc, int width, int height, V4l2FrameSize* size);
  void enumerate_controls();
  bool query_control(uint32_t id_and_flags, Control* out, int* err);
  void refresh_flags(Control* c);
  v4l2_pix_format read_format();
  double read_frame_rate(bool* settable);

  const V4l2Format* find_format(uint32_t fourcc) const;
  uint32_t fourcc_to_use(const CameraConfig& requested, const v4l2_pix_format& current) const;
  double exposure_to_use(double exposure_us);
  uint32_t fourcc_for(PixelFormat f) const;
  v4l2_pix_format try_format(uint32_t fourcc, int width, int height);
  std::optional<V4l2FrameSize::Interval> nearest_interval(uint32_t fourcc, int width, int height,
                                                          double rate_hz);

  Control* find_control(const std::string& name);
  Control* find_control(uint32_t id);
  int64_t control_value(const Control& c);
  std::string control_text(const Control& c);
  void write_control(Control& c, int64_t value, const std::string& text);
  int64_t parse_control_value(const Control& c, const std::string& text);

  void release_buffers(bool device_alive);
  void reopen_for_read_io();
  std::optional<FrameStatus> read_frame(bool error_reported, Frame* frame);
  std::optional<FrameStatus> dequeue_frame(bool error_reported, Frame* frame);
  bool deliver(const uint8_t* data, size_t bytes, uint64_t frame_id, int64_t timestamp_ns,
               Frame* frame);

  std::shared_ptr<V4l2Io> io_;
  std::string dev_path_;
  std::string uri_text_;
  int fd_ = -1;

  uint32_t caps_ = 0;
  bool read_io_ = false;
  bool ext_ctrls_ = true;       // G/S_EXT_CTRLS available (else G/S_CTRL)
  bool query_ext_ctrl_ = true;  // QUERY_EXT_CTRL available (else QUERYCTRL)
  std::vector<V4l2Format> formats_;
  std::vector<Control> controls_;

  v4l2_pix_format fmt_{};
  int queue_depth_ = 4;
  std::vector<Mapping> buffers_;
  bool buffers_allocated_ = false;  // REQBUFS granted buffers (REQBUFS(0) gives them back)
  bool stream_on_ = false;
  std::vector<uint8_t> read_buffer_;
  uint64_t read_frames_ = 0;
  std::optional<uint32_t> last_sequence_;

  CameraStats stats_;
};
}  // namespace posecal::v4l2
