// A userspace emulator of UVC cameras behind posecal's V4l2Io seam.
//
// It answers the system calls the way the kernel's uvcvideo driver and videobuf2 do (V4L2
// specification, "Video Capture Interface", "Streaming I/O (Memory Mapping)", "Read/Write",
// ioctl reference), so the backend above the seam runs unchanged:
//   - QUERYCAP with per-node device_caps (video node vs. UVC metadata node);
//   - ENUM_FMT/ENUM_FRAMESIZES/ENUM_FRAMEINTERVALS; TRY_FMT/S_FMT adjust to the nearest size with
//     uvcvideo's rule and fall back to the first format; S_FMT resets the frame interval;
//     S_FMT/S_PARM/REQBUFS fail with EBUSY while buffers exist or the queue streams;
//   - a buffer queue with owner file handle, QBUF of a queued buffer -> EINVAL, DQBUF on an
//     empty queue of an O_NONBLOCK file -> EAGAIN, STREAMOFF returns every buffer to the app,
//     frames dropped (sequence advances) when no buffer is queued, poll() with EPOLLERR when
//     not streaming and EPOLLIN when a buffer is done; buffer memory outlives REQBUFS(0) and
//     close() while still mapped, as vb2 keeps it;
//   - read() I/O for nodes with V4L2_CAP_READWRITE (capture starts on first read or poll);
//   - controls with ranges, steps (clamped and rounded like uvcvideo), menus with skipped
//     items, control classes, read-only and button controls, automatic modes that make their
//     manual controls inactive (writes -> EACCES) and hand over their value when switched off;
//   - unplug: from then on every call on an open descriptor fails with ENODEV (close and munmap
//     still succeed), poll() reports POLLERR|POLLHUP, the node vanishes (open -> ENOENT).
// Frames are real payloads: a posecal::SyntheticCamera rendering of a ChArUco board, encoded as
// MJPEG (cv::imencode) or packed as YUYV (BT.601 limited range) or GREY, produced at the
// configured frame interval on a steady clock.
//
// It also audits the client: open descriptors, live mappings and bad munmap() calls are
// counted so that tests can assert nothing leaked.
#pragma once

#include <linux/videodev2.h>

#include <condition_variable>
#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <opencv2/core.hpp>
#include <string>
#include <vector>

#include "posecal/v4l2_io.hpp"

namespace posecal::emu {

struct FrameSizeSpec {
  uint32_t width = 0;
  uint32_t height = 0;
  std::vector<uint32_t> fps;  // discrete frame rates (intervals 1/fps), fastest first
};

struct FormatSpec {
  uint32_t fourcc = 0;
  std::string description;
  bool compressed = false;
  std::vector<FrameSizeSpec> sizes;  // discrete sizes; empty: stepwise below
  uint32_t min_width = 0, max_width = 0, step_width = 1;
  uint32_t min_height = 0, max_height = 0, step_height = 1;
  std::vector<uint32_t> stepwise_fps;  // rates offered at every stepwise size
};

struct ControlSpec {
  uint32_t id = 0;
  uint32_t type = V4L2_CTRL_TYPE_INTEGER;
  std::string name;
  int64_t minimum = 0, maximum = 0, step = 1, default_value = 0;
  uint32_t flags = 0;
  std::map<int64_t, std::string> menu;  // valid menu items (indices not listed are skipped)
  // Automatic mode: while control `master` has one of `master_auto_values`, this control is
  // inactive and reads `auto_value` (what the camera's automatics chose).
  uint32_t master = 0;
  std::vector<int64_t> master_auto_values;
  int64_t auto_value = 0;
};

struct DeviceSpec {
  std::string driver = "uvcvideo";
  std::string card;
  std::string bus_info;
  uint32_t device_caps = 0;   // this node
  uint32_t capabilities = 0;  // the whole device (union over its nodes)
  std::vector<FormatSpec> formats;
  std::vector<ControlSpec> controls;
  bool supports_try_fmt = true;
  bool supports_ext_ctrls = true;       // G/S/TRY_EXT_CTRLS
  bool supports_query_ext_ctrl = true;  // QUERY_EXT_CTRL
  bool supports_timeperframe = true;    // G/S_PARM
  uint32_t max_buffers = 32;
};

// Logitech HD Webcam C525 (046d:0826) as uvcvideo on Linux 6.1 presents it.
DeviceSpec c525_video_node();
DeviceSpec c525_metadata_node();
// Microsoft LifeCam HD-3000 (045e:0810): fixed focus, no serial number.
DeviceSpec lifecam_video_node();
DeviceSpec lifecam_metadata_node();
// A made-up monochrome platform camera with read() I/O only (no V4L2_CAP_STREAMING), stepwise
// frame sizes, no TRY_FMT, no extended controls and no frame-rate control: the old-driver paths.
DeviceSpec grey_read_node();

// The payload the emulator sends for an 8-bit grey image in `fourcc` at the image's size: MJPEG
// is the JPEG of the image (cv::imencode, quality 90), YUYV its BT.601 limited-range luma with
// neutral chroma, GREY its rows padded to 32 bytes.
std::vector<uint8_t> encode_payload(uint32_t fourcc, const cv::Mat& grey);

enum class Call { kOpen, kClose, kIoctl, kMmap, kMunmap, kPoll, kRead };
enum class Corruption { kTruncated, kErrorFlag };

class UvcEmulator final : public V4l2Io {
 public:
  UvcEmulator();
  ~UvcEmulator() override;

  // A node at `path`; nodes sharing `usb_device` (e.g. "1-2") are one device and unplug together.
  void add_node(const std::string& path, DeviceSpec spec, const std::string& usb_device);

  // Fault injection.
  void unplug(const std::string& usb_device);
  // Unplugs `usb_device` right before the n-th seam call (1-based, counted over all calls).
  void unplug_before_call(uint64_t n, const std::string& usb_device);
  // Unplugs `usb_device` right before the n-th call of kind `call` (1-based).
  void unplug_before(Call call, int n, const std::string& usb_device);
  // The next `count` frames of the node are corrupt.
  void corrupt_next_frames(const std::string& path, int count, Corruption how);
  // The stream fails: DQBUF/read return `err` (EIO: a USB transfer error), poll() POLLERR.
  void fail_stream(const std::string& path, int err);

  // Frames from a test instead of the fixed scene (closed-loop tests): while streaming with
  // mmap buffers, every frame the sensor puts into a queued buffer is `source(sequence, format)`,
  // the payload in the node's current format (encode_payload). Called under the emulator's lock
  // on the thread that polls or dequeues, so it must not call the emulator. nullptr: the fixed
  // scene. read() I/O always sends the fixed scene.
  using PayloadSource = std::function<std::shared_ptr<const std::vector<uint8_t>>(
      uint32_t sequence, const v4l2_pix_format& format)>;
  void set_payload_source(const std::string& path, PayloadSource source);

  // Audit.
  int open_fds() const;
  int live_mappings() const;
  int bad_munmaps() const;
  uint64_t calls() const;
  uint64_t calls_of(Call call) const;
  // ioctls that change the device (S_FMT, S_PARM, S_CTRL, S_EXT_CTRLS, REQBUFS, QBUF, STREAMON...).
  uint64_t state_changes(const std::string& path) const;
  v4l2_pix_format format(const std::string& path) const;
  double frame_rate(const std::string& path) const;
  int64_t control(const std::string& path, uint32_t id) const;
  bool streaming(const std::string& path) const;
  // The grey scene the node's frames show at the current size (what a perfect decoder returns).
  cv::Mat scene(const std::string& path) const;

  // V4l2Io
  int open(const char* path, int flags) override;
  int close(int fd) override;
  int ioctl(int fd, unsigned long request, void* arg) override;
  void* mmap(void* addr, size_t length, int prot, int flags, int fd, off_t offset) override;
  int munmap(void* addr, size_t length) override;
  int poll(struct pollfd* fds, nfds_t nfds, int timeout_ms) override;
  ssize_t read(int fd, void* buf, size_t count) override;

 private:
  struct Node;
  struct File;
  struct Mapping;
  using Lock = std::unique_lock<std::mutex>;

  void count_call(Call call);  // fault injection hook, with lock held
  void unplug_locked(const std::string& usb_device);
  std::shared_ptr<Node> node_at(const std::string& path) const;
  File* file(int fd);
  int do_ioctl(Lock& lock, int fd, File& f, unsigned long request, void* arg);
  void produce(Node& n);
  short poll_events(Lock& lock, int fd);

  mutable std::mutex mutex_;
  std::condition_variable changed_;
  std::map<std::string, std::shared_ptr<Node>> nodes_;
  std::map<int, std::unique_ptr<File>> files_;
  std::multimap<const void*, std::unique_ptr<Mapping>> mappings_;
  int next_fd_ = 1000;
  int bad_munmaps_ = 0;
  uint64_t calls_ = 0;
  std::map<Call, uint64_t> calls_by_kind_;
  uint64_t unplug_at_call_ = 0;
  std::string unplug_at_call_device_;
  Call unplug_kind_ = Call::kOpen;
  uint64_t unplug_at_kind_ = 0;
  std::string unplug_at_kind_device_;
};

}  // namespace posecal::emu
