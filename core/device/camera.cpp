// The camera state machine, once for every backend: each public call checks the state, then
// calls the backend's hook (camera.hpp draws the states and the table of allowed calls).
#include "device/camera.hpp"

#include "common/error.hpp"

namespace posecal {

const char* camera_state_name(CameraState s) {
  switch (s) {
    case CameraState::kOpened: return "opened";
    case CameraState::kConfigured: return "configured";
    case CameraState::kStreaming: return "streaming";
    case CameraState::kDisconnected: return "disconnected";
  }
  return "unknown";
}

const char* feature_type_name(FeatureType t) {
  switch (t) {
    case FeatureType::kInteger: return "integer";
    case FeatureType::kFloat: return "float";
    case FeatureType::kBoolean: return "boolean";
    case FeatureType::kEnumeration: return "enumeration";
    case FeatureType::kString: return "string";
    case FeatureType::kCommand: return "command";
  }
  return "unknown";
}

namespace {
constexpr std::initializer_list<CameraState> kUsable = {CameraState::kOpened, CameraState::kConfigured,
                                                        CameraState::kStreaming};
constexpr std::initializer_list<CameraState> kIdle = {CameraState::kOpened, CameraState::kConfigured};
}  // namespace

Camera::Camera(DeviceInfo info, std::string label) : info_(std::move(info)), label_(std::move(label)) {
  if (label_.empty()) label_ = "camera '" + info_.uri + "'";
}

void Camera::set_info(DeviceInfo info, std::string label) {
  info_ = std::move(info);
  label_ = label.empty() ? "camera '" + info_.uri + "'" : std::move(label);
}

void Camera::require(std::initializer_list<CameraState> allowed, const char* call) const {
  const CameraState s = state();
  for (const CameraState a : allowed)
    if (a == s) return;
  std::string hint;
  if (s == CameraState::kDisconnected) hint = " (the camera is gone)";
  if (allowed.size() == 1 && *allowed.begin() == CameraState::kStreaming) hint = " (start() first)";
  if (s == CameraState::kStreaming) hint = " (stop() first)";
  throw Error(ErrorCode::kState, label_ + ": " + call + "() is not allowed while " + camera_state_name(s) + hint);
}

void Camera::transition(std::initializer_list<CameraState> from, CameraState to, const char* call) {
  if (followed_) return;
  CameraState s = state();
  while (true) {
    bool allowed = false;
    for (const CameraState f : from) allowed = allowed || f == s;
    if (!allowed) break;
    if (state_.compare_exchange_weak(s, to)) return;
  }
  if (s == to) return;
  throw Error(ErrorCode::kDevice, label_ + " disconnected during " + call + "()");
}

CameraConfig Camera::current_config() {
  require(kUsable, "current_config");
  return do_current_config();
}

CameraConfig Camera::validate(const CameraConfig& requested) {
  require(kUsable, "validate");
  if (requested.queue_depth < 1 || requested.queue_depth > kMaxQueueDepth) {
    throw Error(ErrorCode::kInvalidArgument, label_ + ": queue_depth must be in [1, " +
                                                 std::to_string(kMaxQueueDepth) + "], got " +
                                                 std::to_string(requested.queue_depth));
  }
  return do_validate(requested);
}

void Camera::configure(const CameraConfig& config) {
  require(kIdle, "configure");
  do_configure(validate(config));
  transition(kIdle, CameraState::kConfigured, "configure");
}

std::vector<FeatureInfo> Camera::features() {
  require(kUsable, "features");
  return do_features();
}

std::string Camera::get_feature(const std::string& name) {
  require(kUsable, "get_feature");
  return do_get_feature(name);
}

void Camera::set_feature(const std::string& name, const std::string& value) {
  require(kUsable, "set_feature");
  do_set_feature(name, value);
}

std::map<std::string, std::string> Camera::lock_for_calibration() {
  require(kUsable, "lock_for_calibration");
  return do_lock_for_calibration();
}

void Camera::start() {
  require(kIdle, "start");
  if (state() == CameraState::kOpened) configure(CameraConfig{});
  do_start();
  transition({CameraState::kConfigured}, CameraState::kStreaming, "start");
}

void Camera::stop() {
  if (state() == CameraState::kDisconnected) do_stop_while_disconnected();
  if (state() != CameraState::kStreaming) return;
  do_stop();
  if (followed_) return;
  CameraState s = CameraState::kStreaming;
  state_.compare_exchange_strong(s, CameraState::kConfigured);  // a disconnect meanwhile stays
}

FrameStatus Camera::next_frame(int timeout_ms, Frame* frame) {
  if (frame == nullptr) throw Error(ErrorCode::kInvalidArgument, label_ + ": next_frame(): frame is null");
  if (timeout_ms < 0) {
    throw Error(ErrorCode::kInvalidArgument,
                label_ + ": next_frame(): negative timeout " + std::to_string(timeout_ms) + " ms");
  }
  if (state() == CameraState::kDisconnected) return FrameStatus::kDisconnected;
  require({CameraState::kStreaming}, "next_frame");
  return do_next_frame(timeout_ms, frame);
}

void Camera::set_event_callback(CameraEventCallback cb) {
  std::lock_guard<std::mutex> lock(callback_mutex_);
  callback_ = std::move(cb);
}

std::string Camera::do_get_feature(const std::string& name) {
  throw Error(ErrorCode::kNotFound, label_ + " has no feature '" + name + "'");
}

void Camera::do_set_feature(const std::string& name, const std::string&) {
  throw Error(ErrorCode::kNotFound, label_ + " has no feature '" + name + "'");
}

bool Camera::mark_disconnected() {
  return state_.exchange(CameraState::kDisconnected) != CameraState::kDisconnected;
}

void Camera::mark_reconnected(CameraState state) { state_.store(state); }

void Camera::emit_event(const CameraEvent& event) const {
  CameraEventCallback cb;
  {
    std::lock_guard<std::mutex> lock(callback_mutex_);
    cb = callback_;
  }
  if (!cb) return;
  try {
    cb(event);
  } catch (...) {
    // A host's callback must not take the backend's thread down with it.
  }
}

}  // namespace posecal
