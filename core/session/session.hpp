// A calibration session: one camera feeding one engine. The loop every host runs:
//   step(timeout) = next frame from the camera -> engine -> guidance back to the camera.
// Survives camera disconnects: the engine and its keyframes are kept, and the session goes on
// when the camera delivers frames again. Ends as failed when no board has been seen for
// EngineOptions::board_timeout_s of wall time (the failure reason says so).
#pragma once

#include <chrono>
#include <functional>
#include <map>
#include <memory>
#include <optional>
#include <string>

#include "device/camera.hpp"
#include "select/engine.hpp"
#include "session/journal.hpp"

namespace posecal {

enum class StepStatus { kFrame, kTimeout, kDisconnected, kEndOfStream, kFinished };
const char* step_status_name(StepStatus s);

struct SessionEvent {
  enum class Kind { kEngine, kCameraDisconnected, kCameraReconnected, kCameraError } kind;
  std::optional<EngineEvent> engine;  // for kEngine
  std::string message;
};

class CalibrationSession {
 public:
  // The engine is created at the first frame, when the image size is known.
  CalibrationSession(std::unique_ptr<Camera> camera, const EngineOptions& options,
                     bool lock_settings = true);
  ~CalibrationSession();

  // Takes at most one frame (waiting at most timeout_ms) and advances the engine.
  StepStatus step(int timeout_ms);
  // Processes a frame the host supplies (external sessions); synchronous.
  FrameReport feed(const cv::Mat& image);

  bool finished() const;  // converged or failed (no_frame_failure() included)
  bool has_engine() const { return engine_ != nullptr; }
  // Why a session whose camera never delivered a frame ended (board_timeout_s after the camera
  // was started; there is no engine to fail then); "" otherwise.
  const std::string& no_frame_failure() const { return no_frame_failure_; }
  CalibrationEngine& engine();  // Error(kState) before the first frame
  const CalibrationEngine* engine_ptr() const { return engine_.get(); }
  Camera& camera() { return *camera_; }
  const EngineOptions& options() const { return options_; }
  const std::map<std::string, std::string>& locked_settings() const { return locked_; }
  bool disconnected() const { return disconnected_; }
  uint64_t frames_processed() const { return frames_; }
  const cv::Mat& last_frame() const { return last_frame_; }
  double wall_ms() const;

  void set_event_callback(std::function<void(const SessionEvent&)> cb);

  // Keeps a journal at `path` (session/journal.hpp), before the first frame. `config` is the
  // session config as canonical JSON without the journal's own keys. An existing journal of
  // the same camera (id and serial) and config is resumed: its keyframes are restored into the
  // engine at the first frame and new ones appended. With `resume` false an existing journal is
  // renamed to PATH.<UTC time>.old and a new one started. Throws Error(kInvalidArgument) naming
  // the journal and what differs for another camera's or config's journal, Error(kIo) if it
  // cannot be read or written.
  void open_journal(const std::string& path, const std::string& config, bool images, bool resume);
  struct JournalStatus {
    std::string path;       // "" without a journal
    int resumed_keyframes = 0;
    std::string note;       // what was dropped from a damaged journal, what was renamed, or why
                            // the journal stopped (a write error); "" if nothing
    std::optional<bool> identical;  // after a resume: the recomputed calibration equals the last
                                    // journalled one bit for bit
  };
  const JournalStatus& journal_status() const { return journal_status_; }

  // What the journal receives, for a second keeper (the calibration record, core/records): the
  // image size and locked settings when the engine is made, then every keyframe the engine keeps
  // (1-based index, the record, the frame; the keyframes a journal restores come first, without
  // frames). Set before the first frame (else Error(kState)). The callbacks must not throw: a
  // keeper's failure is the keeper's to report.
  struct KeyframeObserver {
    std::function<void(cv::Size, const std::map<std::string, std::string>&)> on_engine;
    std::function<void(int, const KeyframeRecord&, const cv::Mat&)> on_keyframe;
  };
  void set_keyframe_observer(KeyframeObserver observer);

 private:
  void ensure_engine(cv::Size size);
  FrameReport process(const cv::Mat& image, std::shared_ptr<void> hold);
  void emit(const SessionEvent& e);
  void restore_from_journal(cv::Size size);
  void journal_frame(EngineState state_before, int keyframes_before, const cv::Mat& image);
  // A journal write that failed: reported once, and the journal stops (the calibration goes on).
  void journal_failed(const Error& e);
  // Fails the engine when no board has been seen for board_timeout_s (after a frame or a step
  // without one).
  void check_board_timeout();

  std::unique_ptr<Camera> camera_;
  EngineOptions options_;
  std::unique_ptr<CalibrationEngine> engine_;
  std::function<void(const SessionEvent&)> callback_;
  std::map<std::string, std::string> locked_;
  bool lock_settings_;
  bool started_ = false;
  bool disconnected_ = false;
  uint64_t frames_ = 0;
  cv::Mat last_frame_;
  std::shared_ptr<void> last_hold_;  // keeps a zero-copy backend buffer alive with last_frame_
  std::chrono::steady_clock::time_point t0_;
  std::unique_ptr<JournalWriter> journal_;
  bool journal_images_ = false;
  JournalContents resumed_;  // the journal read at open_journal, until the first frame
  JournalStatus journal_status_;
  KeyframeObserver observer_;
  // Since when no board has been seen: the camera's start (until the first frame), the first
  // frame, the last frame showing the board, the camera's return after a disconnect.
  std::chrono::steady_clock::time_point board_clock_;
  std::string no_frame_failure_;
};

}  // namespace posecal
