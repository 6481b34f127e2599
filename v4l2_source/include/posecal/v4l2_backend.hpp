// V4L2 camera backend: UVC webcams (and other video-capture nodes) through the kernel's V4L2 API.
//
//   v4l2://<stable id>      e.g. v4l2://usb-046d_HD_Webcam_C525_0320EC60-video-index0
//   v4l2:///dev/videoN      a node path (also /dev/v4l/by-id/... links)
//
// Layers (docs/v4l2.md):
//   V4l2Backend  enumerate/open by URI, sysfs identity (v4l2_identity.hpp), USB hot-plug
//   V4l2Camera   QUERYCAP, formats, S_FMT/S_PARM, controls, mmap streaming or read(), frames
//   V4l2Io       the system-call seam (v4l2_io.hpp): the kernel, or the tests' UVC emulator
//
// Threading: as posecal::Camera. A camera's event callback is called from the thread that
// called into the camera when the disconnect was noticed (next_frame, a control access...).
// Hot-plug callbacks come from the backend's hot-plug thread; they must not call
// set_hotplug_callback() and should return quickly.
#pragma once

#include <cstdint>
#include <functional>
#include <memory>
#include <string>
#include <vector>

#include "device/camera.hpp"
#include "posecal/v4l2_io.hpp"

namespace posecal {

// A USB hot-plug notification, as libusb reports it.
struct UsbHotplugEvent {
  enum class Kind { kArrived, kLeft } kind = Kind::kArrived;
  int bus = 0;             // libusb_get_bus_number
  std::vector<int> ports;  // libusb_get_port_numbers, root hub port first
  uint16_t vendor_id = 0;
  uint16_t product_id = 0;
  // The kernel's name of the device in /sys/bus/usb/devices: "<bus>-<port>.<port>...", "" for a
  // root hub (no ports).
  std::string sysfs_name() const;
};

// Where hot-plug events come from: libusb in production, a test's fake otherwise.
class UsbEventSource {
 public:
  using Handler = std::function<void(const UsbHotplugEvent&)>;
  virtual ~UsbEventSource() = default;
  // Starts calling `handler` (from the source's own thread). Returns false and sets *why_not if
  // hot-plug notification is not available here.
  virtual bool start(Handler handler, std::string* why_not) = 0;
  // Stops; when it returns the handler is not running and will not be called again.
  virtual void stop() = 0;
};

// libusb hot-plug (libusb_hotplug_register_callback plus an event thread). start() fails with a
// reason where libusb cannot be initialised or lacks LIBUSB_CAP_HAS_HOTPLUG.
std::shared_ptr<UsbEventSource> make_libusb_event_source();

struct V4l2BackendOptions {
  // System-call seam; null selects the kernel (make_system_v4l2_io()).
  std::shared_ptr<V4l2Io> io;
  // Roots of sysfs and of the device nodes; tests point them at fixture trees.
  std::string sysfs_root = "/sys";
  std::string dev_root = "/dev";
  // Hot-plug event source; null selects libusb (make_libusb_event_source()).
  std::shared_ptr<UsbEventSource> usb_events;
  // After a USB camera arrives, how long to wait for uvcvideo to create its video node.
  int hotplug_settle_ms = 3000;
  // Throws Error(kInvalidArgument) naming the offending field.
  void validate() const;
};

// One frame size of a format, with the frame rates the driver lists for it.
struct V4l2FrameSize {
  int width = 0;
  int height = 0;
  // Frame intervals as fractions (seconds per frame = numerator / denominator), fastest first.
  struct Interval {
    uint32_t numerator = 0;
    uint32_t denominator = 0;
    double rate_hz() const { return numerator ? static_cast<double>(denominator) / numerator : 0; }
  };
  std::vector<Interval> intervals;  // discrete intervals
  double min_rate_hz = 0;           // continuous/stepwise intervals: range of rates
  double max_rate_hz = 0;
};

// A pixel format the device offers (VIDIOC_ENUM_FMT + ENUM_FRAMESIZES + ENUM_FRAMEINTERVALS).
struct V4l2Format {
  uint32_t fourcc = 0;
  std::string fourcc_text;                           // "MJPG", "YUYV", "GREY"
  std::string description;                           // the driver's text, e.g. "Motion-JPEG"
  PixelFormat pixel_format = PixelFormat::kUnknown;  // kUnknown: posecal cannot decode it
  bool compressed = false;
  // Discrete sizes, or (stepwise) a range of sizes in `min`/`max`/`step`; for a stepwise format
  // `sizes` holds the extreme sizes with their intervals.
  std::vector<V4l2FrameSize> sizes;
  bool stepwise = false;
  int min_width = 0, max_width = 0, step_width = 1;
  int min_height = 0, max_height = 0, step_height = 1;
};

// A camera opened by the V4L2 backend. Adds V4L2-specific queries to posecal::Camera.
class V4l2Camera : public Camera {
 public:
  // The node path that was opened (after resolving by-id links).
  virtual const std::string& device_path() const = 0;
  // Formats the device offers (enumerated when the camera was opened).
  virtual const std::vector<V4l2Format>& formats() const = 0;
  // True when the device lacks V4L2_CAP_STREAMING and frames are read with read().
  virtual bool uses_read_io() const = 0;

 protected:
  using Camera::Camera;
};

class V4l2Backend final : public CameraBackend {
 public:
  explicit V4l2Backend(V4l2BackendOptions options = {});
  ~V4l2Backend() override;
  V4l2Backend(const V4l2Backend&) = delete;
  V4l2Backend& operator=(const V4l2Backend&) = delete;

  std::string scheme() const override { return "v4l2"; }
  // Video-capture nodes present now (metadata and output nodes are left out).
  std::vector<DeviceInfo> enumerate() override;
  // Opens v4l2://<stable id> or v4l2:///dev/videoN (returns a V4l2Camera). Throws Error(kNotFound)
  // for a missing camera, kInvalidArgument for a node that is not a video-capture device or an
  // ambiguous id, kDevice where the kernel refuses (permissions, busy).
  std::unique_ptr<Camera> open(const Uri& uri) override;
  // Starts (non-null) or stops (null) hot-plug notification. Where hot-plug is unavailable the
  // call succeeds, nothing is ever notified, and hotplug_status() says why.
  void set_hotplug_callback(HotplugCallback cb) override;
  // "" while hot-plug works or was never asked for; otherwise why it is unavailable.
  std::string hotplug_status() const;

 private:
  struct Impl;
  std::shared_ptr<Impl> impl_;
};

// The factory the plugin uses: a V4l2Backend serving scheme "v4l2".
std::shared_ptr<CameraBackend> make_v4l2_backend(const V4l2BackendOptions& options = {});

}  // namespace posecal
