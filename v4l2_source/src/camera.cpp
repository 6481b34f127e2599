// V4l2Camera: opening a node, its identity and settings, disconnects (camera_internal.hpp).
#include <fcntl.h>
#include <sys/mman.h>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>
#include <numeric>
#include <optional>
#include <cctype>
#include <system_error>

#include "common/clock.hpp"
#include "common/percent_encoding.hpp"

#include "camera_internal.hpp"

namespace posecal::v4l2 {


int xioctl(V4l2Io& io, int fd, unsigned long request, void* arg) {
  for (int tries = 0; tries < 100; ++tries) {
    if (io.ioctl(fd, request, arg) == 0) return 0;
    if (errno != EINTR) return errno;
  }
  return EINTR;
}

std::string errno_text(int err) { return std::generic_category().message(err); }

uint32_t node_caps(const v4l2_capability& cap) {
  return (cap.capabilities & V4L2_CAP_DEVICE_CAPS) ? cap.device_caps : cap.capabilities;
}

bool is_video_capture(uint32_t caps) { return (caps & V4L2_CAP_VIDEO_CAPTURE) != 0; }

std::string caps_text(uint32_t caps) {
  static const std::pair<uint32_t, const char*> kNames[] = {
      {V4L2_CAP_VIDEO_CAPTURE, "video capture"},
      {V4L2_CAP_VIDEO_CAPTURE_MPLANE, "multi-planar video capture"},
      {V4L2_CAP_VIDEO_OUTPUT, "video output"},
      {V4L2_CAP_VIDEO_OUTPUT_MPLANE, "multi-planar video output"},
      {V4L2_CAP_VIDEO_M2M, "memory-to-memory"},
      {V4L2_CAP_VIDEO_M2M_MPLANE, "multi-planar memory-to-memory"},
      {V4L2_CAP_META_CAPTURE, "metadata capture"},
      {V4L2_CAP_META_OUTPUT, "metadata output"},
      {V4L2_CAP_VBI_CAPTURE, "VBI capture"},
      {V4L2_CAP_SDR_CAPTURE, "SDR capture"},
      {V4L2_CAP_TOUCH, "touch"},
      {V4L2_CAP_RADIO, "radio"},
      {V4L2_CAP_STREAMING, "streaming"},
      {V4L2_CAP_READWRITE, "read/write"},
  };
  std::string out;
  for (const auto& [bit, name] : kNames) {
    if (caps & bit) out += (out.empty() ? "" : ", ") + std::string(name);
  }
  return out.empty() ? "none" : out;
}

std::string fixed_string(const void* bytes, size_t size) {
  const char* c = static_cast<const char*>(bytes);
  return std::string(c, strnlen(c, size));
}

std::string fourcc_text(uint32_t fourcc) {
  std::string s;
  for (int i = 0; i < 4; ++i) {
    const char c = static_cast<char>((fourcc >> (8 * i)) & 0x7F);
    s.push_back(std::isprint(static_cast<unsigned char>(c)) ? c : '?');
  }
  while (!s.empty() && s.back() == ' ') s.pop_back();
  if (fourcc & (1u << 31)) s += "-BE";
  return s;
}

PixelFormat pixel_format_of_fourcc(uint32_t fourcc) {
  switch (fourcc) {
    case V4L2_PIX_FMT_MJPEG:
    case V4L2_PIX_FMT_JPEG:
      return PixelFormat::kMJPEG;
    case V4L2_PIX_FMT_YUYV:
      return PixelFormat::kYUYV;
    case V4L2_PIX_FMT_GREY:
      return PixelFormat::kMono8;
    default:
      return PixelFormat::kUnknown;
  }
}

DeviceInfo make_device_info(const V4l2NodeIdentity& id, const v4l2_capability& cap) {
  DeviceInfo info;
  info.backend = "v4l2";
  const std::string driver = fixed_string(cap.driver, sizeof(cap.driver));
  const std::string card = fixed_string(cap.card, sizeof(cap.card));
  if (!id.stable_id.empty()) {
    info.id = id.stable_id;
    info.uri = "v4l2://" + percent_encode(id.stable_id);
  } else {
    info.id = id.dev_path;
    info.uri = "v4l2://" + percent_encode(id.dev_path);
  }
  if (id.usb) {
    info.vendor = id.manufacturer.empty() ? id.vendor_id : id.manufacturer;
    info.model = id.product.empty() ? card : id.product;
    info.serial = id.serial;
    info.transport = driver == "uvcvideo" ? "USB UVC" : "USB (" + driver + ")";
  } else {
    info.vendor = driver;
    info.model = card;
    info.transport = "V4L2 (" + driver + ")";
  }
  return info;
}

V4l2CameraImpl::V4l2CameraImpl(std::shared_ptr<V4l2Io> io, const V4l2NodeIdentity& identity,
                               const std::string& uri_text)
    : V4l2Camera(DeviceInfo{}), io_(std::move(io)), dev_path_(identity.dev_path), uri_text_(uri_text) {
  DeviceInfo named;
  named.model = identity.name.empty() ? identity.node : identity.name;
  name_camera(named);
  fd_ = io_->open(dev_path_.c_str(), O_RDWR | O_NONBLOCK);
  if (fd_ < 0) {
    const int err = errno;
    if (err == ENOENT || is_gone(err)) {
      throw Error(ErrorCode::kNotFound, uri_text_ + ": no device node " + dev_path_);
    }
    if (err == EACCES || err == EPERM) {
      throw Error(ErrorCode::kDevice, uri_text_ + ": permission denied opening " + dev_path_ +
                                          " (is the user in group 'video'?)");
    }
    throw Error(ErrorCode::kDevice,
                uri_text_ + ": cannot open " + dev_path_ + ": " + errno_text(err));
  }
  try {
    v4l2_capability cap{};
    if (const int err = ioctl(VIDIOC_QUERYCAP, &cap)) {
      if (err == ENOTTY) {
        throw Error(ErrorCode::kInvalidArgument,
                    uri_text_ + ": " + dev_path_ +
                        " is not a V4L2 device (VIDIOC_QUERYCAP: " + errno_text(err) + ")");
      }
      throw Error(is_gone(err) ? ErrorCode::kNotFound : ErrorCode::kDevice,
                  uri_text_ + ": VIDIOC_QUERYCAP on " + dev_path_ + " failed: " + errno_text(err));
    }
    caps_ = node_caps(cap);
    name_camera(make_device_info(identity, cap));
    if (!is_video_capture(caps_)) {
      std::string hint;
      if (caps_ & V4L2_CAP_META_CAPTURE)
        hint = "; it is a metadata node, open the node with index 0";
      if (caps_ & V4L2_CAP_VIDEO_CAPTURE_MPLANE) hint = "; multi-planar capture is not supported";
      throw Error(ErrorCode::kInvalidArgument,
                  uri_text_ + ": " + dev_path_ + " is not a video capture device (driver " +
                      fixed_string(cap.driver, sizeof(cap.driver)) + ", card '" +
                      fixed_string(cap.card, sizeof(cap.card)) +
                      "', capabilities: " + caps_text(caps_) + hint + ")");
    }
    if (!(caps_ & (V4L2_CAP_STREAMING | V4L2_CAP_READWRITE))) {
      throw Error(ErrorCode::kUnsupported,
                  who() + " offers neither streaming nor read() I/O (capabilities: " +
                      caps_text(caps_) + ")");
    }
    read_io_ = !(caps_ & V4L2_CAP_STREAMING);
    enumerate_formats();
    enumerate_controls();
    fmt_ = read_format();
  } catch (...) {
    if (fd_ >= 0) io_->close(fd_);
    fd_ = -1;
    throw;
  }
}

V4l2CameraImpl::~V4l2CameraImpl() {
  if (fd_ < 0) return;
  release_buffers(true);
  io_->close(fd_);
  fd_ = -1;
}

void V4l2CameraImpl::name_camera(DeviceInfo info) {
  const std::string label = "v4l2 camera '" + info.model + "' (" + dev_path_ + ")";
  set_info(std::move(info), label);
}

void V4l2CameraImpl::fail(const std::string& what, int err, ErrorCode code) {
  if (is_gone(err)) {
    disconnect(err, what);
    throw Error(ErrorCode::kDevice,
                who() + " disconnected (" + what + ": " + errno_text(err) + ")");
  }
  throw Error(code, who() + ": " + what + " failed: " + errno_text(err));
}

void V4l2CameraImpl::disconnect(int err, const std::string& during) {
  if (!mark_disconnected()) return;
  release_buffers(false);
  if (fd_ >= 0) io_->close(fd_);
  fd_ = -1;
  ++stats_.disconnects;
  emit_event({CameraEvent::Kind::kDisconnected, who() + " disconnected (" + during + ": " + errno_text(err) + ")"});
}

CameraConfig V4l2CameraImpl::do_current_config() {
  fmt_ = read_format();
  CameraConfig c;
  c.pixel_format = pixel_format_of_fourcc(fmt_.pixelformat);
  c.roi = cv::Rect(0, 0, static_cast<int>(fmt_.width), static_cast<int>(fmt_.height));
  bool settable = false;
  const double rate = read_frame_rate(&settable);
  if (rate > 0) c.frame_rate_hz = rate;
  if (Control* e = find_control(V4L2_CID_EXPOSURE_ABSOLUTE)) {
    c.exposure_us = 100.0 * static_cast<double>(control_value(*e));
  }
  c.queue_depth = queue_depth_;
  return c;
}

// The pixel format validate() takes: the requested one, else the current one if posecal decodes
// it, else the first decodable one the device offers (MJPEG first: full frame rate at high
// resolution over USB 2).
uint32_t V4l2CameraImpl::fourcc_to_use(const CameraConfig& requested, const v4l2_pix_format& cur) const {
  uint32_t fourcc = cur.pixelformat;
  if (requested.pixel_format) fourcc = fourcc_for(*requested.pixel_format);
  if (pixel_format_of_fourcc(fourcc) == PixelFormat::kUnknown) {
    fourcc = 0;
    for (uint32_t c :
         {V4L2_PIX_FMT_MJPEG, V4L2_PIX_FMT_JPEG, V4L2_PIX_FMT_YUYV, V4L2_PIX_FMT_GREY}) {
      if (find_format(c)) {
        fourcc = c;
        break;
      }
    }
    if (!fourcc) {
      throw Error(ErrorCode::kUnsupported, who() + " offers no pixel format posecal can decode");
    }
  }
  return fourcc;
}

// The exposure validate() takes: exposure_time_absolute counts 100 us units, clamped to the
// control's range and snapped to its step.
double V4l2CameraImpl::exposure_to_use(double exposure_us) {
  Control* e = find_control(V4L2_CID_EXPOSURE_ABSOLUTE);
  if (!e) {
    throw Error(ErrorCode::kUnsupported,
                who() + ": exposure cannot be set (no exposure_time_absolute control)");
  }
  if (!(exposure_us > 0) || !std::isfinite(exposure_us)) {
    throw Error(ErrorCode::kInvalidArgument, who() + ": exposure_us must be positive and finite");
  }
  // exposure_time_absolute counts 100 us units.
  const double units = std::clamp(exposure_us / 100.0, static_cast<double>(e->minimum),
                                  static_cast<double>(e->maximum));
  const double step = static_cast<double>(std::max<uint64_t>(e->step, 1));
  const double snapped = static_cast<double>(e->minimum) +
                         std::round((units - static_cast<double>(e->minimum)) / step) * step;
  return 100.0 * std::min(snapped, static_cast<double>(e->maximum));
}

CameraConfig V4l2CameraImpl::do_validate(const CameraConfig& requested) {
  CameraConfig out = requested;
  const v4l2_pix_format cur = read_format();

  const uint32_t fourcc = fourcc_to_use(requested, cur);
  int width = static_cast<int>(cur.width), height = static_cast<int>(cur.height);
  if (requested.roi) {
    if (requested.roi->width <= 0 || requested.roi->height <= 0) {
      throw Error(ErrorCode::kInvalidArgument,
                  who() + ": roi " + std::to_string(requested.roi->width) + "x" +
                      std::to_string(requested.roi->height) + " is empty");
    }
    width = requested.roi->width;
    height = requested.roi->height;
  }
  const v4l2_pix_format adjusted = try_format(fourcc, width, height);
  if (adjusted.pixelformat != fourcc) {
    throw Error(ErrorCode::kUnsupported, who() + ": the driver refuses pixel format " +
                                             fourcc_text(fourcc) + " (offers " +
                                             fourcc_text(adjusted.pixelformat) + ")");
  }
  out.pixel_format = pixel_format_of_fourcc(fourcc);
  // UVC has no sensor cropping: the offset is always 0, the size the nearest the driver offers.
  out.roi = cv::Rect(0, 0, static_cast<int>(adjusted.width), static_cast<int>(adjusted.height));

  if (requested.frame_rate_hz) {
    if (!(*requested.frame_rate_hz > 0) || !std::isfinite(*requested.frame_rate_hz)) {
      throw Error(ErrorCode::kInvalidArgument,
                  who() + ": frame_rate_hz must be positive and finite");
    }
    bool settable = false;
    read_frame_rate(&settable);
    if (!settable) {
      throw Error(ErrorCode::kUnsupported,
                  who() + ": the driver does not let the frame rate be set");
    }
    const auto iv =
        nearest_interval(fourcc, out.roi->width, out.roi->height, *requested.frame_rate_hz);
    if (iv) out.frame_rate_hz = iv->rate_hz();
  }

  if (requested.exposure_us) out.exposure_us = exposure_to_use(*requested.exposure_us);

  if (requested.gain_db) {
    throw Error(ErrorCode::kUnsupported,
                who() + ": V4L2 gain has no unit, gain_db cannot be set; use the 'gain' feature");
  }
  // Camera::validate() has checked the queue depth; the driver's buffer limits adjust it.
  out.queue_depth = std::clamp(requested.queue_depth, kMinBuffers, kMaxBuffers);
  return out;
}

void V4l2CameraImpl::do_configure(const CameraConfig& v) {
  bool settable = false;
  const double previous_rate = read_frame_rate(&settable);

  v4l2_format f{};
  f.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
  f.fmt.pix.pixelformat = fourcc_for(*v.pixel_format);
  f.fmt.pix.width = static_cast<uint32_t>(v.roi->width);
  f.fmt.pix.height = static_cast<uint32_t>(v.roi->height);
  f.fmt.pix.field = V4L2_FIELD_ANY;
  if (const int err = ioctl(VIDIOC_S_FMT, &f)) {
    if (err == EBUSY) {
      throw Error(ErrorCode::kDevice,
                  who() + ": VIDIOC_S_FMT: device busy (another application is streaming from it)");
    }
    fail("VIDIOC_S_FMT", err, ErrorCode::kInvalidArgument);
  }
  fmt_ = f.fmt.pix;

  // uvcvideo resets the frame interval with every S_FMT; keep the previous rate unless a new
  // one was asked for.
  const double rate = v.frame_rate_hz ? *v.frame_rate_hz : previous_rate;
  if (settable && rate > 0) {
    if (const auto iv = nearest_interval(fmt_.pixelformat, static_cast<int>(fmt_.width),
                                         static_cast<int>(fmt_.height), rate)) {
      v4l2_streamparm p{};
      p.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
      p.parm.capture.timeperframe = {iv->numerator, iv->denominator};
      if (const int err = ioctl(VIDIOC_S_PARM, &p)) fail("VIDIOC_S_PARM", err);
    }
  }

  if (v.exposure_us) {
    if (Control* a = find_control(V4L2_CID_EXPOSURE_AUTO)) {
      write_control(*a, V4L2_EXPOSURE_MANUAL, "1");
    }
    Control* e = find_control(V4L2_CID_EXPOSURE_ABSOLUTE);
    const auto units = static_cast<int64_t>(std::llround(*v.exposure_us / 100.0));
    write_control(*e, units, std::to_string(units));
  }
  queue_depth_ = v.queue_depth;
}


std::unique_ptr<V4l2Camera> open_v4l2_camera(std::shared_ptr<V4l2Io> io,
                                             const V4l2NodeIdentity& identity,
                                             const std::string& uri_text) {
  return std::make_unique<V4l2CameraImpl>(std::move(io), identity, uri_text);
}

}  // namespace posecal::v4l2
