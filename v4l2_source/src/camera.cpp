// V4l2Camera: one video-capture node driven through the V4l2Io seam.
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
#include <fcntl.h>
#include <sys/mman.h>

#include <algorithm>
#include <charconv>
#include <chrono>
#include <cmath>
#include <cstring>
#include <limits>
#include <mutex>
#include <numeric>
#include <optional>
#include <system_error>

#include "v4l2_internal.hpp"

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

namespace {

std::string uri_escape(const std::string& s) {
  std::string out;
  for (char c : s) {
    if (c == '%' || c == '?') {
      static const char* kHex = "0123456789ABCDEF";
      out += '%';
      out += kHex[(static_cast<unsigned char>(c) >> 4) & 0xF];
      out += kHex[static_cast<unsigned char>(c) & 0xF];
    } else {
      out += c;
    }
  }
  return out;
}

}  // namespace

DeviceInfo make_device_info(const V4l2NodeIdentity& id, const v4l2_capability& cap) {
  DeviceInfo info;
  info.backend = "v4l2";
  const std::string driver = fixed_string(cap.driver, sizeof(cap.driver));
  const std::string card = fixed_string(cap.card, sizeof(cap.card));
  if (!id.stable_id.empty()) {
    info.id = id.stable_id;
    info.uri = "v4l2://" + uri_escape(id.stable_id);
  } else {
    info.id = id.dev_path;
    info.uri = "v4l2://" + uri_escape(id.dev_path);
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

namespace {

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

int64_t host_monotonic_ns() {
  timespec ts{};
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return static_cast<int64_t>(ts.tv_sec) * 1000000000LL + ts.tv_nsec;
}

bool parse_int64(const std::string& s, int64_t* v) {
  const char* b = s.data();
  const char* e = s.data() + s.size();
  if (b != e && *b == '+') ++b;
  const auto r = std::from_chars(b, e, *v);
  return r.ec == std::errc() && r.ptr == e && b != e;
}

const char* control_type_name(uint32_t type) {
  switch (type) {
    case V4L2_CTRL_TYPE_INTEGER:
    case V4L2_CTRL_TYPE_INTEGER64:
    case V4L2_CTRL_TYPE_BITMASK:
      return "integer";
    case V4L2_CTRL_TYPE_BOOLEAN:
      return "boolean";
    case V4L2_CTRL_TYPE_MENU:
    case V4L2_CTRL_TYPE_INTEGER_MENU:
      return "enumeration";
    case V4L2_CTRL_TYPE_BUTTON:
      return "command";
    case V4L2_CTRL_TYPE_STRING:
      return "string";
    default:
      return "unknown";
  }
}

const char* control_unit(uint32_t id) {
  switch (id) {
    case V4L2_CID_EXPOSURE_ABSOLUTE:
      return "100 us";
    case V4L2_CID_WHITE_BALANCE_TEMPERATURE:
      return "K";
    case V4L2_CID_PAN_ABSOLUTE:
    case V4L2_CID_TILT_ABSOLUTE:
      return "arcsec";
    default:
      return "";
  }
}

class V4l2CameraImpl final : public V4l2Camera {
 public:
  V4l2CameraImpl(std::shared_ptr<V4l2Io> io, const V4l2NodeIdentity& identity,
                 const std::string& uri_text);
  ~V4l2CameraImpl() override;

  const DeviceInfo& info() const override { return info_; }
  CameraState state() const override { return state_; }
  CameraConfig current_config() override;
  CameraConfig validate(const CameraConfig& requested) override;
  void configure(const CameraConfig& config) override;
  std::vector<FeatureInfo> features() override;
  std::string get_feature(const std::string& name) override;
  void set_feature(const std::string& name, const std::string& value) override;
  std::map<std::string, std::string> lock_for_calibration() override;
  void start() override;
  void stop() override;
  FrameStatus next_frame(int timeout_ms, Frame* frame) override;
  CameraStats stats() const override { return stats_; }
  void set_event_callback(CameraEventCallback cb) override {
    std::lock_guard<std::mutex> lock(callback_mutex_);
    callback_ = std::move(cb);
  }

  const std::string& device_path() const override { return dev_path_; }
  const std::vector<V4l2Format>& formats() const override { return formats_; }
  bool uses_read_io() const override { return read_io_; }

 private:
  std::string who() const { return "v4l2 camera '" + info_.model + "' (" + dev_path_ + ")"; }
  void require_state(std::initializer_list<CameraState> allowed, const char* call) const;
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
  bool deliver(const uint8_t* data, size_t bytes, uint64_t frame_id, int64_t timestamp_ns,
               Frame* frame);

  std::shared_ptr<V4l2Io> io_;
  std::string dev_path_;
  std::string uri_text_;
  DeviceInfo info_;
  int fd_ = -1;
  CameraState state_ = CameraState::kOpened;

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
  std::mutex callback_mutex_;
  CameraEventCallback callback_;
};

V4l2CameraImpl::V4l2CameraImpl(std::shared_ptr<V4l2Io> io, const V4l2NodeIdentity& identity,
                               const std::string& uri_text)
    : io_(std::move(io)), dev_path_(identity.dev_path), uri_text_(uri_text) {
  info_.model = identity.name.empty() ? identity.node : identity.name;
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
    info_ = make_device_info(identity, cap);
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

void V4l2CameraImpl::require_state(std::initializer_list<CameraState> allowed,
                                   const char* call) const {
  for (CameraState s : allowed) {
    if (s == state_) return;
  }
  throw Error(ErrorCode::kState,
              who() + ": " + call + "() is not allowed while " + camera_state_name(state_));
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
  if (state_ == CameraState::kDisconnected) return;
  release_buffers(false);
  if (fd_ >= 0) io_->close(fd_);
  fd_ = -1;
  state_ = CameraState::kDisconnected;
  ++stats_.disconnects;
  CameraEventCallback cb;
  {
    std::lock_guard<std::mutex> lock(callback_mutex_);
    cb = callback_;
  }
  if (cb) {
    cb({CameraEvent::Kind::kDisconnected,
        who() + " disconnected (" + during + ": " + errno_text(err) + ")"});
  }
}

// ---------------------------------------------------------------------------------------------
// Formats

void V4l2CameraImpl::enumerate_formats() {
  formats_.clear();
  for (uint32_t i = 0; i < kMaxEnumerations; ++i) {
    v4l2_fmtdesc d{};
    d.index = i;
    d.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    if (const int err = ioctl(VIDIOC_ENUM_FMT, &d)) {
      if (err == EINVAL) break;
      fail("VIDIOC_ENUM_FMT", err);
    }
    V4l2Format f;
    f.fourcc = d.pixelformat;
    f.fourcc_text = fourcc_text(d.pixelformat);
    f.description = fixed_string(d.description, sizeof(d.description));
    f.pixel_format = pixel_format_of_fourcc(d.pixelformat);
    f.compressed = (d.flags & V4L2_FMT_FLAG_COMPRESSED) != 0;
    for (uint32_t j = 0; j < kMaxEnumerations; ++j) {
      v4l2_frmsizeenum s{};
      s.index = j;
      s.pixel_format = f.fourcc;
      if (const int err = ioctl(VIDIOC_ENUM_FRAMESIZES, &s)) {
        if (err == EINVAL || err == ENOTTY) break;
        fail("VIDIOC_ENUM_FRAMESIZES", err);
      }
      if (s.type == V4L2_FRMSIZE_TYPE_DISCRETE) {
        V4l2FrameSize size;
        size.width = static_cast<int>(s.discrete.width);
        size.height = static_cast<int>(s.discrete.height);
        frame_intervals(f.fourcc, size.width, size.height, &size);
        f.sizes.push_back(size);
        continue;
      }
      // Stepwise or continuous: one entry describes every size.
      f.stepwise = true;
      f.min_width = static_cast<int>(s.stepwise.min_width);
      f.max_width = static_cast<int>(s.stepwise.max_width);
      f.min_height = static_cast<int>(s.stepwise.min_height);
      f.max_height = static_cast<int>(s.stepwise.max_height);
      const bool continuous = s.type == V4L2_FRMSIZE_TYPE_CONTINUOUS;
      f.step_width = continuous ? 1 : std::max(1, static_cast<int>(s.stepwise.step_width));
      f.step_height = continuous ? 1 : std::max(1, static_cast<int>(s.stepwise.step_height));
      for (const auto& [w, h] :
           {std::pair{f.min_width, f.min_height}, {f.max_width, f.max_height}}) {
        V4l2FrameSize size;
        size.width = w;
        size.height = h;
        frame_intervals(f.fourcc, w, h, &size);
        f.sizes.push_back(size);
      }
      break;
    }
    formats_.push_back(std::move(f));
  }
}

void V4l2CameraImpl::frame_intervals(uint32_t fourcc, int width, int height, V4l2FrameSize* size) {
  size->intervals.clear();
  size->min_rate_hz = size->max_rate_hz = 0;
  for (uint32_t k = 0; k < kMaxEnumerations; ++k) {
    v4l2_frmivalenum e{};
    e.index = k;
    e.pixel_format = fourcc;
    e.width = static_cast<uint32_t>(width);
    e.height = static_cast<uint32_t>(height);
    if (const int err = ioctl(VIDIOC_ENUM_FRAMEINTERVALS, &e)) {
      if (err == EINVAL || err == ENOTTY) break;
      fail("VIDIOC_ENUM_FRAMEINTERVALS", err);
    }
    if (e.type == V4L2_FRMIVAL_TYPE_DISCRETE) {
      if (e.discrete.numerator && e.discrete.denominator) {
        size->intervals.push_back({e.discrete.numerator, e.discrete.denominator});
      }
      continue;
    }
    const auto rate = [](const v4l2_fract& f) {
      return f.numerator ? static_cast<double>(f.denominator) / f.numerator : 0.0;
    };
    size->min_rate_hz = rate(e.stepwise.max);
    size->max_rate_hz = rate(e.stepwise.min);
    break;
  }
  std::sort(size->intervals.begin(), size->intervals.end(),
            [](const auto& a, const auto& b) { return a.rate_hz() > b.rate_hz(); });
}

v4l2_pix_format V4l2CameraImpl::read_format() {
  v4l2_format f{};
  f.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
  if (const int err = ioctl(VIDIOC_G_FMT, &f)) fail("VIDIOC_G_FMT", err);
  return f.fmt.pix;
}

double V4l2CameraImpl::read_frame_rate(bool* settable) {
  v4l2_streamparm p{};
  p.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
  *settable = false;
  if (const int err = ioctl(VIDIOC_G_PARM, &p)) {
    if (err == ENOTTY || err == EINVAL) return 0;
    fail("VIDIOC_G_PARM", err);
  }
  *settable = (p.parm.capture.capability & V4L2_CAP_TIMEPERFRAME) != 0;
  const v4l2_fract& t = p.parm.capture.timeperframe;
  return t.numerator ? static_cast<double>(t.denominator) / t.numerator : 0;
}

const V4l2Format* V4l2CameraImpl::find_format(uint32_t fourcc) const {
  for (const auto& f : formats_) {
    if (f.fourcc == fourcc) return &f;
  }
  return nullptr;
}

uint32_t V4l2CameraImpl::fourcc_for(PixelFormat pf) const {
  std::vector<uint32_t> candidates;
  switch (pf) {
    case PixelFormat::kMJPEG:
      candidates = {V4L2_PIX_FMT_MJPEG, V4L2_PIX_FMT_JPEG};
      break;
    case PixelFormat::kYUYV:
      candidates = {V4L2_PIX_FMT_YUYV};
      break;
    case PixelFormat::kMono8:
      candidates = {V4L2_PIX_FMT_GREY};
      break;
    default:
      break;
  }
  for (uint32_t c : candidates) {
    if (find_format(c)) return c;
  }
  std::string offered;
  for (const auto& f : formats_) {
    if (f.pixel_format != PixelFormat::kUnknown) {
      offered += (offered.empty() ? "" : ", ") + std::string(pixel_format_name(f.pixel_format));
    }
  }
  throw Error(ErrorCode::kUnsupported,
              who() + ": pixel format " + pixel_format_name(pf) +
                  " is not supported (supported: " + (offered.empty() ? "none" : offered) + ")");
}

v4l2_pix_format V4l2CameraImpl::try_format(uint32_t fourcc, int width, int height) {
  v4l2_format f{};
  f.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
  f.fmt.pix.pixelformat = fourcc;
  f.fmt.pix.width = static_cast<uint32_t>(std::max(width, 0));
  f.fmt.pix.height = static_cast<uint32_t>(std::max(height, 0));
  f.fmt.pix.field = V4L2_FIELD_ANY;
  const int err = ioctl(VIDIOC_TRY_FMT, &f);
  if (err == 0) return f.fmt.pix;
  if (err != ENOTTY) fail("VIDIOC_TRY_FMT", err);
  // No TRY_FMT (optional before Linux 5.x for some drivers): pick the nearest listed size with
  // uvcvideo's rule, the smallest difference in covered area.
  const V4l2Format* fmt = find_format(fourcc);
  v4l2_pix_format out{};
  out.pixelformat = fourcc;
  out.width = f.fmt.pix.width;
  out.height = f.fmt.pix.height;
  if (fmt && fmt->stepwise) {
    const auto snap = [](int v, int lo, int hi, int step) {
      v = std::clamp(v, lo, hi);
      return std::min(lo + (v - lo + step / 2) / step * step, hi);
    };
    out.width = static_cast<uint32_t>(snap(width, fmt->min_width, fmt->max_width, fmt->step_width));
    out.height =
        static_cast<uint32_t>(snap(height, fmt->min_height, fmt->max_height, fmt->step_height));
  } else if (fmt && !fmt->sizes.empty()) {
    int64_t best = std::numeric_limits<int64_t>::max();
    for (const auto& s : fmt->sizes) {
      const int64_t covered = int64_t{std::min(width, s.width)} * std::min(height, s.height);
      const int64_t d = int64_t{width} * height + int64_t{s.width} * s.height - 2 * covered;
      if (d < best) {
        best = d;
        out.width = static_cast<uint32_t>(s.width);
        out.height = static_cast<uint32_t>(s.height);
      }
    }
  }
  return out;
}

std::optional<V4l2FrameSize::Interval> V4l2CameraImpl::nearest_interval(uint32_t fourcc, int width,
                                                                        int height,
                                                                        double rate_hz) {
  V4l2FrameSize size;
  frame_intervals(fourcc, width, height, &size);
  if (!size.intervals.empty()) {
    const auto best = std::min_element(
        size.intervals.begin(), size.intervals.end(), [&](const auto& a, const auto& b) {
          return std::abs(a.rate_hz() - rate_hz) < std::abs(b.rate_hz() - rate_hz);
        });
    return *best;
  }
  double r = rate_hz;
  if (size.max_rate_hz > 0) r = std::clamp(r, size.min_rate_hz, size.max_rate_hz);
  if (!(r > 0)) return std::nullopt;
  // Interval in 1/1000 s steps is finer than any UVC descriptor (100 ns units, but rates are
  // whole or NTSC fractions); reduce the fraction.
  uint32_t num = 1000, den = static_cast<uint32_t>(std::lround(r * 1000));
  const uint32_t g = std::gcd(num, den);
  return V4l2FrameSize::Interval{num / g, den / g};
}

CameraConfig V4l2CameraImpl::current_config() {
  require_state({CameraState::kOpened, CameraState::kConfigured, CameraState::kStreaming},
                "current_config");
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

CameraConfig V4l2CameraImpl::validate(const CameraConfig& requested) {
  require_state({CameraState::kOpened, CameraState::kConfigured, CameraState::kStreaming},
                "validate");
  CameraConfig out = requested;
  const v4l2_pix_format cur = read_format();

  uint32_t fourcc = cur.pixelformat;
  if (requested.pixel_format) fourcc = fourcc_for(*requested.pixel_format);
  if (pixel_format_of_fourcc(fourcc) == PixelFormat::kUnknown) {
    // The device is in a format posecal cannot decode and none was asked for: take the first
    // decodable one, MJPEG first (full frame rate at high resolution over USB 2).
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

  if (requested.exposure_us) {
    Control* e = find_control(V4L2_CID_EXPOSURE_ABSOLUTE);
    if (!e) {
      throw Error(ErrorCode::kUnsupported,
                  who() + ": exposure cannot be set (no exposure_time_absolute control)");
    }
    if (!(*requested.exposure_us > 0) || !std::isfinite(*requested.exposure_us)) {
      throw Error(ErrorCode::kInvalidArgument, who() + ": exposure_us must be positive and finite");
    }
    // exposure_time_absolute counts 100 us units.
    const double units = std::clamp(*requested.exposure_us / 100.0, static_cast<double>(e->minimum),
                                    static_cast<double>(e->maximum));
    const double step = static_cast<double>(std::max<uint64_t>(e->step, 1));
    const double snapped = static_cast<double>(e->minimum) +
                           std::round((units - static_cast<double>(e->minimum)) / step) * step;
    out.exposure_us = 100.0 * std::min(snapped, static_cast<double>(e->maximum));
  }

  if (requested.gain_db) {
    throw Error(ErrorCode::kUnsupported,
                who() + ": V4L2 gain has no unit, gain_db cannot be set; use the 'gain' feature");
  }
  if (requested.queue_depth < 1) {
    throw Error(ErrorCode::kInvalidArgument, who() + ": queue_depth must be at least 1");
  }
  out.queue_depth = std::clamp(requested.queue_depth, kMinBuffers, kMaxBuffers);
  return out;
}

void V4l2CameraImpl::configure(const CameraConfig& config) {
  require_state({CameraState::kOpened, CameraState::kConfigured}, "configure");
  const CameraConfig v = validate(config);
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
  state_ = CameraState::kConfigured;
}

// ---------------------------------------------------------------------------------------------
// Controls

bool V4l2CameraImpl::query_control(uint32_t id_and_flags, Control* out, int* err) {
  if (query_ext_ctrl_) {
    v4l2_query_ext_ctrl q{};
    q.id = id_and_flags;
    *err = ioctl(VIDIOC_QUERY_EXT_CTRL, &q);
    if (*err == ENOTTY) {
      query_ext_ctrl_ = false;
    } else if (*err) {
      return false;
    } else {
      out->id = q.id;
      out->type = q.type;
      out->label = fixed_string(q.name, sizeof(q.name));
      out->minimum = q.minimum;
      out->maximum = q.maximum;
      out->step = q.step;
      out->default_value = q.default_value;
      out->flags = q.flags;
      return true;
    }
  }
  v4l2_queryctrl q{};
  // QUERYCTRL knows no compound controls; NEXT_COMPOUND would make old drivers fail.
  q.id = id_and_flags & ~V4L2_CTRL_FLAG_NEXT_COMPOUND;
  *err = ioctl(VIDIOC_QUERYCTRL, &q);
  if (*err) return false;
  out->id = q.id;
  out->type = q.type;
  out->label = fixed_string(q.name, sizeof(q.name));
  out->minimum = q.minimum;
  out->maximum = q.maximum;
  out->step = static_cast<uint64_t>(std::max(q.step, 0));
  out->default_value = q.default_value;
  out->flags = q.flags;
  return true;
}

void V4l2CameraImpl::enumerate_controls() {
  controls_.clear();
  uint32_t id = 0;
  for (int n = 0; n < kMaxEnumerations; ++n) {
    Control c;
    int err = 0;
    if (!query_control(id | V4L2_CTRL_FLAG_NEXT_CTRL | V4L2_CTRL_FLAG_NEXT_COMPOUND, &c, &err)) {
      if (err == EINVAL || err == ENOTTY) break;
      fail("VIDIOC_QUERY_EXT_CTRL", err);
    }
    if (c.id <= id) break;  // a driver that ignores NEXT_CTRL would loop forever
    id = c.id;
    if (c.type == V4L2_CTRL_TYPE_CTRL_CLASS || (c.flags & V4L2_CTRL_FLAG_DISABLED) ||
        c.type >= V4L2_CTRL_COMPOUND_TYPES) {
      continue;
    }
    if (c.type == V4L2_CTRL_TYPE_MENU || c.type == V4L2_CTRL_TYPE_INTEGER_MENU) {
      for (int64_t i = std::max<int64_t>(c.minimum, 0); i <= c.maximum && i - c.minimum < 256;
           ++i) {
        v4l2_querymenu m{};
        m.id = c.id;
        m.index = static_cast<uint32_t>(i);
        if (const int e = ioctl(VIDIOC_QUERYMENU, &m)) {
          if (e == EINVAL) continue;  // an index the driver skips (menu_skip_mask)
          fail("VIDIOC_QUERYMENU", e);
        }
        c.menu.emplace_back(i, c.type == V4L2_CTRL_TYPE_MENU ? fixed_string(m.name, sizeof(m.name))
                                                             : std::to_string(m.value));
      }
    }
    std::string name = v4l2_control_name(c.label);
    if (name.empty()) name = "control_" + std::to_string(c.id);
    std::string unique = name;
    for (int k = 2; find_control(unique); ++k) unique = name + "_" + std::to_string(k);
    c.name = unique;
    controls_.push_back(std::move(c));
  }
}

void V4l2CameraImpl::refresh_flags(Control* c) {
  Control fresh;
  int err = 0;
  if (query_control(c->id, &fresh, &err)) {
    c->flags = fresh.flags;
  } else if (is_gone(err)) {
    fail("VIDIOC_QUERY_EXT_CTRL", err);
  }
}

Control* V4l2CameraImpl::find_control(const std::string& name) {
  for (auto& c : controls_) {
    if (c.name == name) return &c;
  }
  return nullptr;
}

Control* V4l2CameraImpl::find_control(uint32_t id) {
  for (auto& c : controls_) {
    if (c.id == id) return &c;
  }
  return nullptr;
}

int64_t V4l2CameraImpl::control_value(const Control& c) {
  if (ext_ctrls_) {
    v4l2_ext_control ec{};
    ec.id = c.id;
    v4l2_ext_controls cs{};
    cs.which = V4L2_CTRL_ID2WHICH(c.id);  // the control's class: accepted by every kernel
    cs.count = 1;
    cs.controls = &ec;
    const int err = ioctl(VIDIOC_G_EXT_CTRLS, &cs);
    if (err == 0) return c.type == V4L2_CTRL_TYPE_INTEGER64 ? ec.value64 : ec.value;
    if (err != ENOTTY) fail("VIDIOC_G_EXT_CTRLS(" + c.name + ")", err);
    ext_ctrls_ = false;
  }
  if (c.type == V4L2_CTRL_TYPE_INTEGER64) {
    throw Error(ErrorCode::kUnsupported, who() + ": 64-bit control '" + c.name +
                                             "' needs extended controls, which the driver lacks");
  }
  v4l2_control ctl{};
  ctl.id = c.id;
  if (const int err = ioctl(VIDIOC_G_CTRL, &ctl)) fail("VIDIOC_G_CTRL(" + c.name + ")", err);
  return ctl.value;
}

std::string V4l2CameraImpl::control_text(const Control& c) {
  if (c.type == V4L2_CTRL_TYPE_STRING) {
    std::vector<char> buf(static_cast<size_t>(std::max<int64_t>(c.maximum, 0)) + 1, '\0');
    v4l2_ext_control ec{};
    ec.id = c.id;
    ec.size = static_cast<uint32_t>(buf.size());
    ec.string = buf.data();
    v4l2_ext_controls cs{};
    cs.which = V4L2_CTRL_ID2WHICH(c.id);
    cs.count = 1;
    cs.controls = &ec;
    if (const int err = ioctl(VIDIOC_G_EXT_CTRLS, &cs))
      fail("VIDIOC_G_EXT_CTRLS(" + c.name + ")", err);
    return fixed_string(buf.data(), buf.size());
  }
  return std::to_string(control_value(c));
}

int64_t V4l2CameraImpl::parse_control_value(const Control& c, const std::string& text) {
  const auto invalid = [&](const std::string& why) {
    return Error(ErrorCode::kInvalidArgument, who() + ": control '" + c.name + "': " + why);
  };
  int64_t v = 0;
  switch (c.type) {
    case V4L2_CTRL_TYPE_BOOLEAN: {
      if (text == "1" || text == "true" || text == "on" || text == "yes") return 1;
      if (text == "0" || text == "false" || text == "off" || text == "no") return 0;
      throw invalid("'" + text + "' is not a boolean (0/1, true/false, on/off)");
    }
    case V4L2_CTRL_TYPE_MENU:
    case V4L2_CTRL_TYPE_INTEGER_MENU: {
      bool numeric = parse_int64(text, &v);
      if (!numeric) {
        for (const auto& [index, item] : c.menu) {
          if (item == text || v4l2_control_name(item) == v4l2_control_name(text)) {
            v = index;
            numeric = true;
          }
        }
      }
      std::string items;
      for (const auto& [index, item] : c.menu) {
        items += (items.empty() ? "" : ", ") + std::to_string(index) + ": " + item;
      }
      if (!numeric) throw invalid("'" + text + "' is not one of its items (" + items + ")");
      const bool valid =
          std::any_of(c.menu.begin(), c.menu.end(), [&](const auto& m) { return m.first == v; });
      if (!valid) {
        throw invalid("value " + std::to_string(v) + " is out of range (items: " + items + ")");
      }
      return v;
    }
    case V4L2_CTRL_TYPE_BUTTON:
      return 1;
    default: {
      if (!parse_int64(text, &v)) throw invalid("'" + text + "' is not an integer");
      if (v < c.minimum || v > c.maximum) {
        throw invalid("value " + std::to_string(v) + " is out of range [" +
                      std::to_string(c.minimum) + ", " + std::to_string(c.maximum) + "]");
      }
      return v;
    }
  }
}

void V4l2CameraImpl::write_control(Control& c, int64_t value, const std::string& text) {
  if (c.flags & V4L2_CTRL_FLAG_READ_ONLY) {
    throw Error(ErrorCode::kInvalidArgument, who() + ": control '" + c.name + "' is read-only");
  }
  int err = ENOTTY;
  if (ext_ctrls_ || c.type == V4L2_CTRL_TYPE_STRING) {
    v4l2_ext_control ec{};
    ec.id = c.id;
    std::string s = text;
    if (c.type == V4L2_CTRL_TYPE_STRING) {
      if (static_cast<int64_t>(s.size()) < c.minimum ||
          static_cast<int64_t>(s.size()) > c.maximum) {
        throw Error(ErrorCode::kInvalidArgument,
                    who() + ": control '" + c.name + "': length " + std::to_string(s.size()) +
                        " is out of range [" + std::to_string(c.minimum) + ", " +
                        std::to_string(c.maximum) + "]");
      }
      ec.size = static_cast<uint32_t>(s.size() + 1);
      ec.string = s.data();
    } else if (c.type == V4L2_CTRL_TYPE_INTEGER64) {
      ec.value64 = value;
    } else {
      ec.value = static_cast<int32_t>(value);
    }
    v4l2_ext_controls cs{};
    cs.which = V4L2_CTRL_ID2WHICH(c.id);
    cs.count = 1;
    cs.controls = &ec;
    err = ioctl(VIDIOC_S_EXT_CTRLS, &cs);
    if (err == ENOTTY && c.type != V4L2_CTRL_TYPE_STRING) ext_ctrls_ = false;
  }
  if (err == ENOTTY && !ext_ctrls_ && c.type != V4L2_CTRL_TYPE_STRING &&
      c.type != V4L2_CTRL_TYPE_INTEGER64) {
    v4l2_control ctl{};
    ctl.id = c.id;
    ctl.value = static_cast<int32_t>(value);
    err = ioctl(VIDIOC_S_CTRL, &ctl);
  }
  if (err == 0) return;
  if (is_gone(err)) fail("set control '" + c.name + "'", err);
  if (err == EACCES) {
    refresh_flags(&c);
    throw Error(ErrorCode::kInvalidArgument,
                who() + ": control '" + c.name + "' cannot be written now" +
                    ((c.flags & V4L2_CTRL_FLAG_INACTIVE)
                         ? " (inactive: its automatic mode is on, e.g. auto_exposure or "
                           "focus_automatic_continuous)"
                         : " (" + errno_text(err) + ")"));
  }
  if (err == ERANGE || err == EINVAL) {
    throw Error(ErrorCode::kInvalidArgument, who() + ": control '" + c.name + "' rejects value " +
                                                 text + " (" + errno_text(err) + ")");
  }
  throw Error(ErrorCode::kDevice,
              who() + ": setting control '" + c.name + "' failed: " + errno_text(err));
}

std::vector<FeatureInfo> V4l2CameraImpl::features() {
  require_state({CameraState::kOpened, CameraState::kConfigured, CameraState::kStreaming},
                "features");
  std::vector<FeatureInfo> out;
  for (auto& c : controls_) {
    refresh_flags(&c);
    FeatureInfo f;
    f.name = c.name;
    f.type = control_type_name(c.type);
    f.readable = c.type != V4L2_CTRL_TYPE_BUTTON && !(c.flags & V4L2_CTRL_FLAG_WRITE_ONLY);
    f.writable = !(c.flags & (V4L2_CTRL_FLAG_READ_ONLY | V4L2_CTRL_FLAG_INACTIVE));
    f.unit = control_unit(c.id);
    if (f.readable) f.value = control_text(c);
    if (c.type == V4L2_CTRL_TYPE_INTEGER || c.type == V4L2_CTRL_TYPE_INTEGER64 ||
        c.type == V4L2_CTRL_TYPE_BOOLEAN || c.type == V4L2_CTRL_TYPE_BITMASK) {
      f.min = std::to_string(c.minimum);
      f.max = std::to_string(c.maximum);
    }
    for (const auto& [index, item] : c.menu)
      f.options.push_back(std::to_string(index) + ": " + item);
    out.push_back(std::move(f));
  }
  return out;
}

std::string V4l2CameraImpl::get_feature(const std::string& name) {
  require_state({CameraState::kOpened, CameraState::kConfigured, CameraState::kStreaming},
                "get_feature");
  Control* c = find_control(name);
  if (!c) throw Error(ErrorCode::kNotFound, who() + ": no control '" + name + "'");
  if (c->type == V4L2_CTRL_TYPE_BUTTON || (c->flags & V4L2_CTRL_FLAG_WRITE_ONLY)) {
    throw Error(ErrorCode::kInvalidArgument, who() + ": control '" + name + "' is write-only");
  }
  return control_text(*c);
}

void V4l2CameraImpl::set_feature(const std::string& name, const std::string& value) {
  require_state({CameraState::kOpened, CameraState::kConfigured, CameraState::kStreaming},
                "set_feature");
  Control* c = find_control(name);
  if (!c) throw Error(ErrorCode::kNotFound, who() + ": no control '" + name + "'");
  const int64_t v = c->type == V4L2_CTRL_TYPE_STRING ? 0 : parse_control_value(*c, value);
  write_control(*c, v, c->type == V4L2_CTRL_TYPE_STRING ? value : std::to_string(v));
}

std::map<std::string, std::string> V4l2CameraImpl::lock_for_calibration() {
  require_state({CameraState::kOpened, CameraState::kConfigured, CameraState::kStreaming},
                "lock_for_calibration");
  std::map<std::string, std::string> locked;
  // 1. Automatic modes off. Exposure priority ("dynamic framerate") lets the camera lengthen
  //    the exposure at the cost of frame rate, so it goes too. Looked up by control id, not by
  //    name, because kernels renamed them (focus_auto -> focus_automatic_continuous).
  if (Control* c = find_control(V4L2_CID_FOCUS_AUTO)) {
    write_control(*c, 0, "0");
    locked[c->name] = "0";
  }
  if (Control* c = find_control(V4L2_CID_EXPOSURE_AUTO)) {
    const bool has_manual = std::any_of(c->menu.begin(), c->menu.end(), [](const auto& m) {
      return m.first == V4L2_EXPOSURE_MANUAL;
    });
    if (!has_manual) {
      throw Error(ErrorCode::kUnsupported,
                  who() + ": auto_exposure has no manual mode, exposure cannot be locked");
    }
    write_control(*c, V4L2_EXPOSURE_MANUAL, "1");
    locked[c->name] = std::to_string(V4L2_EXPOSURE_MANUAL);
  }
  for (uint32_t id : {V4L2_CID_EXPOSURE_AUTO_PRIORITY, V4L2_CID_AUTOGAIN}) {
    if (Control* c = find_control(id); c && !(c->flags & V4L2_CTRL_FLAG_READ_ONLY)) {
      write_control(*c, 0, "0");
      locked[c->name] = "0";
    }
  }
  // 2. Fix the values the automatics left behind, now that the controls are active.
  for (uint32_t id :
       {V4L2_CID_FOCUS_ABSOLUTE, V4L2_CID_EXPOSURE_ABSOLUTE, V4L2_CID_EXPOSURE, V4L2_CID_GAIN}) {
    Control* c = find_control(id);
    if (!c || (c->flags & V4L2_CTRL_FLAG_READ_ONLY)) continue;
    const int64_t v = control_value(*c);
    write_control(*c, v, std::to_string(v));
    locked[c->name] = std::to_string(control_value(*c));
  }
  return locked;
}

// ---------------------------------------------------------------------------------------------
// Streaming

void V4l2CameraImpl::release_buffers(bool device_alive) {
  if (device_alive && stream_on_) {
    int type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    ioctl(VIDIOC_STREAMOFF, &type);
  }
  stream_on_ = false;
  for (const Mapping& m : buffers_) io_->munmap(m.addr, m.length);
  buffers_.clear();
  if (device_alive && buffers_allocated_) {
    v4l2_requestbuffers req{};
    req.count = 0;
    req.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    req.memory = V4L2_MEMORY_MMAP;
    ioctl(VIDIOC_REQBUFS, &req);
  }
  buffers_allocated_ = false;
  read_buffer_.clear();
  read_buffer_.shrink_to_fit();
}

void V4l2CameraImpl::start() {
  require_state({CameraState::kOpened, CameraState::kConfigured}, "start");
  if (state_ == CameraState::kOpened) configure(CameraConfig{});
  last_sequence_.reset();
  if (read_io_) {
    // read() I/O: capture starts with the first read() (or poll()).
    read_buffer_.assign(std::max<size_t>(fmt_.sizeimage, 1), 0);
    read_frames_ = 0;
    state_ = CameraState::kStreaming;
    return;
  }
  const auto failed = [&](const std::string& what, int err) {
    release_buffers(!is_gone(err));
    fail(what, err);
  };
  v4l2_requestbuffers req{};
  req.count = static_cast<uint32_t>(queue_depth_);
  req.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
  req.memory = V4L2_MEMORY_MMAP;
  if (const int err = ioctl(VIDIOC_REQBUFS, &req)) {
    if (err == EBUSY) {
      throw Error(
          ErrorCode::kDevice,
          who() + ": VIDIOC_REQBUFS: device busy (another application is streaming from it)");
    }
    fail("VIDIOC_REQBUFS", err);
  }
  buffers_allocated_ = req.count > 0;
  if (req.count < static_cast<uint32_t>(kMinBuffers)) {
    release_buffers(true);
    throw Error(ErrorCode::kDevice, who() + ": the driver granted only " +
                                        std::to_string(req.count) +
                                        " buffers (out of buffer memory?)");
  }
  buffers_.reserve(req.count);
  for (uint32_t i = 0; i < req.count; ++i) {
    v4l2_buffer b{};
    b.index = i;
    b.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    b.memory = V4L2_MEMORY_MMAP;
    if (const int err = ioctl(VIDIOC_QUERYBUF, &b)) failed("VIDIOC_QUERYBUF", err);
    void* addr = io_->mmap(nullptr, b.length, PROT_READ | PROT_WRITE, MAP_SHARED, fd_,
                           static_cast<off_t>(b.m.offset));
    if (addr == MAP_FAILED) failed("mmap of buffer " + std::to_string(i), errno);
    buffers_.push_back({addr, b.length});
  }
  for (uint32_t i = 0; i < buffers_.size(); ++i) {
    v4l2_buffer b{};
    b.index = i;
    b.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    b.memory = V4L2_MEMORY_MMAP;
    if (const int err = ioctl(VIDIOC_QBUF, &b)) failed("VIDIOC_QBUF", err);
  }
  int type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
  stream_on_ = true;  // so that a failure below is undone with STREAMOFF as well
  if (const int err = ioctl(VIDIOC_STREAMON, &type)) failed("VIDIOC_STREAMON", err);
  state_ = CameraState::kStreaming;
}

void V4l2CameraImpl::reopen_for_read_io() {
  // A read() capture only stops when the file is closed (and holds the queue until then, so
  // S_FMT would fail with EBUSY): close and open the node again.
  io_->close(fd_);
  fd_ = io_->open(dev_path_.c_str(), O_RDWR | O_NONBLOCK);
  if (fd_ < 0) {
    const int err = errno;
    fd_ = -1;
    disconnect(err, "reopening after read() capture");
    if (err != ENOENT && !is_gone(err)) {
      throw Error(ErrorCode::kDevice,
                  who() + ": cannot reopen " + dev_path_ + ": " + errno_text(err));
    }
  }
}

void V4l2CameraImpl::stop() {
  if (state_ != CameraState::kStreaming) return;
  release_buffers(true);
  state_ = CameraState::kConfigured;
  if (read_io_) reopen_for_read_io();
}

bool V4l2CameraImpl::deliver(const uint8_t* data, size_t bytes, uint64_t frame_id,
                             int64_t timestamp_ns, Frame* frame) {
  const PixelFormat pf = pixel_format_of_fourcc(fmt_.pixelformat);
  cv::Mat image;
  try {
    image = convert_to_engine(pf, data, bytes, static_cast<int>(fmt_.width),
                              static_cast<int>(fmt_.height),
                              pf == PixelFormat::kMJPEG ? 0 : fmt_.bytesperline);
  } catch (const Error& e) {
    if (e.code() != ErrorCode::kInvalidArgument) throw;
    image.release();  // short buffer: an incomplete frame
  }
  if (image.empty()) {
    ++stats_.frames_incomplete;
    return false;
  }
  // The buffer goes back to the driver right after this; Mono8 is only wrapped, so copy it.
  if (image.data == data) image = image.clone();
  frame->image = image;
  frame->frame_id = frame_id;
  frame->timestamp_ns = timestamp_ns;
  frame->source_format = pf;
  frame->hold.reset();
  ++stats_.frames_delivered;
  return true;
}

FrameStatus V4l2CameraImpl::next_frame(int timeout_ms, Frame* frame) {
  if (state_ == CameraState::kDisconnected) return FrameStatus::kDisconnected;
  require_state({CameraState::kStreaming}, "next_frame");
  if (!frame) throw Error(ErrorCode::kInvalidArgument, who() + ": next_frame: null frame");
  const auto deadline = Clock::now() + std::chrono::milliseconds(std::max(timeout_ms, 0));
  for (;;) {
    const auto left = std::chrono::ceil<std::chrono::milliseconds>(deadline - Clock::now()).count();
    pollfd p{fd_, POLLIN, 0};
    const int r = io_->poll(&p, 1, static_cast<int>(std::max<int64_t>(left, 0)));
    if (r < 0) {
      const int err = errno;
      if (err == EINTR) {
        if (Clock::now() >= deadline) return FrameStatus::kTimeout;
        continue;
      }
      fail("poll", err);
    }
    if (r == 0) {
      if (Clock::now() >= deadline) return FrameStatus::kTimeout;
      continue;
    }
    if (p.revents & POLLNVAL) {
      throw Error(ErrorCode::kInternal, who() + ": poll: descriptor is not open");
    }
    const bool error_reported = (p.revents & (POLLERR | POLLHUP)) != 0;

    if (read_io_) {
      const ssize_t n = io_->read(fd_, read_buffer_.data(), read_buffer_.size());
      if (n < 0) {
        const int err = errno;
        if (err == EAGAIN || err == EINTR) {
          if (error_reported) {
            throw Error(ErrorCode::kDevice, who() + ": poll reports an error, read() has no data");
          }
          if (Clock::now() >= deadline) return FrameStatus::kTimeout;
          continue;
        }
        if (is_gone(err) || err == EIO) {
          disconnect(err, "read");
          return FrameStatus::kDisconnected;
        }
        fail("read", err);
      }
      if (deliver(read_buffer_.data(), static_cast<size_t>(n), read_frames_++, host_monotonic_ns(),
                  frame)) {
        return FrameStatus::kOk;
      }
      if (Clock::now() >= deadline) return FrameStatus::kTimeout;
      continue;
    }

    v4l2_buffer b{};
    b.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    b.memory = V4L2_MEMORY_MMAP;
    if (const int err = ioctl(VIDIOC_DQBUF, &b)) {
      if (err == EAGAIN) {
        if (error_reported) {
          throw Error(ErrorCode::kDevice, who() + ": poll reports an error, no buffer is ready");
        }
        if (Clock::now() >= deadline) return FrameStatus::kTimeout;
        continue;
      }
      if (is_gone(err) || err == EIO) {
        disconnect(err, "VIDIOC_DQBUF");
        return FrameStatus::kDisconnected;
      }
      fail("VIDIOC_DQBUF", err);
    }
    if (b.index >= buffers_.size()) {
      throw Error(ErrorCode::kInternal, who() + ": driver returned buffer index " +
                                            std::to_string(b.index) + " of " +
                                            std::to_string(buffers_.size()));
    }
    // Frames the driver had to drop for want of a queued buffer show as sequence gaps.
    if (last_sequence_ && b.sequence > *last_sequence_ + 1) {
      stats_.frames_dropped += b.sequence - *last_sequence_ - 1;
    }
    last_sequence_ = b.sequence;
    bool ok = false;
    if (b.flags & V4L2_BUF_FLAG_ERROR || b.bytesused == 0) {
      ++stats_.frames_incomplete;
    } else {
      const int64_t ts =
          (b.flags & V4L2_BUF_FLAG_TIMESTAMP_MASK) == V4L2_BUF_FLAG_TIMESTAMP_MONOTONIC
              ? static_cast<int64_t>(b.timestamp.tv_sec) * 1000000000LL +
                    static_cast<int64_t>(b.timestamp.tv_usec) * 1000
              : host_monotonic_ns();
      const size_t bytes = std::min<size_t>(b.bytesused, buffers_[b.index].length);
      ok = deliver(static_cast<const uint8_t*>(buffers_[b.index].addr), bytes, b.sequence, ts,
                   frame);
    }
    // The decoded image is a copy, so the buffer can go straight back to the driver.
    v4l2_buffer q{};
    q.index = b.index;
    q.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    q.memory = V4L2_MEMORY_MMAP;
    if (const int err = ioctl(VIDIOC_QBUF, &q)) {
      if (is_gone(err) || err == EIO) {
        disconnect(err, "VIDIOC_QBUF");
        return ok ? FrameStatus::kOk : FrameStatus::kDisconnected;
      }
      fail("VIDIOC_QBUF", err);
    }
    if (ok) return FrameStatus::kOk;
    if (Clock::now() >= deadline) return FrameStatus::kTimeout;
  }
}

}  // namespace

std::unique_ptr<V4l2Camera> open_v4l2_camera(std::shared_ptr<V4l2Io> io,
                                             const V4l2NodeIdentity& identity,
                                             const std::string& uri_text) {
  return std::make_unique<V4l2CameraImpl>(std::move(io), identity, uri_text);
}

}  // namespace posecal::v4l2
