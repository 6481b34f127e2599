#include "uvc_emulator.hpp"

#include <fcntl.h>
#include <sys/mman.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstring>
#include <deque>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "sim/synthetic.hpp"
#include "board/views.hpp"

namespace posecal::emu {

namespace {

using Clock = std::chrono::steady_clock;

constexpr uint32_t kUserClass = 0x00980000;
constexpr uint32_t kCameraClass = 0x009a0000;

ControlSpec integer(uint32_t id, const char* name, int64_t lo, int64_t hi, int64_t step,
                    int64_t def) {
  ControlSpec c;
  c.id = id;
  c.type = V4L2_CTRL_TYPE_INTEGER;
  c.name = name;
  c.minimum = lo;
  c.maximum = hi;
  c.step = step;
  c.default_value = def;
  return c;
}

ControlSpec boolean(uint32_t id, const char* name, int64_t def) {
  ControlSpec c = integer(id, name, 0, 1, 1, def);
  c.type = V4L2_CTRL_TYPE_BOOLEAN;
  return c;
}

ControlSpec menu(uint32_t id, const char* name, int64_t lo, int64_t hi, int64_t def,
                 std::map<int64_t, std::string> items) {
  ControlSpec c = integer(id, name, lo, hi, 1, def);
  c.type = V4L2_CTRL_TYPE_MENU;
  c.menu = std::move(items);
  return c;
}

ControlSpec automatic(ControlSpec c, uint32_t master, std::vector<int64_t> auto_values,
                      int64_t value) {
  c.master = master;
  c.master_auto_values = std::move(auto_values);
  c.auto_value = value;
  return c;
}

FormatSpec format_spec(uint32_t fourcc, const char* description, bool compressed) {
  FormatSpec f;
  f.fourcc = fourcc;
  f.description = description;
  f.compressed = compressed;
  return f;
}

std::vector<FrameSizeSpec> sizes(std::initializer_list<std::pair<uint32_t, uint32_t>> wh,
                                 std::vector<uint32_t> fps) {
  std::vector<FrameSizeSpec> out;
  for (const auto& [w, h] : wh) out.push_back({w, h, fps});
  return out;
}

// uvcvideo on Linux 6.x: a USB capture node has these device caps; the metadata node its own.
constexpr uint32_t kUvcVideoCaps =
    V4L2_CAP_VIDEO_CAPTURE | V4L2_CAP_STREAMING | V4L2_CAP_EXT_PIX_FORMAT;
constexpr uint32_t kUvcMetaCaps =
    V4L2_CAP_META_CAPTURE | V4L2_CAP_STREAMING | V4L2_CAP_EXT_PIX_FORMAT;

std::vector<ControlSpec> uvc_image_controls(int64_t wb_auto_value) {
  return {
      integer(V4L2_CID_BRIGHTNESS, "Brightness", 0, 255, 1, 128),
      integer(V4L2_CID_CONTRAST, "Contrast", 0, 255, 1, 32),
      integer(V4L2_CID_SATURATION, "Saturation", 0, 255, 1, 32),
      boolean(V4L2_CID_AUTO_WHITE_BALANCE, "White Balance, Automatic", 1),
      integer(V4L2_CID_GAIN, "Gain", 0, 255, 1, 64),
      menu(V4L2_CID_POWER_LINE_FREQUENCY, "Power Line Frequency", 0, 2, 2,
           {{0, "Disabled"}, {1, "50 Hz"}, {2, "60 Hz"}}),
      automatic(integer(V4L2_CID_WHITE_BALANCE_TEMPERATURE, "White Balance Temperature", 2000, 6500,
                        1, 4000),
                V4L2_CID_AUTO_WHITE_BALANCE, {1}, wb_auto_value),
      integer(V4L2_CID_SHARPNESS, "Sharpness", 0, 255, 1, 24),
      integer(V4L2_CID_BACKLIGHT_COMPENSATION, "Backlight Compensation", 0, 1, 1, 1),
  };
}

// Limited-range BT.601 luma of a grey level (chroma is neutral for a grey scene).
uint8_t luma(uint8_t grey) {
  return static_cast<uint8_t>(std::lround(16.0 + grey * 219.0 / 255.0));
}

uint32_t bytes_per_line(uint32_t fourcc, uint32_t width) {
  if (fourcc == V4L2_PIX_FMT_YUYV) return 2 * width;
  if (fourcc == V4L2_PIX_FMT_GREY) return (width + 31) & ~31u;  // padded rows: tests the stride
  return 0;
}

uint32_t image_size(uint32_t fourcc, uint32_t width, uint32_t height) {
  if (fourcc == V4L2_PIX_FMT_MJPEG) return width * height * 2;  // uvc: dwMaxVideoFrameBufferSize
  return bytes_per_line(fourcc, width) * height;
}

cv::Mat render_scene(uint32_t width, uint32_t height) {
  static std::mutex mutex;
  static std::map<std::pair<uint32_t, uint32_t>, cv::Mat> cache;
  std::lock_guard<std::mutex> lock(mutex);
  auto it = cache.find({width, height});
  if (it != cache.end()) return it->second;
  // The C525's lens (data/c525_reference.yml), scaled to the frame height.
  const double f = 1070.0 * height / 720.0;
  const CameraModel model = CameraModel::opencv5(static_cast<int>(width), static_cast<int>(height),
                                                 f, f, (width - 1) / 2.0, (height - 1) / 2.0,
                                                 {-0.0032, -0.206, -0.0028, -0.0039, 0.248});
  const Board target;
  double z = f * target.board_size_m().width / (0.55 * width);
  Pose pose = board_pose_at(target, Eigen::Vector3d(0, 0, z), 0.4, 0.3, 0.05);
  for (int i = 0; i < 10 && !board_fully_visible(model, target, pose); ++i) {
    z *= 1.2;
    pose = board_pose_at(target, Eigen::Vector3d(0, 0, z), 0.4, 0.3, 0.05);
  }
  RenderOptions ro;
  ro.supersample = 1;
  ro.blur_sigma_px = 0.5;
  SyntheticCamera camera(model, target, ro);
  cv::Mat img = camera.render(pose);
  cache[{width, height}] = img;
  return img;
}

std::shared_ptr<const std::vector<uint8_t>> payload(uint32_t fourcc, uint32_t width,
                                                    uint32_t height) {
  static std::mutex mutex;
  static std::map<std::tuple<uint32_t, uint32_t, uint32_t>,
                  std::shared_ptr<const std::vector<uint8_t>>>
      cache;
  {
    std::lock_guard<std::mutex> lock(mutex);
    auto it = cache.find({fourcc, width, height});
    if (it != cache.end()) return it->second;
  }
  auto bytes = std::make_shared<const std::vector<uint8_t>>(
      encode_payload(fourcc, render_scene(width, height)));
  std::lock_guard<std::mutex> lock(mutex);
  cache[{fourcc, width, height}] = bytes;
  return bytes;
}

void copy_name(uint8_t* dst, size_t size, const std::string& s) {
  std::memset(dst, 0, size);
  std::memcpy(dst, s.data(), std::min(s.size(), size - 1));
}

timeval to_timeval(Clock::time_point t) {
  const auto us =
      std::chrono::duration_cast<std::chrono::microseconds>(t.time_since_epoch()).count();
  return timeval{static_cast<time_t>(us / 1000000), static_cast<suseconds_t>(us % 1000000)};
}

int fail(int err) {
  errno = err;
  return -1;
}

}  // namespace

std::vector<uint8_t> encode_payload(uint32_t fourcc, const cv::Mat& grey) {
  CV_Assert(grey.type() == CV_8UC1);
  const auto width = static_cast<uint32_t>(grey.cols);
  const auto height = static_cast<uint32_t>(grey.rows);
  std::vector<uint8_t> bytes;
  if (fourcc == V4L2_PIX_FMT_MJPEG) {
    cv::Mat bgr;
    cv::cvtColor(grey, bgr, cv::COLOR_GRAY2BGR);
    cv::imencode(".jpg", bgr, bytes, {cv::IMWRITE_JPEG_QUALITY, 90});
  } else if (fourcc == V4L2_PIX_FMT_YUYV) {
    bytes.resize(2u * width * height);
    for (uint32_t y = 0; y < height; ++y) {
      const uint8_t* row = grey.ptr<uint8_t>(static_cast<int>(y));
      uint8_t* out = bytes.data() + 2u * width * y;
      for (uint32_t x = 0; x < width; ++x) {
        out[2 * x] = luma(row[x]);
        out[2 * x + 1] = 128;  // U for even x, V for odd x: neutral
      }
    }
  } else {
    const uint32_t stride = bytes_per_line(fourcc, width);
    bytes.assign(static_cast<size_t>(stride) * height, 0);
    for (uint32_t y = 0; y < height; ++y) {
      std::memcpy(bytes.data() + static_cast<size_t>(stride) * y, grey.ptr(static_cast<int>(y)),
                  width);
    }
  }
  return bytes;
}

// ---------------------------------------------------------------------------------------------
// Device profiles

DeviceSpec c525_video_node() {
  DeviceSpec d;
  d.card = "HD Webcam C525";
  d.bus_info = "usb-0000:00:14.0-2";
  d.device_caps = kUvcVideoCaps;
  d.capabilities = kUvcVideoCaps | kUvcMetaCaps;
  // uvcvideo lists formats in descriptor order: YUYV first on Logitech cameras. USB 2 bandwidth
  // limits uncompressed 720p to 10 fps; MJPEG reaches 30 fps at every size.
  FormatSpec yuyv = format_spec(V4L2_PIX_FMT_YUYV, "YUYV 4:2:2", false);
  yuyv.sizes = sizes({{640, 480}, {160, 120}, {320, 240}}, {30, 25, 20, 15, 10, 5});
  for (const auto& s : sizes({{800, 600}}, {20, 15, 10, 5})) yuyv.sizes.push_back(s);
  for (const auto& s : sizes({{960, 720}}, {15, 10, 5})) yuyv.sizes.push_back(s);
  for (const auto& s : sizes({{1280, 720}}, {10, 5})) yuyv.sizes.push_back(s);
  FormatSpec mjpeg = format_spec(V4L2_PIX_FMT_MJPEG, "Motion-JPEG", true);
  mjpeg.sizes = sizes({{640, 480}, {160, 120}, {320, 240}, {800, 600}, {960, 720}, {1280, 720}},
                      {30, 25, 20, 15, 10, 5});
  d.formats = {yuyv, mjpeg};
  d.controls = uvc_image_controls(4600);
  d.controls.push_back(menu(V4L2_CID_EXPOSURE_AUTO, "Auto Exposure", 0, 3, 3,
                            {{1, "Manual Mode"}, {3, "Aperture Priority Mode"}}));
  d.controls.push_back(
      automatic(integer(V4L2_CID_EXPOSURE_ABSOLUTE, "Exposure Time, Absolute", 3, 2047, 1, 250),
                V4L2_CID_EXPOSURE_AUTO, {0, 2, 3}, 166));
  d.controls.push_back(boolean(V4L2_CID_EXPOSURE_AUTO_PRIORITY, "Exposure, Dynamic Framerate", 0));
  d.controls.push_back(integer(V4L2_CID_PAN_ABSOLUTE, "Pan, Absolute", -36000, 36000, 3600, 0));
  d.controls.push_back(integer(V4L2_CID_TILT_ABSOLUTE, "Tilt, Absolute", -36000, 36000, 3600, 0));
  d.controls.push_back(automatic(integer(V4L2_CID_FOCUS_ABSOLUTE, "Focus, Absolute", 0, 255, 5, 0),
                                 V4L2_CID_FOCUS_AUTO, {1}, 35));
  d.controls.push_back(boolean(V4L2_CID_FOCUS_AUTO, "Focus, Automatic Continuous", 1));
  d.controls.push_back(integer(V4L2_CID_ZOOM_ABSOLUTE, "Zoom, Absolute", 1, 5, 1, 1));
  return d;
}

DeviceSpec c525_metadata_node() {
  DeviceSpec d;
  d.card = "HD Webcam C525";
  d.bus_info = "usb-0000:00:14.0-2";
  d.device_caps = kUvcMetaCaps;
  d.capabilities = kUvcVideoCaps | kUvcMetaCaps;
  return d;
}

DeviceSpec lifecam_video_node() {
  DeviceSpec d;
  d.card = "Microsoft\xC2\xAE LifeCam HD-3000";  // the product string, truncated to 31 bytes
  d.card.resize(std::min<size_t>(d.card.size(), 31));
  d.bus_info = "usb-0000:00:14.0-3.1";
  d.device_caps = kUvcVideoCaps;
  d.capabilities = kUvcVideoCaps | kUvcMetaCaps;
  FormatSpec yuyv = format_spec(V4L2_PIX_FMT_YUYV, "YUYV 4:2:2", false);
  yuyv.sizes = sizes({{640, 480}, {424, 240}, {320, 240}, {160, 120}}, {30, 15, 10});
  for (const auto& s : sizes({{1280, 720}}, {10})) yuyv.sizes.push_back(s);
  FormatSpec mjpeg = format_spec(V4L2_PIX_FMT_MJPEG, "Motion-JPEG", true);
  mjpeg.sizes = sizes({{640, 480}, {1280, 720}, {960, 544}, {424, 240}}, {30, 15});
  d.formats = {yuyv, mjpeg};
  d.controls = {
      integer(V4L2_CID_BRIGHTNESS, "Brightness", 30, 255, 1, 133),
      integer(V4L2_CID_CONTRAST, "Contrast", 0, 10, 1, 5),
      integer(V4L2_CID_SATURATION, "Saturation", 0, 200, 1, 83),
      boolean(V4L2_CID_AUTO_WHITE_BALANCE, "White Balance, Automatic", 1),
      menu(V4L2_CID_POWER_LINE_FREQUENCY, "Power Line Frequency", 0, 2, 2,
           {{0, "Disabled"}, {1, "50 Hz"}, {2, "60 Hz"}}),
      automatic(integer(V4L2_CID_WHITE_BALANCE_TEMPERATURE, "White Balance Temperature", 2800,
                        10000, 1, 4500),
                V4L2_CID_AUTO_WHITE_BALANCE, {1}, 5000),
      integer(V4L2_CID_SHARPNESS, "Sharpness", 0, 50, 1, 25),
      integer(V4L2_CID_BACKLIGHT_COMPENSATION, "Backlight Compensation", 0, 10, 1, 0),
      menu(V4L2_CID_EXPOSURE_AUTO, "Auto Exposure", 0, 3, 3,
           {{1, "Manual Mode"}, {3, "Aperture Priority Mode"}}),
      automatic(integer(V4L2_CID_EXPOSURE_ABSOLUTE, "Exposure Time, Absolute", 5, 20000, 1, 156),
                V4L2_CID_EXPOSURE_AUTO, {0, 2, 3}, 312),
      integer(V4L2_CID_ZOOM_ABSOLUTE, "Zoom, Absolute", 0, 10, 1, 0),
  };
  return d;
}

DeviceSpec lifecam_metadata_node() {
  DeviceSpec d = c525_metadata_node();
  d.card = lifecam_video_node().card;
  d.bus_info = "usb-0000:00:14.0-3.1";
  return d;
}

DeviceSpec grey_read_node() {
  DeviceSpec d;
  d.driver = "mono_sensor";
  d.card = "Mono Sensor";
  d.bus_info = "platform:mono-sensor.0";
  d.device_caps = V4L2_CAP_VIDEO_CAPTURE | V4L2_CAP_READWRITE;
  d.capabilities = d.device_caps;
  FormatSpec grey = format_spec(V4L2_PIX_FMT_GREY, "8-bit Greyscale", false);
  grey.min_width = 160;
  grey.max_width = 1280;
  grey.step_width = 16;
  grey.min_height = 120;
  grey.max_height = 720;
  grey.step_height = 8;
  grey.stepwise_fps = {30, 15};
  d.formats = {grey};
  ControlSpec temperature =
      integer(V4L2_CID_USER_BASE + 0x1000, "Sensor Temperature", -40, 125, 1, 0);
  temperature.flags = V4L2_CTRL_FLAG_READ_ONLY | V4L2_CTRL_FLAG_VOLATILE;
  ControlSpec white_balance = integer(V4L2_CID_DO_WHITE_BALANCE, "Do White Balance", 0, 0, 0, 0);
  white_balance.type = V4L2_CTRL_TYPE_BUTTON;
  white_balance.flags = V4L2_CTRL_FLAG_WRITE_ONLY | V4L2_CTRL_FLAG_EXECUTE_ON_WRITE;
  d.controls = {integer(V4L2_CID_BRIGHTNESS, "Brightness", 0, 255, 1, 128),
                integer(V4L2_CID_GAIN, "Gain", 0, 48, 1, 0), white_balance, temperature};
  d.supports_try_fmt = false;
  d.supports_ext_ctrls = false;
  d.supports_query_ext_ctrl = false;
  d.supports_timeperframe = false;
  return d;
}

// ---------------------------------------------------------------------------------------------
// Emulator state

struct UvcEmulator::Node {
  enum class BufState { kDequeued, kQueued, kDone };
  struct Buffer {
    std::shared_ptr<std::vector<uint8_t>> memory;
    uint32_t offset = 0;
    BufState state = BufState::kDequeued;
    uint32_t bytesused = 0;
    uint32_t flags = 0;
    uint32_t sequence = 0;
    timeval timestamp{};
  };

  std::string path;
  std::string usb_device;
  DeviceSpec spec;
  bool present = true;

  v4l2_pix_format fmt{};
  uint32_t fps = 30;
  std::map<uint32_t, int64_t> values;

  int owner = -1;  // descriptor owning the queue (REQBUFS, or read())
  std::vector<Buffer> buffers;
  std::deque<uint32_t> queued;
  std::deque<uint32_t> done;
  bool streaming = false;
  bool reading = false;
  Clock::time_point t0;
  uint64_t produced = 0;   // frames the sensor delivered since STREAMON / first read
  uint64_t read_seen = 0;  // read(): frames handed out
  int corrupt = 0;
  Corruption corruption = Corruption::kTruncated;
  UvcEmulator::PayloadSource source;  // frames from a test instead of the fixed scene
  int stream_error = 0;
  uint64_t state_changes = 0;

  bool is_capture() const { return (spec.device_caps & V4L2_CAP_VIDEO_CAPTURE) != 0; }
  bool can_stream() const { return (spec.device_caps & V4L2_CAP_STREAMING) != 0; }

  const FormatSpec* format(uint32_t fourcc) const {
    for (const auto& f : spec.formats) {
      if (f.fourcc == fourcc) return &f;
    }
    return nullptr;
  }

  // The rates offered at a size, empty if the size is not offered.
  std::vector<uint32_t> rates(const FormatSpec& f, uint32_t w, uint32_t h) const {
    if (f.sizes.empty()) {
      const bool ok = w >= f.min_width && w <= f.max_width && h >= f.min_height &&
                      h <= f.max_height && (w - f.min_width) % f.step_width == 0 &&
                      (h - f.min_height) % f.step_height == 0;
      return ok ? f.stepwise_fps : std::vector<uint32_t>{};
    }
    for (const auto& s : f.sizes) {
      if (s.width == w && s.height == h) return s.fps;
    }
    return {};
  }

  // uvcvideo's TRY_FMT: unknown formats fall back to the first; the nearest size by area
  // difference; stepwise sizes are clamped and rounded to the step.
  v4l2_pix_format adjust(uint32_t fourcc, uint32_t w, uint32_t h) const {
    const FormatSpec* f = format(fourcc);
    if (!f) f = &spec.formats.front();
    v4l2_pix_format p{};
    p.pixelformat = f->fourcc;
    if (f->sizes.empty()) {
      const auto snap = [](uint32_t v, uint32_t lo, uint32_t hi, uint32_t step) {
        v = std::clamp(v, lo, hi);
        return std::min(lo + (v - lo + step / 2) / step * step, hi);
      };
      p.width = snap(w, f->min_width, f->max_width, f->step_width);
      p.height = snap(h, f->min_height, f->max_height, f->step_height);
    } else {
      uint64_t best = UINT64_MAX;
      for (const auto& s : f->sizes) {
        const uint64_t covered = uint64_t{std::min(w, s.width)} * std::min(h, s.height);
        const uint64_t d = uint64_t{w} * h + uint64_t{s.width} * s.height - 2 * covered;
        if (d < best) {
          best = d;
          p.width = s.width;
          p.height = s.height;
        }
      }
    }
    p.field = V4L2_FIELD_NONE;
    p.bytesperline = bytes_per_line(p.pixelformat, p.width);
    p.sizeimage = image_size(p.pixelformat, p.width, p.height);
    p.colorspace =
        p.pixelformat == V4L2_PIX_FMT_MJPEG ? V4L2_COLORSPACE_JPEG : V4L2_COLORSPACE_SRGB;
    return p;
  }

  void set_format(const v4l2_pix_format& p) {
    fmt = p;
    const auto r = rates(*format(p.pixelformat), p.width, p.height);
    fps = r.empty() ? 30 : r.front();  // uvcvideo: S_FMT selects the default (fastest) interval
  }

  const ControlSpec* control(uint32_t id) const {
    for (const auto& c : spec.controls) {
      if (c.id == id) return &c;
    }
    return nullptr;
  }
  bool inactive(const ControlSpec& c) const {
    if (!c.master) return false;
    const int64_t m = values.at(c.master);
    return std::find(c.master_auto_values.begin(), c.master_auto_values.end(), m) !=
           c.master_auto_values.end();
  }
  int64_t value(const ControlSpec& c) const { return inactive(c) ? c.auto_value : values.at(c.id); }
  uint32_t flags(const ControlSpec& c) const {
    uint32_t f = c.flags | (inactive(c) ? V4L2_CTRL_FLAG_INACTIVE : 0);
    for (const auto& other : spec.controls) {
      if (other.master == c.id) f |= V4L2_CTRL_FLAG_UPDATE;
    }
    return f;
  }

  void release_queue() {
    streaming = false;
    reading = false;
    buffers.clear();  // memory still mapped lives on in the mappings, as vb2 keeps it
    queued.clear();
    done.clear();
    owner = -1;
  }
};

struct UvcEmulator::File {
  std::shared_ptr<Node> node;
  int flags = 0;
};

struct UvcEmulator::Mapping {
  std::shared_ptr<std::vector<uint8_t>> memory;
  size_t length = 0;
};

UvcEmulator::UvcEmulator() = default;
UvcEmulator::~UvcEmulator() = default;

void UvcEmulator::add_node(const std::string& path, DeviceSpec spec,
                           const std::string& usb_device) {
  std::lock_guard<std::mutex> lock(mutex_);
  auto n = std::make_shared<Node>();
  n->path = path;
  n->usb_device = usb_device;
  n->spec = std::move(spec);
  for (const auto& c : n->spec.controls) n->values[c.id] = c.default_value;
  if (!n->spec.formats.empty()) {
    const FormatSpec& f = n->spec.formats.front();
    const uint32_t w = f.sizes.empty() ? 640 : f.sizes.front().width;
    const uint32_t h = f.sizes.empty() ? 480 : f.sizes.front().height;
    n->set_format(n->adjust(f.fourcc, w, h));
    payload(n->fmt.pixelformat, n->fmt.width, n->fmt.height);
  }
  nodes_[path] = n;
}

void UvcEmulator::unplug_locked(const std::string& usb_device) {
  for (auto it = nodes_.begin(); it != nodes_.end();) {
    if (it->second->usb_device == usb_device) {
      it->second->present = false;
      it = nodes_.erase(it);
    } else {
      ++it;
    }
  }
  changed_.notify_all();
}

void UvcEmulator::unplug(const std::string& usb_device) {
  std::lock_guard<std::mutex> lock(mutex_);
  unplug_locked(usb_device);
}

void UvcEmulator::unplug_before_call(uint64_t n, const std::string& usb_device) {
  std::lock_guard<std::mutex> lock(mutex_);
  unplug_at_call_ = n;
  unplug_at_call_device_ = usb_device;
}

void UvcEmulator::unplug_before(Call call, int n, const std::string& usb_device) {
  std::lock_guard<std::mutex> lock(mutex_);
  unplug_kind_ = call;
  unplug_at_kind_ = static_cast<uint64_t>(n);
  unplug_at_kind_device_ = usb_device;
}

void UvcEmulator::count_call(Call call) {
  ++calls_;
  const uint64_t k = ++calls_by_kind_[call];
  if (unplug_at_call_ && calls_ == unplug_at_call_) unplug_locked(unplug_at_call_device_);
  if (unplug_at_kind_ && call == unplug_kind_ && k == unplug_at_kind_) {
    unplug_locked(unplug_at_kind_device_);
  }
}

void UvcEmulator::corrupt_next_frames(const std::string& path, int count, Corruption how) {
  std::lock_guard<std::mutex> lock(mutex_);
  if (auto n = node_at(path)) {
    n->corrupt = count;
    n->corruption = how;
  }
}

void UvcEmulator::fail_stream(const std::string& path, int err) {
  std::lock_guard<std::mutex> lock(mutex_);
  if (auto n = node_at(path)) n->stream_error = err;
  changed_.notify_all();
}

void UvcEmulator::set_payload_source(const std::string& path, PayloadSource source) {
  std::lock_guard<std::mutex> lock(mutex_);
  if (auto n = node_at(path)) n->source = std::move(source);
}

int UvcEmulator::open_fds() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return static_cast<int>(files_.size());
}

int UvcEmulator::live_mappings() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return static_cast<int>(mappings_.size());
}

int UvcEmulator::bad_munmaps() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return bad_munmaps_;
}

uint64_t UvcEmulator::calls() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return calls_;
}

uint64_t UvcEmulator::calls_of(Call call) const {
  std::lock_guard<std::mutex> lock(mutex_);
  auto it = calls_by_kind_.find(call);
  return it == calls_by_kind_.end() ? 0 : it->second;
}

std::shared_ptr<UvcEmulator::Node> UvcEmulator::node_at(const std::string& path) const {
  auto it = nodes_.find(path);
  return it == nodes_.end() ? nullptr : it->second;
}

uint64_t UvcEmulator::state_changes(const std::string& path) const {
  std::lock_guard<std::mutex> lock(mutex_);
  auto n = node_at(path);
  return n ? n->state_changes : 0;
}

v4l2_pix_format UvcEmulator::format(const std::string& path) const {
  std::lock_guard<std::mutex> lock(mutex_);
  auto n = node_at(path);
  return n ? n->fmt : v4l2_pix_format{};
}

double UvcEmulator::frame_rate(const std::string& path) const {
  std::lock_guard<std::mutex> lock(mutex_);
  auto n = node_at(path);
  return n ? n->fps : 0.0;
}

int64_t UvcEmulator::control(const std::string& path, uint32_t id) const {
  std::lock_guard<std::mutex> lock(mutex_);
  auto n = node_at(path);
  const ControlSpec* c = n ? n->control(id) : nullptr;
  return c ? n->value(*c) : 0;
}

bool UvcEmulator::streaming(const std::string& path) const {
  std::lock_guard<std::mutex> lock(mutex_);
  auto n = node_at(path);
  return n && n->streaming;
}

cv::Mat UvcEmulator::scene(const std::string& path) const {
  v4l2_pix_format f = format(path);
  return render_scene(f.width, f.height);
}

UvcEmulator::File* UvcEmulator::file(int fd) {
  auto it = files_.find(fd);
  return it == files_.end() ? nullptr : it->second.get();
}

// The sensor: frame k (k >= 0) is due at t0 + (k + 1) * interval. A due frame fills the oldest
// queued buffer or, with none queued, is dropped (its sequence number is used up either way).
void UvcEmulator::produce(Node& n) {
  if (!n.streaming && !n.reading) return;
  const double period_s = 1.0 / n.fps;
  const double elapsed_s = std::chrono::duration<double>(Clock::now() - n.t0).count();
  const auto due = static_cast<uint64_t>(std::max(0.0, std::floor(elapsed_s / period_s)));
  std::shared_ptr<const std::vector<uint8_t>> data;
  while (n.produced < due) {
    const uint64_t k = n.produced++;
    if (!n.streaming || n.queued.empty()) continue;
    std::shared_ptr<const std::vector<uint8_t>> sourced;
    if (n.source) sourced = n.source(static_cast<uint32_t>(k), n.fmt);
    if (!sourced && !data) data = payload(n.fmt.pixelformat, n.fmt.width, n.fmt.height);
    const std::vector<uint8_t>& bytes_out = sourced ? *sourced : *data;
    const uint32_t idx = n.queued.front();
    n.queued.pop_front();
    Node::Buffer& b = n.buffers[idx];
    size_t bytes = std::min(bytes_out.size(), b.memory->size());
    b.flags = 0;
    if (n.corrupt > 0) {
      --n.corrupt;
      if (n.corruption == Corruption::kTruncated) {
        bytes /= 2;  // the end of the frame never arrived, as after lost isochronous packets
      } else {
        b.flags |= V4L2_BUF_FLAG_ERROR;  // uvcvideo marks frames with errors in their payload
      }
    }
    std::memcpy(b.memory->data(), bytes_out.data(), bytes);
    b.bytesused = static_cast<uint32_t>(bytes);
    b.sequence = static_cast<uint32_t>(k);
    b.timestamp = to_timeval(n.t0 + std::chrono::duration_cast<Clock::duration>(
                                        std::chrono::duration<double>((k + 1) * period_s)));
    b.state = Node::BufState::kDone;
    n.done.push_back(idx);
  }
}

// ---------------------------------------------------------------------------------------------
// V4l2Io

int UvcEmulator::open(const char* path, int flags) {
  std::lock_guard<std::mutex> lock(mutex_);
  count_call(Call::kOpen);
  auto n = node_at(path ? path : "");
  if (!n) return fail(ENOENT);
  const int fd = next_fd_++;
  files_[fd] = std::make_unique<File>(File{n, flags});
  return fd;
}

int UvcEmulator::close(int fd) {
  std::lock_guard<std::mutex> lock(mutex_);
  count_call(Call::kClose);
  File* f = file(fd);
  if (!f) return fail(EBADF);
  if (f->node->owner == fd) f->node->release_queue();
  files_.erase(fd);
  changed_.notify_all();
  return 0;
}

void* UvcEmulator::mmap(void* /*addr*/, size_t length, int prot, int flags, int fd, off_t offset) {
  std::lock_guard<std::mutex> lock(mutex_);
  count_call(Call::kMmap);
  File* f = file(fd);
  if (!f) return (errno = EBADF, MAP_FAILED);
  Node& n = *f->node;
  if (!n.present) return (errno = ENODEV, MAP_FAILED);
  if (!(flags & MAP_SHARED) || !(prot & PROT_READ)) return (errno = EINVAL, MAP_FAILED);
  for (const auto& b : n.buffers) {
    if (b.offset != static_cast<uint32_t>(offset)) continue;
    if (length == 0 || length > b.memory->size()) return (errno = EINVAL, MAP_FAILED);
    const void* addr = b.memory->data();
    mappings_.emplace(addr, std::make_unique<Mapping>(Mapping{b.memory, length}));
    return const_cast<void*>(addr);
  }
  return (errno = EINVAL, MAP_FAILED);
}

int UvcEmulator::munmap(void* addr, size_t length) {
  std::lock_guard<std::mutex> lock(mutex_);
  count_call(Call::kMunmap);
  auto [lo, hi] = mappings_.equal_range(addr);
  for (auto it = lo; it != hi; ++it) {
    if (it->second->length == length) {
      mappings_.erase(it);
      return 0;
    }
  }
  ++bad_munmaps_;  // the kernel would accept it silently; a client bug all the same
  return fail(EINVAL);
}

short UvcEmulator::poll_events(Lock& /*lock*/, int fd) {
  File* f = file(fd);
  if (!f) return POLLNVAL;
  Node& n = *f->node;
  if (!n.present) return POLLERR | POLLHUP;  // v4l2-core on an unregistered device
  if (n.stream_error) return POLLERR;
  if (n.streaming) {
    if (n.owner != fd) return POLLERR;
    produce(n);
    return n.done.empty() ? 0 : (POLLIN | POLLRDNORM);
  }
  if ((n.spec.device_caps & V4L2_CAP_READWRITE) && n.buffers.empty() &&
      (n.owner == -1 || n.owner == fd)) {
    if (!n.reading) {  // poll() starts a read() capture
      payload(n.fmt.pixelformat, n.fmt.width, n.fmt.height);
      n.reading = true;
      n.owner = fd;
      n.t0 = Clock::now();
      n.produced = n.read_seen = 0;
    }
    produce(n);
    return n.produced > n.read_seen ? (POLLIN | POLLRDNORM) : 0;
  }
  return POLLERR;  // vb2: nothing to wait for when not streaming
}

int UvcEmulator::poll(struct pollfd* fds, nfds_t nfds, int timeout_ms) {
  Lock lock(mutex_);
  count_call(Call::kPoll);
  // A negative timeout waits for ever in the kernel; a minute here, so a buggy test ends.
  const auto deadline =
      Clock::now() + std::chrono::milliseconds(timeout_ms < 0 ? 60000 : timeout_ms);
  for (;;) {
    int ready = 0;
    for (nfds_t i = 0; i < nfds; ++i) {
      const short ev = poll_events(lock, fds[i].fd);
      fds[i].revents = static_cast<short>(ev & (fds[i].events | POLLERR | POLLHUP | POLLNVAL));
      if (fds[i].revents) ++ready;
    }
    if (ready || Clock::now() >= deadline) return ready;
    auto wake = deadline;
    for (nfds_t i = 0; i < nfds; ++i) {
      File* f = file(fds[i].fd);
      if (!f || !(f->node->streaming || f->node->reading)) continue;
      const Node& n = *f->node;
      const auto next = n.t0 + std::chrono::duration_cast<Clock::duration>(
                                   std::chrono::duration<double>((n.produced + 1) / double(n.fps)));
      wake = std::min(wake, next);
    }
    changed_.wait_until(lock, wake);
  }
}

ssize_t UvcEmulator::read(int fd, void* buf, size_t count) {
  Lock lock(mutex_);
  count_call(Call::kRead);
  File* f = file(fd);
  if (!f) return fail(EBADF);
  std::shared_ptr<Node> node = f->node;
  Node& n = *node;
  if (!n.present) return fail(ENODEV);
  if (n.stream_error) return fail(n.stream_error);
  if (!(n.spec.device_caps & V4L2_CAP_READWRITE)) return fail(EINVAL);
  if (!n.buffers.empty() || (n.owner != -1 && n.owner != fd)) return fail(EBUSY);
  if (!n.reading) {
    payload(n.fmt.pixelformat, n.fmt.width, n.fmt.height);
    n.reading = true;
    n.owner = fd;
    n.t0 = Clock::now();
    n.produced = n.read_seen = 0;
  }
  const bool nonblocking = (f->flags & O_NONBLOCK) != 0;
  const auto give_up = Clock::now() + std::chrono::seconds(30);
  for (;;) {
    produce(n);
    if (n.produced > n.read_seen) {
      n.read_seen = n.produced;  // read() hands out the newest frame
      const auto data = payload(n.fmt.pixelformat, n.fmt.width, n.fmt.height);
      size_t bytes = std::min(count, data->size());
      if (n.corrupt > 0) {
        --n.corrupt;
        bytes /= 2;
      }
      std::memcpy(buf, data->data(), bytes);
      return static_cast<ssize_t>(bytes);
    }
    if (nonblocking) return fail(EAGAIN);
    const auto next = n.t0 + std::chrono::duration_cast<Clock::duration>(
                                 std::chrono::duration<double>((n.produced + 1) / double(n.fps)));
    if (Clock::now() > give_up) return fail(EIO);
    changed_.wait_until(lock, next);
    if (!n.present) return fail(ENODEV);
    if (!file(fd)) return fail(EBADF);
  }
}

int UvcEmulator::ioctl(int fd, unsigned long request, void* arg) {
  Lock lock(mutex_);
  count_call(Call::kIoctl);
  File* f = file(fd);
  if (!f) return fail(EBADF);
  if (!f->node->present) return fail(ENODEV);
  const int err = do_ioctl(lock, fd, *f, request, arg);
  return err ? fail(err) : 0;
}

int UvcEmulator::do_ioctl(Lock& lock, int fd, File& f, unsigned long request, void* arg) {
  Node& n = *f.node;
  const auto capture_type = [&](uint32_t type) {
    return n.is_capture() && type == V4L2_BUF_TYPE_VIDEO_CAPTURE;
  };
  const auto queue_owned_by_other = [&] { return n.owner != -1 && n.owner != fd; };

  switch (request) {
    case VIDIOC_QUERYCAP: {
      auto* cap = static_cast<v4l2_capability*>(arg);
      std::memset(cap, 0, sizeof *cap);
      copy_name(cap->driver, sizeof cap->driver, n.spec.driver);
      copy_name(cap->card, sizeof cap->card, n.spec.card);
      copy_name(cap->bus_info, sizeof cap->bus_info, n.spec.bus_info);
      cap->version = (6u << 16) | (1u << 8);
      cap->capabilities = n.spec.capabilities | V4L2_CAP_DEVICE_CAPS;
      cap->device_caps = n.spec.device_caps;
      return 0;
    }
    case VIDIOC_ENUM_FMT: {
      auto* d = static_cast<v4l2_fmtdesc*>(arg);
      if (!capture_type(d->type) || d->index >= n.spec.formats.size()) return EINVAL;
      const FormatSpec& fs = n.spec.formats[d->index];
      const uint32_t index = d->index, type = d->type;
      std::memset(d, 0, sizeof *d);
      d->index = index;
      d->type = type;
      d->flags = fs.compressed ? V4L2_FMT_FLAG_COMPRESSED : 0;
      copy_name(d->description, sizeof d->description, fs.description);
      d->pixelformat = fs.fourcc;
      return 0;
    }
    case VIDIOC_ENUM_FRAMESIZES: {
      auto* s = static_cast<v4l2_frmsizeenum*>(arg);
      const FormatSpec* fs = n.format(s->pixel_format);
      if (!n.is_capture() || !fs) return EINVAL;
      if (fs->sizes.empty()) {
        if (s->index != 0) return EINVAL;
        s->type = V4L2_FRMSIZE_TYPE_STEPWISE;
        s->stepwise = {fs->min_width,  fs->max_width,  fs->step_width,
                       fs->min_height, fs->max_height, fs->step_height};
        return 0;
      }
      if (s->index >= fs->sizes.size()) return EINVAL;
      s->type = V4L2_FRMSIZE_TYPE_DISCRETE;
      s->discrete = {fs->sizes[s->index].width, fs->sizes[s->index].height};
      return 0;
    }
    case VIDIOC_ENUM_FRAMEINTERVALS: {
      auto* e = static_cast<v4l2_frmivalenum*>(arg);
      const FormatSpec* fs = n.format(e->pixel_format);
      if (!n.is_capture() || !fs) return EINVAL;
      const auto r = n.rates(*fs, e->width, e->height);
      if (e->index >= r.size()) return EINVAL;
      e->type = V4L2_FRMIVAL_TYPE_DISCRETE;
      e->discrete = {1, r[e->index]};
      return 0;
    }
    case VIDIOC_G_FMT:
    case VIDIOC_TRY_FMT:
    case VIDIOC_S_FMT: {
      auto* fmt = static_cast<v4l2_format*>(arg);
      if (!capture_type(fmt->type)) return EINVAL;
      if (request == VIDIOC_G_FMT) {
        fmt->fmt.pix = n.fmt;
        return 0;
      }
      if (request == VIDIOC_TRY_FMT && !n.spec.supports_try_fmt) return ENOTTY;
      const v4l2_pix_format p =
          n.adjust(fmt->fmt.pix.pixelformat, fmt->fmt.pix.width, fmt->fmt.pix.height);
      if (request == VIDIOC_S_FMT) {
        // vb2_is_busy(): buffers allocated, streaming, or a read() capture holding the queue.
        if (n.streaming || !n.buffers.empty() || n.reading) return EBUSY;
        n.set_format(p);
        // Render the scene now, so that producing frames later costs no more than a copy (the
        // first frame must not be late because of the emulator, e.g. under valgrind).
        payload(p.pixelformat, p.width, p.height);
        ++n.state_changes;
      }
      fmt->fmt.pix = p;
      return 0;
    }
    case VIDIOC_G_PARM:
    case VIDIOC_S_PARM: {
      auto* parm = static_cast<v4l2_streamparm*>(arg);
      if (!n.spec.supports_timeperframe) return ENOTTY;
      if (!capture_type(parm->type)) return EINVAL;
      if (request == VIDIOC_S_PARM) {
        if (n.streaming) return EBUSY;  // uvcvideo cannot renegotiate while streaming
        const v4l2_fract t = parm->parm.capture.timeperframe;
        if (t.numerator && t.denominator) {
          const double want = static_cast<double>(t.denominator) / t.numerator;
          const auto r = n.rates(*n.format(n.fmt.pixelformat), n.fmt.width, n.fmt.height);
          uint32_t best = n.fps;
          for (uint32_t fps : r) {
            if (std::abs(fps - want) < std::abs(best - want)) best = fps;
          }
          n.fps = best;
          ++n.state_changes;
        }
      }
      std::memset(&parm->parm, 0, sizeof parm->parm);
      parm->parm.capture.capability = V4L2_CAP_TIMEPERFRAME;
      parm->parm.capture.timeperframe = {1, n.fps};
      return 0;
    }
    case VIDIOC_REQBUFS: {
      auto* req = static_cast<v4l2_requestbuffers*>(arg);
      if (!n.can_stream()) return ENOTTY;
      if (!capture_type(req->type) || req->memory != V4L2_MEMORY_MMAP) return EINVAL;
      if (queue_owned_by_other() || n.streaming || n.reading) return EBUSY;
      ++n.state_changes;
      n.buffers.clear();
      n.queued.clear();
      n.done.clear();
      if (req->count == 0) {
        n.owner = -1;
        req->capabilities = V4L2_BUF_CAP_SUPPORTS_MMAP;
        return 0;
      }
      const uint32_t count = std::clamp<uint32_t>(req->count, 2, n.spec.max_buffers);
      uint32_t offset = 0;
      for (uint32_t i = 0; i < count; ++i) {
        Node::Buffer b;
        b.memory = std::make_shared<std::vector<uint8_t>>(n.fmt.sizeimage);
        b.offset = offset;
        offset += (n.fmt.sizeimage + 4095) & ~4095u;  // vb2: page-aligned offset cookies
        n.buffers.push_back(b);
      }
      n.owner = fd;
      req->count = count;
      req->capabilities = V4L2_BUF_CAP_SUPPORTS_MMAP;
      return 0;
    }
    case VIDIOC_QUERYBUF:
    case VIDIOC_QBUF:
    case VIDIOC_DQBUF: {
      auto* b = static_cast<v4l2_buffer*>(arg);
      if (!n.can_stream()) return ENOTTY;
      if (!capture_type(b->type) || b->memory != V4L2_MEMORY_MMAP) return EINVAL;
      if (request != VIDIOC_QUERYBUF && queue_owned_by_other()) return EBUSY;
      if (request == VIDIOC_DQBUF) {
        if (n.stream_error) return n.stream_error;
        if (!n.streaming) return EINVAL;
        produce(n);
        const auto give_up = Clock::now() + std::chrono::seconds(30);
        while (n.done.empty()) {
          if (f.flags & O_NONBLOCK) return EAGAIN;
          if (n.queued.empty() || Clock::now() > give_up) return EIO;
          changed_.wait_for(lock, std::chrono::milliseconds(5));
          if (!n.present) return ENODEV;
          if (!n.streaming) return EINVAL;
          produce(n);
        }
        const uint32_t idx = n.done.front();
        n.done.pop_front();
        n.buffers[idx].state = Node::BufState::kDequeued;
        b->index = idx;
      }
      if (b->index >= n.buffers.size()) return EINVAL;
      Node::Buffer& buf = n.buffers[b->index];
      if (request == VIDIOC_QBUF) {
        if (buf.state != Node::BufState::kDequeued) return EINVAL;  // vb2: already queued
        buf.state = Node::BufState::kQueued;
        n.queued.push_back(b->index);
        ++n.state_changes;
      }
      b->bytesused = buf.bytesused;
      b->flags = buf.flags | V4L2_BUF_FLAG_TIMESTAMP_MONOTONIC | V4L2_BUF_FLAG_TSTAMP_SRC_SOE;
      if (buf.state == Node::BufState::kQueued) b->flags |= V4L2_BUF_FLAG_QUEUED;
      if (buf.state == Node::BufState::kDone) b->flags |= V4L2_BUF_FLAG_DONE;
      for (const auto& [addr, m] : mappings_) {
        if (m->memory == buf.memory) b->flags |= V4L2_BUF_FLAG_MAPPED;
      }
      b->field = V4L2_FIELD_NONE;
      b->timestamp = buf.timestamp;
      b->sequence = buf.sequence;
      b->m.offset = buf.offset;
      b->length = static_cast<uint32_t>(buf.memory->size());
      return 0;
    }
    case VIDIOC_STREAMON:
    case VIDIOC_STREAMOFF: {
      const auto type = *static_cast<int*>(arg);
      if (!n.can_stream()) return ENOTTY;
      if (!capture_type(static_cast<uint32_t>(type))) return EINVAL;
      if (queue_owned_by_other()) return EBUSY;
      if (request == VIDIOC_STREAMON) {
        if (n.buffers.empty()) return EINVAL;
        if (n.streaming) return 0;
        payload(n.fmt.pixelformat, n.fmt.width, n.fmt.height);  // the sensor is ready at STREAMON
        n.streaming = true;
        n.t0 = Clock::now();
        n.produced = 0;
        ++n.state_changes;
        return 0;
      }
      // STREAMOFF: every buffer goes back to the application, done or not.
      n.streaming = false;
      for (auto& buf : n.buffers) buf.state = Node::BufState::kDequeued;
      n.queued.clear();
      n.done.clear();
      changed_.notify_all();
      return 0;
    }
    case VIDIOC_QUERYCTRL:
    case VIDIOC_QUERY_EXT_CTRL: {
      if (request == VIDIOC_QUERY_EXT_CTRL && !n.spec.supports_query_ext_ctrl) return ENOTTY;
      uint32_t& id_field = request == VIDIOC_QUERYCTRL ? static_cast<v4l2_queryctrl*>(arg)->id
                                                       : static_cast<v4l2_query_ext_ctrl*>(arg)->id;
      const uint32_t raw = id_field;
      const bool next = (raw & (V4L2_CTRL_FLAG_NEXT_CTRL | V4L2_CTRL_FLAG_NEXT_COMPOUND)) != 0;
      const uint32_t base = raw & ~(V4L2_CTRL_FLAG_NEXT_CTRL | V4L2_CTRL_FLAG_NEXT_COMPOUND);
      // Control classes are listed before their controls, as v4l2-ctrls does.
      std::map<uint32_t, const ControlSpec*> entries;
      for (const auto& c : n.spec.controls) {
        entries[c.id] = &c;
        entries.emplace((c.id & 0x0fff0000) | 1, nullptr);
      }
      auto it = next ? entries.upper_bound(base) : entries.find(base);
      if (it == entries.end()) return EINVAL;
      const ControlSpec* c = it->second;
      const uint32_t id = it->first;
      const uint32_t cls = id & 0x0fff0000;
      const std::string name = c                     ? c->name
                               : cls == kUserClass   ? "User Controls"
                               : cls == kCameraClass ? "Camera Controls"
                                                     : "Controls";
      const uint32_t type = c ? c->type : uint32_t{V4L2_CTRL_TYPE_CTRL_CLASS};
      const uint32_t flags =
          c ? n.flags(*c) : uint32_t{V4L2_CTRL_FLAG_READ_ONLY | V4L2_CTRL_FLAG_WRITE_ONLY};
      if (request == VIDIOC_QUERYCTRL) {
        auto* q = static_cast<v4l2_queryctrl*>(arg);
        std::memset(q, 0, sizeof *q);
        q->id = id;
        q->type = type;
        copy_name(q->name, sizeof q->name, name);
        if (c) {
          q->minimum = static_cast<int32_t>(c->minimum);
          q->maximum = static_cast<int32_t>(c->maximum);
          q->step = static_cast<int32_t>(c->step);
          q->default_value = static_cast<int32_t>(c->default_value);
        }
        q->flags = flags;
      } else {
        auto* q = static_cast<v4l2_query_ext_ctrl*>(arg);
        std::memset(q, 0, sizeof *q);
        q->id = id;
        q->type = type;
        copy_name(reinterpret_cast<uint8_t*>(q->name), sizeof q->name, name);
        if (c) {
          q->minimum = c->minimum;
          q->maximum = c->maximum;
          q->step = static_cast<uint64_t>(c->step);
          q->default_value = c->default_value;
          q->elem_size = 4;
          q->elems = 1;
        }
        q->flags = flags;
      }
      return 0;
    }
    case VIDIOC_QUERYMENU: {
      auto* m = static_cast<v4l2_querymenu*>(arg);
      const ControlSpec* c = n.control(m->id);
      if (!c || c->type != V4L2_CTRL_TYPE_MENU) return EINVAL;
      auto it = c->menu.find(m->index);
      if (it == c->menu.end()) return EINVAL;
      std::memset(m->name, 0, sizeof m->name);
      copy_name(m->name, sizeof m->name, it->second);
      return 0;
    }
    case VIDIOC_G_CTRL:
    case VIDIOC_S_CTRL:
    case VIDIOC_G_EXT_CTRLS:
    case VIDIOC_S_EXT_CTRLS:
    case VIDIOC_TRY_EXT_CTRLS: {
      const bool ext = request != VIDIOC_G_CTRL && request != VIDIOC_S_CTRL;
      if (ext && !n.spec.supports_ext_ctrls) return ENOTTY;
      const bool write = request == VIDIOC_S_CTRL || request == VIDIOC_S_EXT_CTRLS;
      const bool check = write || request == VIDIOC_TRY_EXT_CTRLS;
      std::vector<std::pair<uint32_t, int32_t*>> items;
      v4l2_ext_controls* cs = nullptr;
      if (ext) {
        cs = static_cast<v4l2_ext_controls*>(arg);
        if (cs->count > 64) return EINVAL;
        for (uint32_t i = 0; i < cs->count; ++i) {
          const uint32_t id = cs->controls[i].id;
          // `which`: the current value, or (legacy ctrl_class) the class of every control.
          if (cs->which != V4L2_CTRL_WHICH_CUR_VAL && cs->which != V4L2_CTRL_ID2WHICH(id)) {
            cs->error_idx = cs->count;
            return EINVAL;
          }
          items.emplace_back(id, &cs->controls[i].value);
        }
      } else {
        auto* ctl = static_cast<v4l2_control*>(arg);
        items.emplace_back(ctl->id, &ctl->value);
      }
      // Validate everything first (v4l2-ctrls: all or nothing).
      std::vector<int64_t> values;
      for (size_t i = 0; i < items.size(); ++i) {
        const ControlSpec* c = n.control(items[i].first);
        const auto reject = [&](int err) {
          if (cs) cs->error_idx = static_cast<uint32_t>(check ? i : cs->count);
          return err;
        };
        if (!c) return reject(EINVAL);
        if (!check) {
          if (c->flags & V4L2_CTRL_FLAG_WRITE_ONLY) return reject(EACCES);
          values.push_back(n.value(*c));
          continue;
        }
        if (c->flags & V4L2_CTRL_FLAG_READ_ONLY) return reject(EACCES);
        if (n.inactive(*c)) return reject(EACCES);  // uvcvideo refuses inactive controls
        int64_t v = *items[i].second;
        switch (c->type) {
          case V4L2_CTRL_TYPE_BOOLEAN:
            v = v ? 1 : 0;
            break;
          case V4L2_CTRL_TYPE_MENU:
            if (v < c->minimum || v > c->maximum) return reject(ERANGE);
            if (!c->menu.count(v)) return reject(EINVAL);
            break;
          case V4L2_CTRL_TYPE_BUTTON:
            v = 0;
            break;
          default: {
            v = std::clamp(v, c->minimum, c->maximum);  // uvcvideo clamps, then rounds to step
            const int64_t step = std::max<int64_t>(c->step, 1);
            v = c->minimum + (v - c->minimum + step / 2) / step * step;
            if (v > c->maximum) v -= step;
          }
        }
        values.push_back(v);
      }
      for (size_t i = 0; i < items.size(); ++i) {
        const ControlSpec* c = n.control(items[i].first);
        if (write && c->type != V4L2_CTRL_TYPE_BUTTON) {
          // Switching an automatic mode off leaves its manual controls where the automatics were.
          std::vector<std::pair<uint32_t, bool>> before;
          for (const auto& other : n.spec.controls) {
            if (other.master == c->id) before.emplace_back(other.id, n.inactive(other));
          }
          n.values[c->id] = values[i];
          for (const auto& [other_id, was_inactive] : before) {
            const ControlSpec* other = n.control(other_id);
            if (was_inactive && !n.inactive(*other)) n.values[other_id] = other->auto_value;
          }
          ++n.state_changes;
        }
        *items[i].second = static_cast<int32_t>(values[i]);
      }
      return 0;
    }
    default:
      return ENOTTY;
  }
}

}  // namespace posecal::emu
