#include "aravis_camera.hpp"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>

#include "genicam_features.hpp"
#include "common/error.hpp"

namespace posecal::aravis {

namespace {

// The pump thread's wait for a buffer: bounds how long stop() and teardown wait for it.
constexpr guint64 kPumpPopTimeoutUs = 50000;
constexpr auto kSupervisorTick = std::chrono::milliseconds(50);

int64_t now_ns() {
  return std::chrono::duration_cast<std::chrono::nanoseconds>(
             std::chrono::steady_clock::now().time_since_epoch())
      .count();
}

std::string number(double v) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "%g", v);
  return buf;
}

std::string rect_text(const cv::Rect& r) {
  return std::to_string(r.width) + "x" + std::to_string(r.height) + "+" + std::to_string(r.x) +
         "+" + std::to_string(r.y);
}

std::string join(const std::vector<std::string>& items) {
  std::string out;
  for (const auto& s : items) out += (out.empty() ? "" : ", ") + s;
  return out;
}

// Features that change the size or layout of the payload: the stream's buffers were sized for
// the old one, so these are refused while streaming.
bool changes_payload(const std::string& name) {
  static const char* const kNames[] = {
      "PixelFormat",        "Width",           "Height",
      "BinningHorizontal",  "BinningVertical", "DecimationHorizontal",
      "DecimationVertical", "ChunkModeActive", "ChunkEnable",
      "GevSCPSPacketSize"};
  for (const char* n : kNames) {
    if (name == n) return true;
  }
  return false;
}

// Acquisition belongs to start()/stop(); running these behind the backend's back would desync
// the camera from the stream.
bool is_acquisition_command(const std::string& name) {
  return name == "AcquisitionStart" || name == "AcquisitionStop" || name == "AcquisitionAbort";
}

void on_control_lost(ArvDevice* /*device*/, gpointer data) {
  // Runs on Aravis' heartbeat thread: only flag and wake the supervisor.
  auto& wakeup = *static_cast<std::shared_ptr<SupervisorWakeup>*>(data);
  wakeup->control_lost = true;
  {
    std::lock_guard<std::mutex> lock(wakeup->mutex);
    wakeup->wake = true;
  }
  wakeup->cv.notify_all();
}

void free_wakeup(gpointer data, GClosure* /*closure*/) {
  delete static_cast<std::shared_ptr<SupervisorWakeup>*>(data);
}

bool available(gboolean (*query)(ArvCamera*, GError**), ArvCamera* camera) {
  GErr err;
  const gboolean yes = query(camera, err.out());
  return !err && yes;
}

}  // namespace

// ---------------------------------------------------------------------------------------------
// BufferPool

void BufferPool::give_back(ArvBuffer* buffer) {
  std::lock_guard<std::mutex> lock(mutex_);
  if (stream_ != nullptr) {
    arv_stream_push_buffer(stream_, buffer);  // (transfer full)
  } else {
    g_object_unref(buffer);
  }
}

void BufferPool::retire() {
  std::lock_guard<std::mutex> lock(mutex_);
  stream_ = nullptr;
}

// ---------------------------------------------------------------------------------------------
// Life cycle

AravisCameraImpl::AravisCameraImpl(GPtr<ArvCamera> camera, DeviceInfo info, Locator locator,
                                   const AravisBackendOptions& options)
    : AravisCamera(info),
      options_(options),
      label_(label()),
      locator_(std::move(locator)),
      wakeup_(std::make_shared<SupervisorWakeup>()) {
  {
    std::lock_guard<std::mutex> lock(device_mutex_);
    attach_locked(std::move(camera));
  }
  supervisor_ = std::thread(&AravisCameraImpl::supervise, this);
}

AravisCameraImpl::~AravisCameraImpl() {
  {
    std::lock_guard<std::mutex> lock(wakeup_->mutex);
    wakeup_->quit = true;
  }
  wakeup_->cv.notify_all();
  if (supervisor_.joinable()) supervisor_.join();
  {
    std::lock_guard<std::mutex> lock(device_mutex_);
    // Talking to a camera that is gone costs Aravis' full GVCP timeout per transaction.
    const Locator loc = locator();
    const bool alive = state() != CameraState::kDisconnected &&
                       (!loc.gige || loc.address.empty() ||
                        gvcp_probe(loc.address, options_.probe_timeout_ms, options_.probe_retries));
    GPtr<ArvStream> stream = stop_locked(alive);
    GPtr<ArvCamera> camera = detach_locked();
    if (alive) {
      stream.reset();
      camera.reset();
    } else {
      reap(std::move(stream), std::move(camera));
    }
  }
  std::lock_guard<std::mutex> lock(reaper_mutex_);
  for (Reaper& r : reapers_) r.thread.join();
  reapers_.clear();
}

void AravisCameraImpl::attach_locked(GPtr<ArvCamera> camera) {
  ArvCamera* cam = camera.get();
  if (arv_camera_is_gv_device(cam)) {
    if (!options_.packet_socket) {
      arv_camera_gv_set_stream_options(cam, ARV_GV_STREAM_OPTION_PACKET_SOCKET_DISABLED);
    }
    if (options_.packet_size > 0) {
      arv_camera_gv_set_packet_size_adjustment(cam, ARV_GV_PACKET_SIZE_ADJUSTMENT_NEVER);
      GErr err;
      arv_camera_gv_set_packet_size(cam, options_.packet_size, err.out());
      if (err) {
        throw Error(ErrorCode::kDevice, label_ + ": setting the GVSP packet size to " +
                                            std::to_string(options_.packet_size) +
                                            " bytes failed: " + err.message());
      }
    }
    GSocketAddress* address =
        arv_gv_device_get_device_address(ARV_GV_DEVICE(arv_camera_get_device(cam)));
    if (address != nullptr && G_IS_INET_SOCKET_ADDRESS(address)) {
      gchar* text = g_inet_address_to_string(
          g_inet_socket_address_get_address(G_INET_SOCKET_ADDRESS(address)));
      std::lock_guard<std::mutex> lock(locator_mutex_);
      locator_.address = text;
      locator_.gige = true;
      g_free(text);
    }
  }
  camera_ = std::move(camera);
  device_ = arv_camera_get_device(camera_.get());
  wakeup_->control_lost = false;
  control_lost_handler_ = g_signal_connect_data(
      device_, "control-lost", G_CALLBACK(on_control_lost),
      new std::shared_ptr<SupervisorWakeup>(wakeup_), free_wakeup, GConnectFlags(0));
}

GPtr<ArvCamera> AravisCameraImpl::detach_locked() {
  if (device_ != nullptr && control_lost_handler_ != 0) {
    g_signal_handler_disconnect(device_, control_lost_handler_);
  }
  control_lost_handler_ = 0;
  device_ = nullptr;
  return std::move(camera_);
}

Locator AravisCameraImpl::locator() const {
  std::lock_guard<std::mutex> lock(locator_mutex_);
  return locator_;
}

// ---------------------------------------------------------------------------------------------
// Configuration

CameraConfig AravisCameraImpl::read_config_locked() {
  ArvCamera* cam = camera_.get();
  auto check = [&](const GErr& err, const char* what) {
    if (err)
      throw Error(ErrorCode::kDevice, label_ + ": reading " + what + " failed: " + err.message());
  };
  CameraConfig c;
  GErr err;
  const char* format = arv_camera_get_pixel_format_as_string(cam, err.out());
  check(err, "PixelFormat");
  c.pixel_format = pixel_format_from_genicam(format != nullptr ? format : "");
  gint x = 0, y = 0, w = 0, h = 0;
  arv_camera_get_region(cam, &x, &y, &w, &h, err.out());
  check(err, "the region of interest");
  c.roi = cv::Rect(x, y, w, h);
  if (available(arv_camera_is_exposure_time_available, cam)) {
    const double v = arv_camera_get_exposure_time(cam, err.out());
    check(err, "the exposure time");
    c.exposure_us = v;
  }
  if (available(arv_camera_is_gain_available, cam)) {
    const double v = arv_camera_get_gain(cam, err.out());
    check(err, "the gain");
    c.gain_db = v;
  }
  if (available(arv_camera_is_frame_rate_available, cam)) {
    const double v = arv_camera_get_frame_rate(cam, err.out());
    check(err, "the frame rate");
    c.frame_rate_hz = v;
  }
  c.queue_depth = queue_depth_.load();
  return c;
}

void AravisCameraImpl::check_read(const GErr& err, const std::string& what) const {
  if (err) throw Error(ErrorCode::kDevice, label_ + ": reading " + what + " failed: " + err.message());
}

// Pixel format: one the camera offers and the engine converter reads (Adjusted where none was
// requested and the current one cannot be read).
std::optional<PixelFormat> AravisCameraImpl::validate_pixel_format_locked(const std::optional<PixelFormat>& requested) {
  ArvCamera* cam = camera_.get();
  GErr err;
  std::optional<PixelFormat> out = requested;
  guint n_formats = 0;
  const char** formats =
      arv_camera_dup_available_pixel_formats_as_strings(cam, &n_formats, err.out());
  check_read(err, "the available pixel formats");
  std::vector<std::string> offered;
  for (guint i = 0; formats != nullptr && i < n_formats; ++i) {
    if (formats[i] != nullptr) offered.emplace_back(formats[i]);
  }
  g_free(formats);
  auto offered_name = [&](PixelFormat f) -> std::string {
    for (const std::string& n : genicam_pixel_format_names(f)) {
      if (std::find(offered.begin(), offered.end(), n) != offered.end()) return n;
    }
    return "";
  };
  if (requested) {
    const PixelFormat f = *requested;
    if (!engine_can_convert(f)) {
      throw Error(ErrorCode::kUnsupported, label_ + ": pixel format " + pixel_format_name(f) +
                                               " is not supported by GenICam cameras");
    }
    if (offered_name(f).empty()) {
      throw Error(ErrorCode::kUnsupported, label_ + ": pixel format " + pixel_format_name(f) +
                                               " is not supported by the camera (it offers " +
                                               join(offered) + ")");
    }
  } else {
    const char* current = arv_camera_get_pixel_format_as_string(cam, err.out());
    check_read(err, "PixelFormat");
    if (!engine_can_convert(pixel_format_from_genicam(current != nullptr ? current : ""))) {
      // Adjusted: the first format the engine can read, cheapest conversion first.
      for (PixelFormat f : {PixelFormat::kMono8, PixelFormat::kBayerRG8, PixelFormat::kBayerGR8,
                            PixelFormat::kBayerGB8, PixelFormat::kBayerBG8, PixelFormat::kBGR8,
                            PixelFormat::kRGB8, PixelFormat::kYUYV, PixelFormat::kMono16}) {
        if (!offered_name(f).empty()) {
          out = f;
          break;
        }
      }
      if (!out) {
        throw Error(ErrorCode::kUnsupported, label_ + ": none of the camera's pixel formats (" +
                                                 join(offered) + ") can be converted");
      }
    }
  }

  return out;
}

// Region of interest: inside the sensor, on the camera's increments.
cv::Rect AravisCameraImpl::validate_roi_locked(const cv::Rect& requested) {
  ArvCamera* cam = camera_.get();
  GErr err;
  const cv::Rect r = requested;
  if (r.width <= 0 || r.height <= 0 || r.x < 0 || r.y < 0) {
    throw Error(ErrorCode::kInvalidArgument,
                label_ + ": ROI " + rect_text(r) +
                    " is invalid (width and height must be positive, offsets not negative)");
  }
  gint wmin = 1, wmax = 0, hmin = 1, hmax = 0, cur_x = 0, cur_y = 0, cur_w = 0, cur_h = 0;
  arv_camera_get_width_bounds(cam, &wmin, &wmax, err.out());
  check_read(err, "the width range");
  arv_camera_get_height_bounds(cam, &hmin, &hmax, err.out());
  check_read(err, "the height range");
  arv_camera_get_region(cam, &cur_x, &cur_y, &cur_w, &cur_h, err.out());
  check_read(err, "the region of interest");
  // SFNC: WidthMax = (sensor width / binning) - OffsetX, so the limit for offset + width is
  // the current maximum plus the current offset, capped by the sensor where it is known.
  int limit_w = wmax + cur_x, limit_h = hmax + cur_y;
  gint sensor_w = 0, sensor_h = 0;
  arv_camera_get_sensor_size(cam, &sensor_w, &sensor_h, err.out());
  if (!err && sensor_w > 0 && sensor_h > 0) {
    gint bx = 1, by = 1;
    if (available(arv_camera_is_binning_available, cam)) {
      GErr berr;
      arv_camera_get_binning(cam, &bx, &by, berr.out());
      if (berr || bx < 1 || by < 1) bx = by = 1;
    }
    limit_w = std::min(limit_w, sensor_w / bx);
    limit_h = std::min(limit_h, sensor_h / by);
  }
  err.reset();
  const int winc = std::max(1, arv_camera_get_width_increment(cam, nullptr));
  const int hinc = std::max(1, arv_camera_get_height_increment(cam, nullptr));
  const bool offsets = available(arv_camera_is_region_offset_available, cam);
  const int xinc = offsets ? std::max(1, arv_camera_get_x_offset_increment(cam, nullptr)) : 1;
  const int yinc = offsets ? std::max(1, arv_camera_get_y_offset_increment(cam, nullptr)) : 1;
  auto fit = [](int v, int lo, int hi, int inc) {
    v = std::clamp(v, lo, std::max(lo, hi));
    return lo + ((v - lo) / inc) * inc;
  };
  const int w = fit(r.width, wmin, limit_w, winc);
  const int h = fit(r.height, hmin, limit_h, hinc);
  int x = offsets ? (r.x / xinc) * xinc : 0;
  int y = offsets ? (r.y / yinc) * yinc : 0;
  if (x + w > limit_w) x = std::max(0, ((limit_w - w) / xinc) * xinc);
  if (y + h > limit_h) y = std::max(0, ((limit_h - h) / yinc) * yinc);
  return cv::Rect(x, y, w, h);
}

// An exposure, gain or frame rate clamped to the camera's range.
std::optional<double> AravisCameraImpl::clamp_setting_locked(const std::optional<double>& value, const char* what,
                                                             const char* unit, bool (*is_available)(ArvCamera*),
                                                             void (*bounds)(ArvCamera*, double*, double*, GError**)) {
  ArvCamera* cam = camera_.get();
  if (!value) return std::nullopt;
  if (!std::isfinite(*value) || (std::string(what) != "gain_db" && *value <= 0)) {
    throw Error(ErrorCode::kInvalidArgument,
                label_ + ": " + what + " " + number(*value) + " is invalid (" + unit + ")");
  }
  if (!is_available(cam)) {
    throw Error(ErrorCode::kUnsupported, label_ + ": the camera has no adjustable " + what);
  }
  double lo = 0, hi = 0;
  GErr berr;
  bounds(cam, &lo, &hi, berr.out());
  if (berr)
    throw Error(ErrorCode::kDevice,
                label_ + ": reading the " + what + " range failed: " + berr.message());
  return std::clamp(*value, lo, std::max(lo, hi));
}

CameraConfig AravisCameraImpl::validate_locked(const CameraConfig& requested) {
  CameraConfig out = requested;
  // Camera::validate() has checked the queue depth (at most Camera::kMaxQueueDepth).
  out.pixel_format = validate_pixel_format_locked(requested.pixel_format);
  if (requested.roi) out.roi = validate_roi_locked(*requested.roi);
  out.exposure_us = clamp_setting_locked(
      requested.exposure_us, "exposure_us", "a positive number of microseconds",
      [](ArvCamera* c) { return available(arv_camera_is_exposure_time_available, c); },
      arv_camera_get_exposure_time_bounds);
  out.gain_db = clamp_setting_locked(
      requested.gain_db, "gain_db", "a finite number",
      [](ArvCamera* c) { return available(arv_camera_is_gain_available, c); },
      arv_camera_get_gain_bounds);
  out.frame_rate_hz = clamp_setting_locked(
      requested.frame_rate_hz, "frame_rate_hz", "a positive number of frames per second",
      [](ArvCamera* c) { return available(arv_camera_is_frame_rate_available, c); },
      arv_camera_get_frame_rate_bounds);
  return out;
}

void AravisCameraImpl::apply_config_locked(const CameraConfig& c) {
  ArvCamera* cam = camera_.get();
  GErr err;
  auto check = [&](const std::string& what) {
    if (err) {
      throw Error(err.is_genicam_error() ? ErrorCode::kInvalidArgument : ErrorCode::kDevice,
                  label_ + ": setting " + what + " failed: " + err.message());
    }
  };
  auto set_int = [&](const char* feature, gint64 v) {
    arv_camera_set_integer(cam, feature, v, err.out());
    check(std::string(feature) + " to " + std::to_string(v));
  };
  if (c.pixel_format) {
    std::string entry;
    guint n = 0;
    const char** formats = arv_camera_dup_available_pixel_formats_as_strings(cam, &n, err.out());
    check("PixelFormat");
    for (const std::string& name : genicam_pixel_format_names(*c.pixel_format)) {
      for (guint i = 0; formats != nullptr && i < n && entry.empty(); ++i) {
        if (formats[i] != nullptr && name == formats[i]) entry = name;
      }
    }
    g_free(formats);
    if (entry.empty()) {
      throw Error(ErrorCode::kUnsupported, label_ + ": pixel format " +
                                               pixel_format_name(*c.pixel_format) +
                                               " is not supported by the camera");
    }
    arv_camera_set_pixel_format_from_string(cam, entry.c_str(), err.out());
    check("PixelFormat to " + entry);
  }
  if (c.roi) {
    // Offsets to 0 first so the new width and height are always within range.
    const bool offsets = available(arv_camera_is_region_offset_available, cam);
    if (offsets) {
      set_int("OffsetX", 0);
      set_int("OffsetY", 0);
    }
    set_int("Width", c.roi->width);
    set_int("Height", c.roi->height);
    if (offsets) {
      set_int("OffsetX", c.roi->x);
      set_int("OffsetY", c.roi->y);
    }
  }
  if (c.exposure_us) {
    // An explicit value means manual exposure; the automatic control would overwrite it.
    if (available(arv_camera_is_exposure_auto_available, cam)) {
      arv_camera_set_exposure_time_auto(cam, ARV_AUTO_OFF, err.out());
      check("ExposureAuto to Off");
    }
    arv_camera_set_exposure_time(cam, *c.exposure_us, err.out());
    check("the exposure time to " + number(*c.exposure_us) + " us");
  }
  if (c.gain_db) {
    if (available(arv_camera_is_gain_auto_available, cam)) {
      arv_camera_set_gain_auto(cam, ARV_AUTO_OFF, err.out());
      check("GainAuto to Off");
    }
    arv_camera_set_gain(cam, *c.gain_db, err.out());
    check("the gain to " + number(*c.gain_db));
  }
  if (c.frame_rate_hz) {
    arv_camera_set_frame_rate(cam, *c.frame_rate_hz, err.out());
    check("the frame rate to " + number(*c.frame_rate_hz) + " Hz");
  }
  queue_depth_ = c.queue_depth;
}

void AravisCameraImpl::record_locked(Setting setting) {
  // One entry per feature (and one configure()), in the order of their last change.
  settings_.erase(std::remove_if(settings_.begin(), settings_.end(),
                                 [&](const Setting& s) {
                                   return setting.config ? s.config.has_value()
                                                         : (!s.config && s.name == setting.name);
                                 }),
                  settings_.end());
  settings_.push_back(std::move(setting));
}

CameraConfig AravisCameraImpl::do_current_config() {
  std::lock_guard<std::mutex> lock(device_mutex_);
  return read_config_locked();
}

CameraConfig AravisCameraImpl::do_validate(const CameraConfig& requested) {
  std::lock_guard<std::mutex> lock(device_mutex_);
  return validate_locked(requested);
}

void AravisCameraImpl::do_configure(const CameraConfig& valid) {
  std::lock_guard<std::mutex> lock(device_mutex_);
  apply_config_locked(valid);
  record_locked(Setting{valid, "", ""});
  configured_ = true;
}

// ---------------------------------------------------------------------------------------------
// Features

std::vector<FeatureInfo> AravisCameraImpl::do_features() {
  std::lock_guard<std::mutex> lock(device_mutex_);
  return list_features(device_);
}

std::string AravisCameraImpl::do_get_feature(const std::string& name) {
  std::lock_guard<std::mutex> lock(device_mutex_);
  return read_feature(device_, label_, name);
}

void AravisCameraImpl::do_set_feature(const std::string& name, const std::string& value) {
  std::lock_guard<std::mutex> lock(device_mutex_);
  if (is_acquisition_command(name)) {
    throw Error(ErrorCode::kInvalidArgument,
                label_ + ": feature '" + name + "' is driven by start()/stop(), not set_feature()");
  }
  if (state() == CameraState::kStreaming && changes_payload(name)) {
    throw Error(ErrorCode::kState, label_ + ": feature '" + name +
                                       "' changes the frame layout and cannot be set while "
                                       "streaming (stop() first)");
  }
  write_feature_locked(name, value);
}

void AravisCameraImpl::write_feature_locked(const std::string& name, const std::string& value) {
  write_feature(device_, label_, name, value);
  ArvGcFeatureNode* f = find_feature(device_, name);
  // Commands are actions, not state: they are not replayed after a reconnect.
  if (f != nullptr && !ARV_IS_GC_COMMAND(f)) record_locked(Setting{std::nullopt, name, value});
}

std::map<std::string, std::string> AravisCameraImpl::do_lock_for_calibration() {
  std::lock_guard<std::mutex> lock(device_mutex_);
  std::map<std::string, std::string> locked;
  // Automatic controls that would change the image (or, for focus, the intrinsics) mid-way.
  for (const char* name : {"ExposureAuto", "GainAuto", "BalanceWhiteAuto", "FocusAuto"}) {
    ArvGcFeatureNode* f = find_feature(device_, name);
    if (f == nullptr || !ARV_IS_GC_ENUMERATION(f)) continue;
    const std::vector<std::string> options = enumeration_options(f);
    if (std::find(options.begin(), options.end(), "Off") == options.end()) continue;
    write_feature_locked(name, "Off");
    locked[name] = read_feature(device_, label_, name);
  }
  // The values the controls left behind, pinned so that a reconnect restores them too.
  for (const char* name : {"ExposureTime", "ExposureTimeAbs", "Gain", "GainRaw", "FocusPosition"}) {
    ArvGcFeatureNode* f = find_feature(device_, name);
    if (f == nullptr) continue;
    const FeatureInfo fi = describe_feature(f);
    if (!fi.readable) continue;
    locked[name] = fi.value;
    if (fi.writable) record_locked(Setting{std::nullopt, name, fi.value});
  }
  // What else determines the intrinsics of the images being calibrated.
  for (const char* name :
       {"PixelFormat", "Width", "Height", "OffsetX", "OffsetY", "BinningHorizontal",
        "BinningVertical", "DecimationHorizontal", "DecimationVertical", "ReverseX", "ReverseY"}) {
    ArvGcFeatureNode* f = find_feature(device_, name);
    if (f == nullptr) continue;
    const FeatureInfo fi = describe_feature(f);
    if (fi.readable) locked[name] = fi.value;
  }
  return locked;
}

// ---------------------------------------------------------------------------------------------
// Streaming

void AravisCameraImpl::do_start() {
  std::lock_guard<std::mutex> lock(device_mutex_);
  start_locked();
  if (state() == CameraState::kDisconnected) {
    // A disconnect was declared meanwhile; the supervisor's teardown releases the stream.
    throw Error(ErrorCode::kDevice, label_ + " disconnected during start()");
  }
  want_streaming_ = true;
}

void AravisCameraImpl::start_locked() {
  ArvCamera* cam = camera_.get();
  GErr err;
  auto fail = [&](const std::string& what) {
    throw Error(ErrorCode::kDevice,
                label_ + ": " + what + " failed" + (err ? ": " + err.message() : std::string()));
  };
  const char* format = arv_camera_get_pixel_format_as_string(cam, err.out());
  if (err) fail("reading PixelFormat");
  if (!engine_can_convert(pixel_format_from_genicam(format != nullptr ? format : ""))) {
    throw Error(ErrorCode::kUnsupported,
                label_ + ": pixel format " + (format != nullptr ? format : "?") +
                    " cannot be converted for the engine (configure a supported one)");
  }
  const guint payload = arv_camera_get_payload(cam, err.out());
  if (err || payload == 0) fail("reading PayloadSize");
  GPtr<ArvStream> stream(arv_camera_create_stream(cam, nullptr, nullptr, err.out()));
  if (!stream) fail("creating the stream");
  if (ARV_IS_GV_STREAM(stream.get())) {
    // Four frames of socket buffer: a camera sends a frame as one burst of packets.
    const gint socket_buffer =
        options_.socket_buffer_size > 0
            ? options_.socket_buffer_size
            : static_cast<gint>(std::min<guint64>(4ull * payload, guint64{64} << 20));
    g_object_set(stream.get(), "packet-resend",
                 options_.packet_resend ? ARV_GV_STREAM_PACKET_RESEND_ALWAYS
                                        : ARV_GV_STREAM_PACKET_RESEND_NEVER,
                 "socket-buffer", ARV_GV_STREAM_SOCKET_BUFFER_FIXED, "socket-buffer-size",
                 socket_buffer, "packet-timeout", static_cast<guint>(options_.packet_timeout_us),
                 "frame-retention", static_cast<guint>(options_.frame_retention_us), nullptr);
  }
  auto pool = std::make_shared<BufferPool>(stream.get());
  const int n_buffers = queue_depth_.load() + options_.max_lent_buffers + options_.extra_buffers;
  for (int i = 0; i < n_buffers; ++i)
    arv_stream_push_buffer(stream.get(), arv_buffer_new_allocate(payload));
  arv_camera_set_acquisition_mode(cam, ARV_ACQUISITION_MODE_CONTINUOUS, err.out());
  if (err) fail("setting AcquisitionMode to Continuous");
  last_buffer_ns_ = now_ns();
  discard_until_ns_ = now_ns() + int64_t{options_.startup_discard_ms} * 1000000;
  arv_camera_start_acquisition(cam, err.out());
  if (err) {
    pool->retire();
    fail("starting acquisition");
  }
  stream_ = std::move(stream);
  pool_ = pool;
  pump_quit_ = false;
  pump_thread_ = std::thread(&AravisCameraImpl::pump, this, pool, stream_.get());
}

GPtr<ArvStream> AravisCameraImpl::stop_locked(bool talk_to_camera) {
  if (pump_thread_.joinable()) {
    pump_quit_ = true;
    pump_thread_.join();
  }
  if (camera_ && stream_ && talk_to_camera) {
    GErr err;  // a camera that fails to stop is caught by the supervisor's probe
    arv_camera_stop_acquisition(camera_.get(), err.out());
  }
  if (pool_) pool_->retire();
  {
    std::lock_guard<std::mutex> lock(queue_mutex_);
    for (Queued& q : queue_) q.pool->give_back(q.buffer);
    queue_.clear();
  }
  pool_.reset();
  return std::move(stream_);
}

void AravisCameraImpl::do_stop() {
  std::lock_guard<std::mutex> lock(device_mutex_);
  want_streaming_ = false;
  GPtr<ArvStream> stream = stop_locked(true);
  stream.reset();
}

void AravisCameraImpl::do_stop_while_disconnected() {
  std::lock_guard<std::mutex> lock(device_mutex_);
  want_streaming_ = false;  // do not resume after a reconnect
}

void AravisCameraImpl::pump(std::shared_ptr<BufferPool> pool, ArvStream* stream) {
  while (!pump_quit_.load()) {
    ArvBuffer* buffer = arv_stream_timeout_pop_buffer(stream, kPumpPopTimeoutUs);
    if (buffer == nullptr) continue;
    last_buffer_ns_ = now_ns();
    if (last_buffer_ns_.load() < discard_until_ns_) {
      // Complete or not, possibly assembled with other cameras' packets (startup_discard_ms).
      ++dropped_;
      pool->give_back(buffer);
      continue;
    }
    size_t size = 0;
    if (arv_buffer_get_status(buffer) != ARV_BUFFER_STATUS_SUCCESS ||
        arv_buffer_get_image_data(buffer, &size) == nullptr) {
      // Missing packets, timeouts, size mismatches: never passed on.
      ++incomplete_;
      pool->give_back(buffer);
      continue;
    }
    {
      std::lock_guard<std::mutex> lock(queue_mutex_);
      // Bounded queue: the oldest frame makes room (calibration wants the newest view).
      while (queue_.size() >= static_cast<size_t>(std::max(1, queue_depth_.load()))) {
        Queued oldest = queue_.front();
        queue_.pop_front();
        oldest.pool->give_back(oldest.buffer);
        ++dropped_;
      }
      queue_.push_back(Queued{buffer, pool});
    }
    queue_cv_.notify_one();
  }
}

FrameStatus AravisCameraImpl::do_next_frame(int timeout_ms, Frame* frame) {
  CameraState s = state();
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::milliseconds(timeout_ms);
  Queued item{};
  {
    std::unique_lock<std::mutex> lock(queue_mutex_);
    for (;;) {
      s = state();
      if (s == CameraState::kDisconnected) return FrameStatus::kDisconnected;
      if (!queue_.empty()) {
        item = queue_.front();
        queue_.pop_front();
        break;
      }
      if (s != CameraState::kStreaming) {
        throw Error(ErrorCode::kState, label_ + ": next_frame() while " + camera_state_name(s));
      }
      if (queue_cv_.wait_until(lock, deadline) == std::cv_status::timeout && queue_.empty()) {
        return state() == CameraState::kDisconnected ? FrameStatus::kDisconnected
                                                           : FrameStatus::kTimeout;
      }
    }
  }
  return deliver(std::move(item), frame);
}

FrameStatus AravisCameraImpl::deliver(Queued item, Frame* frame) {
  // The caller's previous frame is being replaced: give its buffer back before deciding whether
  // this one can be lent (a consumer reusing one Frame then never forces a copy).
  frame->hold.reset();
  frame->image.release();
  ArvBuffer* buffer = item.buffer;
  size_t size = 0;
  const void* data = arv_buffer_get_image_data(buffer, &size);
  const int width = arv_buffer_get_image_width(buffer);
  const int height = arv_buffer_get_image_height(buffer);
  gint x_padding = 0, y_padding = 0;
  arv_buffer_get_image_padding(buffer, &x_padding, &y_padding);
  const ArvPixelFormat arv_format = arv_buffer_get_image_pixel_format(buffer);
  const PixelFormat format = pixel_format_from_arv(arv_format);
  const int bpp = bytes_per_pixel(format);
  cv::Mat image;
  bool lend = false;
  try {
    if (bpp == 0) {
      char code[16];
      std::snprintf(code, sizeof code, "0x%08x", static_cast<unsigned>(arv_format));
      throw Error(ErrorCode::kUnsupported, label_ + ": received a frame in pixel format " + code +
                                               ", which cannot be converted");
    }
    const size_t stride =
        static_cast<size_t>(width) * bpp + static_cast<size_t>(std::max(0, x_padding));
    image = convert_to_engine(format, data, size, width, height, stride);
    if (image.data == static_cast<const uchar*>(data)) {
      // Mono8/BGR8 wrap the buffer: lend it unless too many are out already.
      if (options_.zero_copy && item.pool->lent.load() < options_.max_lent_buffers) {
        lend = true;
      } else {
        image = image.clone();
        ++copied_;
      }
    }
  } catch (...) {
    item.pool->give_back(buffer);
    ++incomplete_;
    throw;
  }
  frame->image = image;
  frame->frame_id = arv_buffer_get_frame_id(buffer);
  const guint64 device_ts = arv_buffer_get_timestamp(buffer);
  frame->timestamp_ns = device_ts != 0 ? static_cast<int64_t>(device_ts) : now_ns();
  frame->source_format = format;
  if (lend) {
    ++item.pool->lent;
    ++zero_copy_;
    std::shared_ptr<BufferPool> pool = item.pool;
    frame->hold = std::shared_ptr<void>(buffer, [pool](void* b) {
      --pool->lent;
      pool->give_back(static_cast<ArvBuffer*>(b));
    });
  } else {
    item.pool->give_back(buffer);
  }
  ++delivered_;
  return FrameStatus::kOk;
}

CameraStats AravisCameraImpl::do_stats() const {
  CameraStats s;
  s.frames_delivered = delivered_.load();
  s.frames_dropped = dropped_.load();
  s.frames_incomplete = incomplete_.load();
  s.disconnects = disconnects_.load();
  return s;
}

AravisTransportStats AravisCameraImpl::transport_stats() {
  std::lock_guard<std::mutex> lock(device_mutex_);
  if (state() == CameraState::kDisconnected) {
    throw Error(ErrorCode::kState, label_ + ": transport_stats() is not allowed while disconnected");
  }
  AravisTransportStats t;
  t.protocol = info().transport;
  t.device_address = locator().address;
  if (arv_camera_is_gv_device(camera_.get())) {
    GErr err;
    t.packet_size = arv_camera_gv_get_packet_size(camera_.get(), err.out());
  }
  t.packet_resend = options_.packet_resend;
  if (stream_) {
    guint64 completed = 0, failures = 0, underruns = 0;
    arv_stream_get_statistics(stream_.get(), &completed, &failures, &underruns);
    t.completed_buffers = completed;
    t.failed_buffers = failures;
    t.underruns = underruns;
    if (ARV_IS_GV_STREAM(stream_.get())) {
      t.resent_packets = arv_stream_get_info_uint64_by_name(stream_.get(), "n_resent_packets");
      t.missing_packets = arv_stream_get_info_uint64_by_name(stream_.get(), "n_missing_packets");
    }
  }
  t.frames_zero_copy = zero_copy_.load();
  t.frames_copied = copied_.load();
  t.buffers_lent = pool_ ? pool_->lent.load() : 0;
  t.reconnects = reconnects_.load();
  return t;
}

// ---------------------------------------------------------------------------------------------
// Supervisor: liveness, disconnect, reconnect

void AravisCameraImpl::emit(CameraEvent::Kind kind, const std::string& message) {
  emit_event(CameraEvent{kind, message});
}

bool AravisCameraImpl::probe() {
  const Locator loc = locator();
  if (loc.gige && !loc.address.empty()) {
    return gvcp_probe(loc.address, options_.probe_timeout_ms, options_.probe_retries);
  }
  // USB3 Vision: a register read (a vanished USB device fails at once). Skip the round if the
  // session thread is using the device.
  std::unique_lock<std::mutex> lock(device_mutex_, std::try_to_lock);
  if (!lock.owns_lock() || device_ == nullptr) return true;
  guint32 value = 0;
  GErr err;
  return arv_device_read_register(device_, 0x0, &value, err.out()) != FALSE;
}

void AravisCameraImpl::supervise() {
  const int64_t ms = 1000000;
  int64_t last_probe = now_ns();
  int64_t next_attempt = 0;
  int backoff_ms = options_.reconnect_min_backoff_ms;
  int attempt = 0;
  std::unique_lock<std::mutex> lock(wakeup_->mutex);
  while (!wakeup_->quit) {
    wakeup_->cv.wait_for(lock, kSupervisorTick, [&] { return wakeup_->quit || wakeup_->wake; });
    if (wakeup_->quit) break;
    wakeup_->wake = false;
    lock.unlock();
    const int64_t now = now_ns();
    const CameraState s = state();
    if (s == CameraState::kDisconnected) {
      if (options_.auto_reconnect && now >= next_attempt) {
        if (try_reconnect(++attempt)) {
          attempt = 0;
          backoff_ms = options_.reconnect_min_backoff_ms;
          last_probe = now_ns();
        } else {
          next_attempt = now_ns() + backoff_ms * ms;
          backoff_ms = std::min(backoff_ms * 2, options_.reconnect_max_backoff_ms);
        }
      }
    } else if (wakeup_->control_lost.exchange(false)) {
      declare_disconnected("Aravis lost control of the camera (heartbeat failed)");
      next_attempt = now_ns() + options_.reconnect_min_backoff_ms * ms;
      backoff_ms = options_.reconnect_min_backoff_ms;
    } else {
      bool due;
      int64_t gap_ms = 0;
      if (s == CameraState::kStreaming) {
        gap_ms = (now - last_buffer_ns_.load()) / ms;
        due = gap_ms >= options_.frame_timeout_ms &&
              (now - last_probe) / ms >= options_.frame_timeout_ms;
      } else {
        due = (now - last_probe) / ms >= options_.idle_probe_interval_ms;
      }
      if (due) {
        last_probe = now;
        if (!probe()) {
          const Locator loc = locator();
          std::string why = "the camera does not answer";
          if (loc.gige) why += " GVCP at " + loc.address;
          if (s == CameraState::kStreaming)
            why = "no frame for " + std::to_string(gap_ms) + " ms and " + why;
          declare_disconnected(why);
          next_attempt = now_ns() + options_.reconnect_min_backoff_ms * ms;
          backoff_ms = options_.reconnect_min_backoff_ms;
        }
      }
    }
    lock.lock();
  }
}

void AravisCameraImpl::declare_disconnected(const std::string& why) {
  {
    std::lock_guard<std::mutex> lock(queue_mutex_);
    if (!mark_disconnected()) return;
    // Frames queued before the disconnect are stale; next_frame reports the disconnect now.
    dropped_ += queue_.size();
    for (Queued& q : queue_) q.pool->give_back(q.buffer);
    queue_.clear();
  }
  queue_cv_.notify_all();
  ++disconnects_;
  emit(CameraEvent::Kind::kDisconnected, label_ + " disconnected: " + why);
  std::lock_guard<std::mutex> lock(device_mutex_);
  GPtr<ArvStream> stream = stop_locked(false);
  reap(std::move(stream), detach_locked());
}

void AravisCameraImpl::reap(GPtr<ArvStream> stream, GPtr<ArvCamera> camera) {
  if (!stream && !camera) return;
  std::lock_guard<std::mutex> lock(reaper_mutex_);
  for (auto it = reapers_.begin(); it != reapers_.end();) {
    if (it->done->load()) {
      it->thread.join();
      it = reapers_.erase(it);
    } else {
      ++it;
    }
  }
  auto done = std::make_shared<std::atomic<bool>>(false);
  // Releasing a vanished camera's objects talks to it (the stream resets the camera's stream
  // channel, the device leaves control) and waits out Aravis' GVCP timeouts: off the supervisor.
  std::thread t([s = stream.release(), c = camera.release(), done] {
    if (s != nullptr) g_object_unref(s);
    if (c != nullptr) g_object_unref(c);
    *done = true;
  });
  reapers_.push_back(Reaper{std::move(t), done});
}

// Where the vanished camera answers again: its address if the cheap probe succeeds, else (every
// fourth attempt: the probe failed three times) what discovery (one second) finds with its serial
// number or device id, at another address (DHCP) or on USB, where discovery is the only way. ""
// if nowhere.
std::string AravisCameraImpl::find_again(int attempt) const {
  const Locator loc = locator();
  std::string target;
  if (loc.gige && !loc.address.empty() &&
      gvcp_probe(loc.address, options_.probe_timeout_ms, options_.probe_retries)) {
    target = loc.address;
  } else if (!loc.gige || attempt % 4 == 0) {
    std::lock_guard<std::mutex> lock(device_list_mutex());
    arv_update_device_list();
    const unsigned n = arv_get_n_devices();
    for (unsigned i = 0; i < n && target.empty(); ++i) {
      const char* id = arv_get_device_id(i);
      const char* serial = arv_get_device_serial_nbr(i);
      const char* address = arv_get_device_address(i);
      const char* protocol = arv_get_device_protocol(i);
      const bool match = (serial != nullptr && !loc.serial.empty() && loc.serial == serial) ||
                         (id != nullptr && !loc.device_id.empty() && loc.device_id == id);
      if (!match) continue;
      const bool gige = protocol != nullptr && std::string(protocol) == "GigEVision";
      target = gige && address != nullptr ? address : (id != nullptr ? id : "");
    }
  }
  return target;
}

// Opens `target` and checks that it is the same camera (serial number); nullptr if not.
GPtr<ArvCamera> AravisCameraImpl::reopen(const std::string& target) const {
  const Locator loc = locator();
  GPtr<ArvCamera> camera;
  {
    std::lock_guard<std::mutex> lock(device_list_mutex());
    GErr err;
    camera.reset(arv_camera_new(target.c_str(), err.out()));
  }
  if (!camera) return nullptr;
  {
    GErr err;
    const char* serial = arv_camera_get_device_serial_number(camera.get(), err.out());
    if (err || serial == nullptr || (!loc.serial.empty() && loc.serial != serial)) return nullptr;
  }

  return camera;
}

// Replays what the session asked for, in order; the settings that failed.
std::vector<std::string> AravisCameraImpl::restore_settings_locked() {
  std::vector<std::string> problems;
  for (const Setting& s : settings_) {
    try {
      if (s.config) {
        apply_config_locked(validate_locked(*s.config));
      } else {
        write_feature(device_, label_, s.name, s.value);
      }
    } catch (const std::exception& e) {
      problems.push_back(e.what());
    }
  }
  return problems;
}

bool AravisCameraImpl::try_reconnect(int attempt) {
  const std::string target = find_again(attempt);
  if (target.empty()) return false;
  GPtr<ArvCamera> camera = reopen(target);
  if (!camera) return false;

  std::vector<std::string> problems;
  bool streaming = false;
  {
    std::lock_guard<std::mutex> lock(device_mutex_);
    try {
      attach_locked(std::move(camera));
    } catch (const std::exception&) {
      return false;
    }
    problems = restore_settings_locked();
    CameraState target_state = configured_ ? CameraState::kConfigured : CameraState::kOpened;
    bool failed = false;
    if (want_streaming_) {
      try {
        start_locked();
        target_state = CameraState::kStreaming;
        streaming = true;
      } catch (const std::exception&) {
        failed = true;
      }
    }
    // Settings that failed because the camera vanished again do not make a reconnect.
    const Locator now_at = locator();
    if (!failed && !problems.empty() && now_at.gige &&
        !gvcp_probe(now_at.address, options_.probe_timeout_ms, options_.probe_retries)) {
      failed = true;
    }
    if (failed) {
      GPtr<ArvStream> stream = stop_locked(false);
      reap(std::move(stream), detach_locked());
      return false;
    }
    wakeup_->control_lost = false;
    last_buffer_ns_ = now_ns();
    mark_reconnected(target_state);
  }
  ++reconnects_;
  emit(CameraEvent::Kind::kReconnected,
       label_ + " reconnected" + (streaming ? " and streaming again" : ""));
  for (const std::string& p : problems) {
    emit(CameraEvent::Kind::kError,
         label_ + ": restoring a setting after the reconnect failed: " + p);
  }
  return true;
}

}  // namespace posecal::aravis
