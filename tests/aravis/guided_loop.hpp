// Test support: the sim:// closed loop (core/sim/sim_camera.cpp, SimCameraImpl) rebuilt around a
// real camera backend. A SimulatedOperator guided by the engine moves the board, a
// SyntheticCamera renders it, and a camera simulator that runs on its own clock (Aravis' GigE
// Vision simulator thread, the UVC emulator's sensor) sends the rendering through the real
// protocol; the session receives it through the backend.
//
//   camera's thread                            session's thread
//   GuidedScene::frame(frame_id) ─ payload ─► protocol ─► backend ─► GuidedCamera::next_frame
//        ▲  one operator step per new frame                                   │ engine
//        └──────────── GuidedScene::guide(step, guidance) ◄── GuidedCamera::guide ◄┘
//
// Lockstep: the camera sends frames at its own rate, but the operator takes step k+1 only after
// the engine has processed step k and handed back its guidance, exactly as sim:// does (there
// next_frame() renders with the guidance of the previous frame). Until then the camera repeats
// step k's image under new frame ids; GuidedCamera passes each step to the session once and
// skips the repeats, so no frame is counted twice and none is skipped. With the same options
// the session therefore sees the same sequence of poses, noise and guidance as sim://, frame for
// frame; every frame is checked bit for bit against what the simulator sent.
#pragma once

#include <condition_variable>
#include <cstdint>
#include <deque>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <vector>

#include "device/camera.hpp"
#include "sim/sim_camera.hpp"
#include "sim/synthetic.hpp"

namespace posecal::testing {

using Payload = std::shared_ptr<const std::vector<uint8_t>>;

struct GuidedSceneOptions {
  CameraModel truth;  // ground truth; the camera must deliver frames of this size
  BoardSpec board;
  RenderOptions render;  // noise, blur, seed
  OperatorOptions op;
  uint64_t seed = 1;  // as SimCameraOptions::seed (the operator's random stream)
  // true: lockstep (top of this file), as sim://. false: free-running, one operator step per frame
  // the camera sends, with the latest guidance the engine has handed back, like a person who moves
  // on whether or not the engine has looked; frames the engine does not get to are lost to it
  // (GuidedCameraStats::step_gaps). The many-camera benchmark measures with this.
  bool lockstep = true;
  // The sim:// camera of these options: the same truth, renderer and operator.
  SimCameraOptions as_sim() const;
};

struct GuidedSceneStats {
  uint64_t steps = 0;    // operator steps taken (= new images rendered)
  uint64_t frames = 0;   // frames the camera asked for (steps + repeats)
  uint64_t repeats = 0;  // frames that repeated a step the engine had not processed yet
};

// The producer side, shared by the camera's thread and the session's thread (thread-safe).
class GuidedScene {
 public:
  // `encode` turns a rendered 8-bit grey image into the camera's payload (Mono8 bytes, a JPEG,
  // YUYV...), exactly as the simulator sends it.
  using Encoder = std::function<std::vector<uint8_t>(const cv::Mat& grey)>;
  GuidedScene(const GuidedSceneOptions& options, Encoder encode);

  // Camera's thread: the payload of the frame `frame_id` the camera is about to send. Takes an
  // operator step and renders it if the engine has processed the previous step, else repeats
  // the previous step. Records which step the frame shows.
  Payload frame(uint64_t frame_id);
  // Session's thread: the engine processed `step` and wants `guidance` next.
  void guide(uint64_t step, const GuidanceInfo& guidance);

  // Free-running scenes may render ahead, as a sensor has its image ready at the frame's tick:
  // a thread of the caller's calls prepare_next() in a loop, which takes the next operator step
  // with the latest guidance as soon as the previously prepared one has been sent. frame() then
  // only hands steps out; a frame whose step is not ready yet repeats the last one (counted in
  // repeats). Returns false once stop_preparing() was called.
  bool prepare_next();
  void stop_preparing();

  // The step a frame id was sent for (nullopt if never sent). Frame ids may wrap or restart
  // (a restarted simulator): the latest frame sent under an id wins.
  std::optional<uint64_t> step_of(uint64_t frame_id) const;
  // The payload of a recent step (nullptr once it is older than the last 32 steps).
  Payload payload(uint64_t step) const;
  // Robot: the operator signalled "pose reached" when it took `step`.
  bool pose_reached_at(uint64_t step) const;

  const GuidedSceneOptions& options() const { return options_; }
  const CameraModel& truth() const { return options_.truth; }
  GuidedSceneStats stats() const;
  // Per target kind: attempts and captures of the operator (as SimulatedOperator::attempts).
  std::map<std::string, AttemptStats> attempts() const;

 private:
  struct Step {
    uint64_t index = 0;
    Payload payload;
    bool pose_reached = false;
  };
  const Step* find(uint64_t step) const;
  // With mutex_ held: a new step becomes the current one; a frame id shows the current step.
  void publish_locked(Step step);
  Payload record_locked(uint64_t frame_id, bool fresh);

  GuidedSceneOptions options_;
  Encoder encode_;
  Board target_;
  // Touched only by the camera's thread (under render_mutex_, so that a scene may be fed by
  // more than one thread in turn, e.g. a restarted simulator).
  mutable std::mutex render_mutex_;
  SyntheticCamera renderer_;
  SimulatedOperator operator_;
  // Shared state.
  mutable std::mutex mutex_;
  GuidanceInfo guidance_;
  uint64_t guided_step_ = 0;   // the last step the engine processed
  uint64_t current_step_ = 0;  // the last step rendered
  std::deque<Step> recent_;    // the last steps, newest at the back
  std::map<uint64_t, uint64_t> step_of_id_;
  std::deque<uint64_t> id_order_;  // bounds step_of_id_
  GuidedSceneStats stats_;
  // Rendering ahead (free-running only).
  std::condition_variable prepared_cv_;
  std::optional<Step> prepared_;
  bool preparing_ = false;
  bool stop_preparing_ = false;
};

struct GuidedCameraStats {
  uint64_t delivered = 0;        // steps passed to the session
  uint64_t exact = 0;            // ... bit-identical to what the camera sent
  uint64_t corrupt = 0;          // ... not identical (must stay 0)
  uint64_t step_gaps = 0;        // steps never delivered (lockstep: must stay 0)
  uint64_t repeats_skipped = 0;  // frames of a step already delivered
  uint64_t unknown = 0;          // frames the scene never sent (must stay 0)
};

// The consumer side: wraps the backend's camera for the session. Everything but next_frame,
// guide and take_pose_reached goes straight to the backend's camera.
class GuidedCamera final : public Camera {
 public:
  // `decode` turns a payload into what the backend must deliver to the engine (the reference
  // for the bit-exact check), e.g. convert_to_engine of the payload.
  using Decoder = std::function<cv::Mat(const std::vector<uint8_t>& payload)>;
  GuidedCamera(std::unique_ptr<Camera> inner, std::shared_ptr<GuidedScene> scene, Decoder decode);

  void guide(const GuidanceInfo& guidance) override;
  bool take_pose_reached() override;

  Camera& inner() { return *inner_; }
  GuidedCameraStats guided_stats() const;
  uint64_t last_step() const;
  // Description of the first corrupt or unknown frame ("" if none).
  std::string first_problem() const;

 protected:
  CameraConfig do_current_config() override { return inner_->current_config(); }
  CameraConfig do_validate(const CameraConfig& c) override { return inner_->validate(c); }
  void do_configure(const CameraConfig& c) override { inner_->configure(c); }
  std::vector<FeatureInfo> do_features() override { return inner_->features(); }
  std::string do_get_feature(const std::string& n) override { return inner_->get_feature(n); }
  void do_set_feature(const std::string& n, const std::string& v) override { inner_->set_feature(n, v); }
  std::map<std::string, std::string> do_lock_for_calibration() override { return inner_->lock_for_calibration(); }
  void do_start() override { inner_->start(); }
  void do_stop() override { inner_->stop(); }
  CameraStats do_stats() const override { return inner_->stats(); }
  // The next step not yet delivered, checked bit for bit; repeats are skipped. Never waits
  // longer than timeout_ms; kTimeout, kDisconnected and kEndOfStream pass through.
  FrameStatus do_next_frame(int timeout_ms, Frame* frame) override;
 private:
  std::unique_ptr<Camera> inner_;
  std::shared_ptr<GuidedScene> scene_;
  Decoder decode_;
  mutable std::mutex mutex_;  // guided_stats() may be read from another thread
  uint64_t step_ = 0;         // last step delivered
  bool reached_taken_ = false;
  GuidedCameraStats stats_;
  std::string first_problem_;
};

}  // namespace posecal::testing
