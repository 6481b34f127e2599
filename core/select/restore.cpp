// The engine and the session journal: what is kept of a keyframe, and the engine rebuilt from
// those records after a kill (core/session/journal.hpp).
#include <string>

#include "common/error.hpp"
#include "select/engine_internal.hpp"

namespace posecal {

namespace {

// num_params < 0: any model of the lens table (EngineOptions::auto_lens_model).
void check_record(const KeyframeRecord& r, size_t index, int num_params, bool with_prior) {
  const std::string where = "journal keyframe " + std::to_string(index + 1) + ": ";
  auto bad = [&](const std::string& why) { throw Error(ErrorCode::kInvalidArgument, where + why); };
  if (num_params < 0) {
    num_params = static_cast<int>(r.estimate_after.size());
    bool known = false;
    for (const LensModel m : lens_models()) known = known || num_intrinsics(m) == num_params;
    if (!known)
      bad("it has " + std::to_string(num_params) + " intrinsics, no lens model has as many");
  }
  if (static_cast<int>(r.estimate_after.size()) != num_params ||
      static_cast<int>(r.converged_after.size()) != num_params) {
    bad("it has " + std::to_string(r.estimate_after.size()) +
        " intrinsics, the session's lens model " + std::to_string(num_params));
  }
  const Observation& o = r.observation;
  if (o.ids.size() != o.image_points.size() || o.ids.size() != o.board_points.size() ||
      o.ids.size() < 4) {
    bad("its corners are inconsistent or fewer than 4");
  }
  if (r.target_param < -1 || r.target_param >= num_params) bad("target parameter out of range");
  const bool captured_in = r.state_before == EngineState::kInitialPose1 ||
                           r.state_before == EngineState::kInitialPose2 ||
                           r.state_before == EngineState::kRefining;
  const bool after = r.state_after != EngineState::kWaitingForBoard &&
                     r.state_after != EngineState::kBootstrapping &&
                     r.state_after != EngineState::kInitialPose1;
  if (!captured_in || !after) bad("a keyframe cannot be captured in these states");
  if (index == 0 && !with_prior && r.state_before != EngineState::kInitialPose1)
    bad("the first keyframe is the first initial pose");
  if (index == 0 && with_prior && r.state_before != EngineState::kRefining)
    bad("a session with a prior has no initial poses");
}

}  // namespace

KeyframeRecord CalibrationEngine::keyframe_record(int i, EngineState state_before) const {
  const Impl& s = *impl_;
  if (i < 0 || i >= static_cast<int>(s.keyframes.size())) {
    throw Error(ErrorCode::kInvalidArgument, "engine: no keyframe " + std::to_string(i));
  }
  KeyframeRecord r;
  r.observation = s.keyframes[static_cast<size_t>(i)];
  r.state_before = state_before;
  r.target_param = s.keyframe_target[static_cast<size_t>(i)];
  r.state_after = s.state;
  r.estimate_after = s.estimate.params();
  r.converged_after = s.param_converged;
  r.failure = s.failure;
  return r;
}

bool CalibrationEngine::restore(const std::vector<KeyframeRecord>& records) {
  Impl& s = *impl_;
  if (s.frame_index != 0 || !s.keyframes.empty()) {
    throw Error(ErrorCode::kState, "engine: keyframes can be restored only before the first frame");
  }
  const int n = s.opt.auto_lens_model ? -1 : s.estimate.num_params();
  for (size_t k = 0; k < records.size(); ++k) check_record(records[k], k, n, s.prior.has_value());
  if (records.empty()) return true;
  // No events while rebuilding: the host saw them when the keyframes were captured.
  auto callback = std::move(s.callback);
  s.callback = nullptr;
  struct Restore {
    Impl& s;
    std::function<void(const EngineEvent&)>& cb;
    ~Restore() { s.callback = std::move(cb); }
  } restore_callback{s, callback};
  for (size_t k = 0; k < records.size(); ++k) {
    const KeyframeRecord& r = records[k];
    s.keyframes.push_back(r.observation);
    s.keyframe_target.push_back(r.state_before == EngineState::kRefining ? r.target_param : -1);
    if (k == 0 &&
        !s.prior) {  // the first keyframe is not calibrated alone: its estimate is the bootstrap's
      // (An automatic lens model's bootstrap may have chosen the fisheye: the count says which.)
      if (s.opt.auto_lens_model) {
        for (const LensModel m : lens_models()) {
          if (num_intrinsics(m) == static_cast<int>(r.estimate_after.size()) &&
              m != s.opt.calibration.lens_model)
            s.move_to_lens_model(m);
        }
      }
      s.estimate =
          CameraModel(s.size.width, s.size.height, s.opt.calibration.lens_model, r.estimate_after);
      s.have_bootstrap = true;
      continue;
    }
    s.state = r.state_before;
    if (!s.recalibrate()) {
      throw Error(ErrorCode::kInvalidArgument,
                  "journal keyframe " + std::to_string(k + 1) + ": the calibration rejects it");
    }
  }
  const KeyframeRecord& last = records.back();
  const bool identical = s.estimate.params() == last.estimate_after;
  // (An automatic lens model the replay did not reach again keeps the replay's own state.)
  if (last.converged_after.size() == s.param_converged.size())
    s.param_converged = last.converged_after;
  s.state = last.state_after;
  s.failure = last.failure;
  switch (last.state_after) {
    case EngineState::kInitialPose2:
      s.initial_retries = 0;
      s.set_target(s.posegen.initial_pose(1, s.estimate), -1);
      break;
    case EngineState::kRefining:
      s.after_calibration();
      break;
    default:  // converged or failed: finished as before
      s.target.reset();
      s.target_param = -1;
      break;
  }
  return identical;
}

}  // namespace posecal
