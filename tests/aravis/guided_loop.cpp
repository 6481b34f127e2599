#include "guided_loop.hpp"

#include <chrono>
#include <sstream>

namespace posecal::testing {

namespace {
constexpr size_t kRecentSteps = 32;
constexpr size_t kRememberedIds = 4096;
using Clock = std::chrono::steady_clock;
}  // namespace

SimCameraOptions GuidedSceneOptions::as_sim() const {
  SimCameraOptions o;
  o.truth = truth;
  o.board = board;
  o.render = render;
  o.op = op;
  o.seed = seed;
  return o;
}

GuidedScene::GuidedScene(const GuidedSceneOptions& options, Encoder encode)
    : options_(options),
      encode_(std::move(encode)),
      target_(options.board),
      renderer_(options.truth, target_, options.render),
      // The operator's stream is seeded as SimCameraImpl seeds it, so that a run reproduces
      // sim://?seed=N with the same options.
      operator_(options.truth, target_, options.op, options.seed * 0x9e3779b97f4a7c15ull + 17) {}

Payload GuidedScene::frame(uint64_t frame_id) {
  {
    std::unique_lock<std::mutex> lock(mutex_);
    if (preparing_) {
      // Rendering ahead: hand out the prepared step, or repeat the last one if it is late (the
      // very first one is waited for, so that every frame shows a step).
      if (recent_.empty()) {
        prepared_cv_.wait_for(lock, std::chrono::seconds(2),
                              [&] { return prepared_.has_value() || stop_preparing_; });
      }
      const bool fresh = prepared_.has_value();
      if (fresh) {
        publish_locked(std::move(*prepared_));
        prepared_.reset();
        prepared_cv_.notify_all();
      }
      return recent_.empty() ? nullptr : record_locked(frame_id, fresh);
    }
  }
  std::lock_guard<std::mutex> render_lock(render_mutex_);
  GuidanceInfo guidance;
  bool advance = false;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    // Lockstep: only once the engine has processed the last step (true for the first frame).
    advance = !options_.lockstep || guided_step_ == current_step_;
    if (advance) guidance = guidance_;
  }
  if (advance) {
    // One operator step, as SimCameraImpl::next_frame takes it: the pose for the guidance of
    // the previous frame, then the robot's signal for this pose.
    const Pose pose = operator_.next_pose(guidance);
    Step s;
    s.pose_reached = operator_.take_pose_reached();
    s.payload = std::make_shared<const std::vector<uint8_t>>(encode_(renderer_.render(pose)));
    std::lock_guard<std::mutex> lock(mutex_);
    publish_locked(std::move(s));
  }
  std::lock_guard<std::mutex> lock(mutex_);
  return record_locked(frame_id, advance);
}

void GuidedScene::publish_locked(Step s) {
  s.index = ++current_step_;
  recent_.push_back(std::move(s));
  if (recent_.size() > kRecentSteps) recent_.pop_front();
  ++stats_.steps;
}

Payload GuidedScene::record_locked(uint64_t frame_id, bool fresh) {
  ++stats_.frames;
  if (!fresh) ++stats_.repeats;
  if (step_of_id_.count(frame_id) == 0) {
    id_order_.push_back(frame_id);
    if (id_order_.size() > kRememberedIds) {
      step_of_id_.erase(id_order_.front());
      id_order_.pop_front();
    }
  }
  step_of_id_[frame_id] = current_step_;
  return recent_.back().payload;
}

bool GuidedScene::prepare_next() {
  GuidanceInfo guidance;
  {
    std::unique_lock<std::mutex> lock(mutex_);
    if (options_.lockstep) return false;  // lockstep renders on demand only
    preparing_ = true;
    prepared_cv_.wait(lock, [&] { return stop_preparing_ || !prepared_.has_value(); });
    if (stop_preparing_) return false;
    guidance = guidance_;
  }
  Step s;
  {
    std::lock_guard<std::mutex> render_lock(render_mutex_);
    const Pose pose = operator_.next_pose(guidance);
    s.pose_reached = operator_.take_pose_reached();
    s.payload = std::make_shared<const std::vector<uint8_t>>(encode_(renderer_.render(pose)));
  }
  std::lock_guard<std::mutex> lock(mutex_);
  prepared_ = std::move(s);
  prepared_cv_.notify_all();
  return !stop_preparing_;
}

void GuidedScene::stop_preparing() {
  std::lock_guard<std::mutex> lock(mutex_);
  stop_preparing_ = true;
  prepared_cv_.notify_all();
}

void GuidedScene::guide(uint64_t step, const GuidanceInfo& guidance) {
  std::lock_guard<std::mutex> lock(mutex_);
  guidance_ = guidance;
  guided_step_ = step;
}

std::optional<uint64_t> GuidedScene::step_of(uint64_t frame_id) const {
  std::lock_guard<std::mutex> lock(mutex_);
  auto it = step_of_id_.find(frame_id);
  if (it == step_of_id_.end()) return std::nullopt;
  return it->second;
}

const GuidedScene::Step* GuidedScene::find(uint64_t step) const {
  for (const Step& s : recent_) {
    if (s.index == step) return &s;
  }
  return nullptr;
}

Payload GuidedScene::payload(uint64_t step) const {
  std::lock_guard<std::mutex> lock(mutex_);
  const Step* s = find(step);
  return s ? s->payload : nullptr;
}

bool GuidedScene::pose_reached_at(uint64_t step) const {
  std::lock_guard<std::mutex> lock(mutex_);
  const Step* s = find(step);
  return s && s->pose_reached;
}

GuidedSceneStats GuidedScene::stats() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return stats_;
}

std::map<std::string, AttemptStats> GuidedScene::attempts() const {
  std::lock_guard<std::mutex> lock(render_mutex_);
  return operator_.attempts();
}

// ---------------------------------------------------------------------------------------------

GuidedCamera::GuidedCamera(std::unique_ptr<Camera> inner, std::shared_ptr<GuidedScene> scene,
                           Decoder decode)
    : Camera(inner->info()), inner_(std::move(inner)), scene_(std::move(scene)), decode_(std::move(decode)) {
  follow_state_of(inner_.get());
  inner_->set_event_callback([this](const CameraEvent& e) { emit_event(e); });
}

FrameStatus GuidedCamera::do_next_frame(int timeout_ms, Frame* frame) {
  const auto deadline = Clock::now() + std::chrono::milliseconds(timeout_ms);
  for (;;) {
    const auto left =
        std::chrono::duration_cast<std::chrono::milliseconds>(deadline - Clock::now());
    Frame f;
    const FrameStatus st =
        inner_->next_frame(static_cast<int>(std::max<int64_t>(0, left.count())), &f);
    if (st != FrameStatus::kOk) return st;
    const std::optional<uint64_t> step = scene_->step_of(f.frame_id);
    std::lock_guard<std::mutex> lock(mutex_);
    if (!step) {
      ++stats_.unknown;
      if (first_problem_.empty()) {
        first_problem_ = "frame id " + std::to_string(f.frame_id) + " was never sent by the scene";
      }
    } else if (*step <= step_) {
      ++stats_.repeats_skipped;
    } else {
      if (*step != step_ + 1) stats_.step_gaps += *step - step_ - 1;
      // Bit for bit against what the camera sent for this step.
      const Payload sent = scene_->payload(*step);
      const cv::Mat expected = sent ? decode_(*sent) : cv::Mat();
      const bool exact = !expected.empty() && !f.image.empty() &&
                         expected.size() == f.image.size() && expected.type() == f.image.type() &&
                         cv::norm(expected, f.image, cv::NORM_INF) == 0;
      if (exact) {
        ++stats_.exact;
      } else {
        ++stats_.corrupt;
        if (first_problem_.empty()) {
          std::ostringstream why;
          why << "step " << *step << " (frame id " << f.frame_id << ") differs from what was sent";
          if (!expected.empty() && !f.image.empty() && expected.size() == f.image.size() &&
              expected.type() == f.image.type()) {
            why << ": max difference " << cv::norm(expected, f.image, cv::NORM_INF) << ", "
                << cv::countNonZero(expected != f.image) << " pixels";
          }
          // Diagnosis: is it another step's image (a bookkeeping error) or a damaged one?
          for (uint64_t other = *step > 8 ? *step - 8 : 1; other <= *step + 8; ++other) {
            const Payload p = other == *step ? nullptr : scene_->payload(other);
            if (!p) continue;
            const cv::Mat e = decode_(*p);
            if (e.size() == f.image.size() && e.type() == f.image.type() &&
                cv::norm(e, f.image, cv::NORM_INF) == 0) {
              why << "; it is step " << other << "'s image";
            }
          }
          first_problem_ = why.str();
        }
      }
      ++stats_.delivered;
      step_ = *step;
      reached_taken_ = false;
      *frame = std::move(f);
      return FrameStatus::kOk;
    }
    if (Clock::now() >= deadline) return FrameStatus::kTimeout;
  }
}

void GuidedCamera::guide(const GuidanceInfo& guidance) {
  inner_->guide(guidance);
  uint64_t step = 0;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    step = step_;
  }
  scene_->guide(step, guidance);
}

bool GuidedCamera::take_pose_reached() {
  std::lock_guard<std::mutex> lock(mutex_);
  if (reached_taken_ || step_ == 0) return false;
  reached_taken_ = true;
  return scene_->pose_reached_at(step_);
}

GuidedCameraStats GuidedCamera::guided_stats() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return stats_;
}

uint64_t GuidedCamera::last_step() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return step_;
}

std::string GuidedCamera::first_problem() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return first_problem_;
}

}  // namespace posecal::testing
