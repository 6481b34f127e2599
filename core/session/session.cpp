#include "session/session.hpp"

#include <sys/stat.h>

#include <cstdio>

#include "common/clock.hpp"
#include "common/error.hpp"

namespace posecal {

const char* step_status_name(StepStatus s) {
  switch (s) {
    case StepStatus::kFrame: return "frame";
    case StepStatus::kTimeout: return "timeout";
    case StepStatus::kDisconnected: return "disconnected";
    case StepStatus::kEndOfStream: return "end_of_stream";
    case StepStatus::kFinished: return "finished";
  }
  return "unknown";
}

CalibrationSession::CalibrationSession(std::unique_ptr<Camera> camera, const EngineOptions& options,
                                       bool lock_settings)
    : camera_(std::move(camera)), options_(options), lock_settings_(lock_settings) {
  if (!camera_) throw Error(ErrorCode::kInvalidArgument, "session: no camera");
  std::string why;
  if (!options.is_valid(&why)) throw Error(ErrorCode::kInvalidArgument, "session options: " + why);
  t0_ = std::chrono::steady_clock::now();
}

CalibrationSession::~CalibrationSession() {
  try {
    camera_->stop();
  } catch (...) {
    // Destructors never throw; a camera that cannot stop is already gone.
  }
}

void CalibrationSession::set_event_callback(std::function<void(const SessionEvent&)> cb) {
  callback_ = std::move(cb);
  if (engine_) {
    engine_->set_event_callback([this](const EngineEvent& e) { emit({SessionEvent::Kind::kEngine, e, ""}); });
  }
}

void CalibrationSession::emit(const SessionEvent& e) {
  if (callback_) callback_(e);
}

void CalibrationSession::ensure_engine(cv::Size size) {
  if (engine_) {
    if (size.width != engine_->estimate().width() || size.height != engine_->estimate().height()) {
      throw Error(ErrorCode::kInvalidArgument, "session: frame size changed from " +
                                                   std::to_string(engine_->estimate().width()) + "x" +
                                                   std::to_string(engine_->estimate().height()) + " to " +
                                                   std::to_string(size.width) + "x" + std::to_string(size.height));
    }
    return;
  }
  engine_ = std::make_unique<CalibrationEngine>(size, options_);
  if (observer_.on_engine) observer_.on_engine(size, locked_);
  restore_from_journal(size);
  board_clock_ = std::chrono::steady_clock::now();
  engine_->set_event_callback([this](const EngineEvent& e) { emit({SessionEvent::Kind::kEngine, e, ""}); });
}

CalibrationEngine& CalibrationSession::engine() {
  if (!engine_) throw Error(ErrorCode::kState, "session: no frame processed yet");
  return *engine_;
}

bool CalibrationSession::finished() const {
  if (!no_frame_failure_.empty()) return true;
  return engine_ && (engine_->state() == EngineState::kConverged || engine_->state() == EngineState::kFailed);
}

double CalibrationSession::wall_ms() const {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0_).count();
}

void CalibrationSession::check_board_timeout() {
  const double limit_s = options_.board_timeout_s;
  if (finished() || disconnected_ || limit_s <= 0 || (!engine_ && !started_)) return;
  const double waited_s =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - board_clock_).count();
  if (waited_s < limit_s) return;
  char figures[96];
  std::snprintf(figures, sizeof figures, " for %.3g s (board_timeout_s = %g)", waited_s, limit_s);
  if (!engine_) {
    // The camera was started but has not delivered a single frame: no engine exists to fail.
    no_frame_failure_ = "no frame from the camera" + std::string(figures);
    emit({SessionEvent::Kind::kCameraError, std::nullopt, no_frame_failure_});
    return;
  }
  engine_->give_up("no board (" + options_.board.to_string() + ") seen" + figures);
}

FrameReport CalibrationSession::feed(const cv::Mat& image) {
  // A host frame is the caller's only for this call: last_frame() keeps a copy.
  return process(image.clone(), nullptr);
}

FrameReport CalibrationSession::process(const cv::Mat& image, std::shared_ptr<void> hold) {
  if (finished()) throw Error(ErrorCode::kState, "session: calibration already finished");
  ensure_engine(image.size());
  // Camera frames may point into a backend buffer (zero-copy Aravis frames): keep the buffer
  // alive as long as last_frame() refers to it.
  last_frame_ = image;
  last_hold_ = std::move(hold);
  ++frames_;
  const EngineState state_before = engine_->state();
  const int keyframes_before = engine_->keyframes();
  const FrameReport r = engine_->process(image);
  if (r.board_visible) board_clock_ = std::chrono::steady_clock::now();
  check_board_timeout();
  journal_frame(state_before, keyframes_before, image);
  if (observer_.on_keyframe && engine_->keyframes() > keyframes_before) {
    const int n = engine_->keyframes();
    observer_.on_keyframe(n, engine_->keyframe_record(n - 1, state_before), image);
  }
  camera_->guide(engine_->guidance_info());
  if (camera_->take_pose_reached() && !finished()) {
    try {
      engine_->report_pose_reached();
    } catch (const Error&) {
      // No target at this instant (e.g. just converged): nothing to report.
    }
  }
  return r;
}

StepStatus CalibrationSession::step(int timeout_ms) {
  if (finished()) return StepStatus::kFinished;
  if (timeout_ms < 0) throw Error(ErrorCode::kInvalidArgument, "session: timeout must be >= 0");
  if (!started_) {
    if (lock_settings_) {
      try {
        locked_ = camera_->lock_for_calibration();
      } catch (const Error& e) {
        emit({SessionEvent::Kind::kCameraError, std::nullopt, std::string("settings lock failed: ") + e.what()});
      }
    }
    camera_->start();
    started_ = true;
    board_clock_ = std::chrono::steady_clock::now();  // until the first frame: since the start
  }
  Frame frame;
  FrameStatus fs;
  try {
    fs = camera_->next_frame(timeout_ms, &frame);
  } catch (const Error& e) {
    if (e.code() != ErrorCode::kDevice) throw;
    fs = FrameStatus::kDisconnected;
  }
  switch (fs) {
    case FrameStatus::kTimeout:
      check_board_timeout();  // a camera that delivers nothing shows no board either
      return StepStatus::kTimeout;
    case FrameStatus::kEndOfStream: return StepStatus::kEndOfStream;
    case FrameStatus::kDisconnected:
      if (!disconnected_) {
        disconnected_ = true;
        emit({SessionEvent::Kind::kCameraDisconnected, std::nullopt,
              "camera '" + camera_->info().uri + "' disconnected; keyframes kept"});
      }
      return StepStatus::kDisconnected;
    case FrameStatus::kOk: break;
  }
  if (disconnected_) {
    disconnected_ = false;
    board_clock_ = std::chrono::steady_clock::now();  // the time away does not count
    emit({SessionEvent::Kind::kCameraReconnected, std::nullopt, "camera '" + camera_->info().uri + "' is back"});
  }
  process(frame.image, frame.hold);
  return StepStatus::kFrame;
}

// ---- the journal ----

namespace {

bool file_exists(const std::string& path) {
  struct stat st {};
  return ::lstat(path.c_str(), &st) == 0;
}

JournalHeader header_for(const DeviceInfo& d, const std::string& config) {
  JournalHeader h;
  h.camera_uri = d.uri;
  h.camera_id = d.id;
  h.camera_vendor = d.vendor;
  h.camera_model = d.model;
  h.camera_serial = d.serial;
  h.config = config;
  h.posecal_version = POSECAL_VERSION_STRING;
  return h;
}

// Why the journal cannot be resumed by this session ("" if it can).
std::string mismatch(const JournalContents& j, const DeviceInfo& d, const std::string& config) {
  if (j.header.camera_id != d.id || j.header.camera_serial != d.serial) {
    return "it was recorded with camera '" + j.header.camera_id + "' (serial '" + j.header.camera_serial +
           "'), this session's camera is '" + d.id + "' (serial '" + d.serial + "')";
  }
  if (j.header.config != config) {
    return "it was recorded with another session config (" + j.header.config + ", now " + config + ")";
  }
  return "";
}

}  // namespace

void CalibrationSession::open_journal(const std::string& path, const std::string& config, bool images,
                                      bool resume) {
  if (engine_ || started_) throw Error(ErrorCode::kState, "session: the journal is opened before the first frame");
  journal_images_ = images;
  journal_status_ = JournalStatus{};
  journal_status_.path = path;
  const DeviceInfo& camera = camera_->info();
  if (file_exists(path) && !resume) {
    const std::string old = path + "." + utc_now_iso8601() + ".old";
    if (::rename(path.c_str(), old.c_str()) != 0) {
      throw Error(ErrorCode::kIo, "cannot set journal '" + path + "' aside as '" + old + "'");
    }
    journal_status_.note = "the previous journal was kept as '" + old + "'";
  }
  if (file_exists(path)) {
    JournalContents j = read_journal(path);
    if (j.has_header) {
      const std::string why = mismatch(j, camera, config);
      if (!why.empty()) {
        throw Error(ErrorCode::kInvalidArgument, "journal '" + path + "' cannot be resumed: " + why +
                                                     "; set \"resume\": false to start afresh (the old journal is kept)");
      }
      journal_ = JournalWriter::resume(path, j.valid_bytes);
      journal_status_.resumed_keyframes = static_cast<int>(j.keyframes.size());
      journal_status_.note = j.damage;
      resumed_ = std::move(j);
      return;
    }
    journal_status_.note = "the journal's header was cut (" + j.damage + "): started afresh";
  }
  journal_ = JournalWriter::create(path, header_for(camera, config));
}

void CalibrationSession::set_keyframe_observer(KeyframeObserver observer) {
  if (engine_) throw Error(ErrorCode::kState, "session: a keyframe observer is set before the first frame");
  observer_ = std::move(observer);
}

void CalibrationSession::restore_from_journal(cv::Size size) {
  if (!journal_) return;
  if (resumed_.image_size.width > 0 && resumed_.image_size != size) {
    throw Error(ErrorCode::kInvalidArgument,
                "journal '" + journal_->path() + "' was recorded at " + std::to_string(resumed_.image_size.width) +
                    "x" + std::to_string(resumed_.image_size.height) + ", the camera delivers " +
                    std::to_string(size.width) + "x" + std::to_string(size.height));
  }
  try {
    if (resumed_.image_size.width == 0) journal_->append_engine(size, locked_);
  } catch (const Error& e) {
    journal_failed(e);
  }
  if (!resumed_.keyframes.empty()) journal_status_.identical = engine_->restore(resumed_.keyframes);
  if (observer_.on_keyframe) {
    for (size_t i = 0; i < resumed_.keyframes.size(); ++i)
      observer_.on_keyframe(static_cast<int>(i) + 1, resumed_.keyframes[i], cv::Mat());
  }
  resumed_ = JournalContents{};
}

void CalibrationSession::journal_frame(EngineState state_before, int keyframes_before, const cv::Mat& image) {
  if (!journal_) return;
  try {
    const int n = engine_->keyframes();
    if (n > keyframes_before) {
      journal_->append_keyframe(n, engine_->keyframe_record(n - 1, state_before),
                                journal_images_ ? image : cv::Mat());
    }
    if (finished()) journal_->append_end(engine_state_name(engine_->state()));
  } catch (const Error& e) {
    journal_failed(e);
  }
}

void CalibrationSession::journal_failed(const Error& e) {
  journal_.reset();
  journal_status_.note = std::string("the journal stopped: ") + e.what();
  emit({SessionEvent::Kind::kCameraError, std::nullopt, journal_status_.note});
}

}  // namespace posecal
