// The engine's state machine (engine.hpp draws it): each frame is detected, checked for
// stillness and the target, captured as a keyframe when it is there, and every keyframe is
// recalibrated with. The rest of the engine: engine_internal.hpp.
#include <algorithm>
#include <cmath>
#include <limits>
#include <map>
#include <opencv2/imgproc.hpp>
#include <utility>

#include "calib/information.hpp"
#include "calib/pose_estimation.hpp"
#include "common/error.hpp"
#include "common/statistics.hpp"
#include "select/engine_internal.hpp"

namespace posecal {

const char* engine_state_name(EngineState s) {
  switch (s) {
    case EngineState::kWaitingForBoard: return "waiting_for_board";
    case EngineState::kBootstrapping: return "bootstrapping";
    case EngineState::kInitialPose1: return "initial_pose_1";
    case EngineState::kInitialPose2: return "initial_pose_2";
    case EngineState::kRefining: return "refining";
    case EngineState::kConverged: return "converged";
    case EngineState::kFailed: return "failed";
  }
  return "unknown";
}

bool engine_state_from_name(const std::string& name, EngineState* s) {
  for (EngineState e : {EngineState::kWaitingForBoard, EngineState::kBootstrapping, EngineState::kInitialPose1,
                        EngineState::kInitialPose2, EngineState::kRefining, EngineState::kConverged,
                        EngineState::kFailed}) {
    if (name == engine_state_name(e)) {
      *s = e;
      return true;
    }
  }
  return false;
}

const char* engine_event_name(EngineEvent::Kind k) {
  switch (k) {
    case EngineEvent::Kind::kStateChanged: return "state_changed";
    case EngineEvent::Kind::kCaptured: return "captured";
    case EngineEvent::Kind::kKeyframeRejected: return "keyframe_rejected";
    case EngineEvent::Kind::kCalibrated: return "calibrated";
    case EngineEvent::Kind::kParameterConverged: return "parameter_converged";
    case EngineEvent::Kind::kParameterReopened:
      return "parameter_reopened";
    case EngineEvent::Kind::kTargetChanged: return "target_changed";
    case EngineEvent::Kind::kTargetSkipped: return "target_skipped";
    case EngineEvent::Kind::kError: return "error";
  }
  return "unknown";
}

bool EngineOptions::is_valid(std::string* error) const {
  auto fail = [&](const std::string& w) {
    if (error) *error = w;
    return false;
  };
  try {
    board.validate();
  } catch (const Error& e) {
    return fail(std::string("target: ") + e.what());
  }
  // The ranges of the session keys (core/session/session_keys.def), the one declaration of them.
#define POSECAL_RANGE_Number(key, member, lo, hi) \
  if (!(member >= lo && member <= hi)) return fail(#key " must be in [" #lo ", " #hi "]");
#define POSECAL_RANGE_Integer(key, member, lo, hi) POSECAL_RANGE_Number(key, member, lo, hi)
#define POSECAL_RANGE_OptionalNumber(key, member, lo, hi) \
  if (member && !(*member >= lo && *member <= hi)) return fail(#key " must be in [" #lo ", " #hi "]");
#define POSECAL_RANGE_Bool(key, member, lo, hi)
#define POSECAL_RANGE_Choice(key, member, lo, hi)
#define POSECAL_RANGE_Text(key, member, lo, hi)
#define POSECAL_RANGE_TextList(key, member, lo, hi)
#define POSECAL_RANGE_engine(kind, key, member, lo, hi) POSECAL_RANGE_##kind(key, member, lo, hi)
#define POSECAL_RANGE_session(kind, key, member, lo, hi)
#define POSECAL_KEY(scope, key, kind, member, lo, hi, choices, def, alias, doc) \
  POSECAL_RANGE_##scope(kind, key, member, lo, hi)
#include "session/session_keys.def"
#undef POSECAL_KEY
  if (!measured_convergence && !prospective_convergence)
    return fail("measured_convergence and prospective_convergence cannot both be off");
  if (method != Method::kPosecal && method != Method::kPaper && method != Method::kReferenceStd)
    return fail("unknown method");
  if (accuracy_px && method != Method::kPosecal)
    return fail(std::string("accuracy_px cannot be honoured by method \"") +
                (method == Method::kPaper ? "paper" : "reference-std") +
                "\", which stops on the ratio test; use method \"posecal\"");
  if (auto_lens_model && calibration.prior)
    return fail("lens_model auto cannot be used with a prior: the prior is of one lens model");
  if (bootstrap_min_corners < 0) return fail("bootstrap_min_corners must be >= 0");
  if (!(bootstrap_max_relative_std > 0 && bootstrap_max_relative_std <= 1)) {
    return fail("bootstrap_max_relative_std must be in (0, 1]");
  }
  if (!(bootstrap_max_pp_sensitivity > 0 && bootstrap_max_pp_sensitivity <= 10)) {
    return fail("bootstrap_max_pp_sensitivity must be in (0, 10]");
  }
  if (!(initial_focal_guess >= 0) || !std::isfinite(initial_focal_guess)) return fail("initial_focal_guess must be >= 0");
  std::string why;
  if (!posegen.is_valid(&why)) return fail("posegen: " + why);
  if (!calibration.is_valid(&why)) return fail("calibration: " + why);
  return true;
}

void EngineOptions::set_method(Method m) {
  const EngineOptions d;  // posecal's defaults
  method = m;
  pose_candidates = d.pose_candidates;
  prospective_convergence = d.prospective_convergence;
  measured_convergence = d.measured_convergence;
  convergence_measure = d.convergence_measure;
  view_candidates = d.view_candidates;
  view_must_serve_target = d.view_must_serve_target;
  candidate_score = d.candidate_score;
  posegen.pinhole_fill = d.posegen.pinhole_fill;
  ratio_stop_max_p90_px = d.ratio_stop_max_p90_px;
  if (m == Method::kPosecal) return;
  // The paper's rules: one generated pose per target, the measured ratio test only, the
  // reference implementation's board distance (about 0.53-0.6 of the view).
  pose_candidates = 1;
  prospective_convergence = false;
  measured_convergence = true;
  convergence_measure = m == Method::kReferenceStd ? ConvergenceMeasure::kStd : ConvergenceMeasure::kVariance;
  view_candidates = 0;
  view_must_serve_target = false;
  posegen.pinhole_fill = 0.6;
  ratio_stop_max_p90_px = 0;
}

CalibrationEngine::Impl::Impl(cv::Size s, const EngineOptions& o)
    : size(s), opt(o), board(o.board), posegen(board, s, o.posegen) {
  const double f = o.initial_focal_guess > 0 ? o.initial_focal_guess : std::max(s.width, s.height);
  estimate = CameraModel::pinhole(o.calibration.lens_model, s.width, s.height, f, f, (s.width - 1) * 0.5,
                                  (s.height - 1) * 0.5);
  if (o.calibration.prior) {
    prior = prior_result(s, o.calibration);
    prior_expected = posecal::expected_error(*prior);
    estimate = prior->model;
  }
  const int n = estimate.num_params();
  param_converged.assign(n, false);
  param_targeted.assign(n, 0);
}

void CalibrationEngine::Impl::emit(EngineEvent e) {
  e.keyframes = static_cast<int>(keyframes.size());
  if (callback) callback(e);
}

void CalibrationEngine::Impl::set_state(EngineState s, const std::string& message) {
  if (s == state) return;
  EngineEvent e{EngineEvent::Kind::kStateChanged};
  e.from = state;
  e.to = s;
  e.message = message;
  state = s;
  emit(e);
}

void CalibrationEngine::Impl::fail(const std::string& why) {
  failure = why;
  target.reset();
  set_state(EngineState::kFailed, why);
}

void CalibrationEngine::Impl::set_target(TargetPose t, int param) {
  target = std::move(t);
  target_param = param;
  ++target_serial;
  target_since_frame = frame_index;
  robot_reached = false;
  crowded_frames = 0;
  EngineEvent e{EngineEvent::Kind::kTargetChanged};
  e.parameter = param >= 0 ? estimate.param_names()[param] : "";
  e.message = target_kind_name(target->kind) + (target->note.empty() ? "" : ": " + target->note);
  emit(e);
}

// Points needed per keyframe so that constraints >= factor x unknowns (paper §4.3): for the
// two initial frames the unknowns are the intrinsics plus 6 per frame, spread over both
// frames; afterwards every frame only adds its own 6 pose parameters.
int CalibrationEngine::Impl::corners_required() const {
  const double n_intr = estimate.num_params();
  double pts;
  if (keyframes.size() < 2 && !prior) {
    pts = opt.constraint_factor * (n_intr + 2 * 6) / 2.0 / 2.0;
  } else {
    pts = opt.constraint_factor * 6 / 2.0;
  }
  return static_cast<int>(std::ceil(pts - 1e-9));
}

FrameReport CalibrationEngine::Impl::process(const cv::Mat& image) {
  if (image.empty() || image.depth() != CV_8U || (image.channels() != 1 && image.channels() != 3)) {
    throw Error(ErrorCode::kInvalidArgument, "engine: frames must be 8-bit grey or BGR");
  }
  if (image.size() != size) {
    throw Error(ErrorCode::kInvalidArgument, "engine: frame is " + std::to_string(image.cols) + "x" +
                                                 std::to_string(image.rows) + ", calibration is for " +
                                                 std::to_string(size.width) + "x" + std::to_string(size.height));
  }
  FrameReport r;
  r.frame_index = frame_index++;
  const Detection det = detect(image);
  r.corners = static_cast<int>(det.size());
  r.board_visible = det.size() >= 4;
  r.corners_required = corners_required();
  measure_stillness(det, &r);
  bootstrap_step(det, r);
  const std::optional<Pose> current = current_pose(det, &r);
  capture_step(image, det, &r);
  // A target choice is ahead: draw part of its view candidates now, spread over the frames in
  // which the board is moved to the current target.
  if (opt.view_candidates > 0 && scoring() && (state == EngineState::kInitialPose2 || state == EngineState::kRefining)) {
    grow_view_pool(kViewsPerFrame, kPoolFactor * opt.view_candidates);
  }
  r.state = state;
  r.keyframes = static_cast<int>(keyframes.size());
  r.target_parameter = (state == EngineState::kRefining && target_param >= 0) ? estimate.param_names()[target_param] : "";
  r.guidance = guidance_text(r, current);
  last = r;
  return r;
}

Detection CalibrationEngine::Impl::detect(const cv::Mat& image) {
  if (opt.track_board) return tracker.detect(board, image, opt.detector);
  return tracker.detect_whole(board, image, opt.detector);
}

// Stillness (paper §4.3): every corner of the previous frame re-detected, mean motion small.
void CalibrationEngine::Impl::measure_stillness(const Detection& det, FrameReport* r) {
  if (!previous.empty() && !det.empty()) {
    std::map<int, cv::Point2d> now;
    for (size_t i = 0; i < det.size(); ++i) now[det.ids[i]] = det.image_points[i];
    double sum = 0;
    bool all = true;
    for (size_t i = 0; i < previous.size(); ++i) {
      auto it = now.find(previous.ids[i]);
      if (it == now.end()) {
        all = false;
        break;
      }
      sum += cv::norm(it->second - previous.image_points[i]);
    }
    if (all) {
      r->motion_px = sum / static_cast<double>(previous.size());
      r->still = r->motion_px < opt.still_motion_px;
    }
  }
  previous = det;
}

// The board seen for the first time starts the bootstrap; until two keyframes exist, a better
// single-view fit replaces the estimate (paper §3.4).
void CalibrationEngine::Impl::bootstrap_step(const Detection& det, const FrameReport& r) {
  if (prior) {
    if (state == EngineState::kWaitingForBoard && r.board_visible) start_from_prior();
    return;
  }
  if (state == EngineState::kWaitingForBoard && r.board_visible) set_state(EngineState::kBootstrapping);
  if (state != EngineState::kBootstrapping && state != EngineState::kInitialPose1 &&
      state != EngineState::kInitialPose2) {
    return;
  }
  const double f_before = estimate.fx();
  // Robots: only still frames (not the ones taken while moving); the strong view at the
  // first target (tilted 45 degrees) then replaces a weaker start view.
  const bool may_bootstrap = !opt.robot || r.still;
  // A board held still shows the view already fitted: the fit (a few ms) would only repeat.
  const bool seen = r.still && bootstrap_view_fitted;
  bootstrap_view_fitted = keyframes.empty() && may_bootstrap && (seen || r.board_visible);
  if (keyframes.empty() && may_bootstrap && !seen && try_bootstrap(det)) {
    const bool first = state == EngineState::kBootstrapping;
    if (first) set_state(EngineState::kInitialPose1);
    // Regenerate the target only when the focal length moved noticeably, so the overlay
    // does not jitter with every slightly better bootstrap.
    if (first || !target || std::abs(estimate.fx() - f_before) > 0.02 * f_before) {
      set_target(posegen.initial_pose(0, estimate, initial_retries), -1);
    }
  }
}

// With a prior there is no bootstrap and no initial pose: the first target is chosen from what
// the prior says, as every later one is from the last calibration (docs/pose-selection.md, "The
// fleet prior").
void CalibrationEngine::Impl::start_from_prior() {
  set_state(EngineState::kRefining, "starting from the prior");
  if (opt.accuracy_px) {
    choose_accuracy_target();
  } else {
    choose_refinement_target();
  }
}

// The board's pose under the current estimate and its overlap with the target (paper §4.2).
std::optional<Pose> CalibrationEngine::Impl::current_pose(const Detection& det, FrameReport* r) const {
  const bool active = state == EngineState::kInitialPose1 || state == EngineState::kInitialPose2 ||
                      state == EngineState::kRefining || (opt.robot && state == EngineState::kBootstrapping);
  if (!active || !target || !r->board_visible) return std::nullopt;
  Pose p;
  if (!estimate_pose(estimate, Observation::from(det), &p)) return std::nullopt;
  r->pose_estimated = true;
  r->jaccard = board_jaccard(estimate, board, target->T_cam_board, p);
  return p;
}

// At the target, still and with enough corners: a keyframe. At the target without the corners:
// the target moves back. Not reached in time: the next target.
void CalibrationEngine::Impl::capture_step(const cv::Mat& image, const Detection& det,
                                           FrameReport* r) {
  const bool can_capture = state == EngineState::kInitialPose1 || state == EngineState::kInitialPose2 ||
                           state == EngineState::kRefining;
  if (!can_capture || !target) return;
  const bool timed_out =
      opt.target_timeout_frames > 0 &&
      frame_index - target_since_frame > static_cast<uint64_t>(opt.target_timeout_frames);
  // Robots: the host's report decides, the Jaccard index (which needs good intrinsics) is
  // only reported. People: the projected areas must overlap (paper §4.2).
  r->pose_reached = opt.robot ? robot_reached : (r->jaccard > opt.jaccard_threshold);
  if (r->pose_reached && r->still && r->corners >= r->corners_required) {
    r->captured = true;
    crowded_frames = 0;
    const size_t had = keyframes.size();
    const EngineState was = state;
    // A keyframe is measured as with tracking off: the whole frame searched at full resolution.
    const bool tracked = tracker.last_was_tracked();
    const Detection whole =
        tracked ? tracker.detect_whole(board, image, opt.detector) : Detection{};
    capture(tracked && whole.size() >= det.size() ? whole : det);
    // A board held at a target whose keyframes the calibration keeps rejecting (seen: a tilted
    // sensor's second initial pose, refused at every frame for 3000 frames) times out as an
    // unreached target does.
    if (keyframes.size() == had && state == was && target && timed_out)
      skip_timed_out_target("its keyframes rejected");
  } else if (r->pose_reached && r->still && r->corners < r->corners_required &&
             ++crowded_frames >= kCrowdedFrames) {
    move_target_back(r->corners);
  } else if (timed_out) {
    skip_timed_out_target("not reached");
  }
}

void CalibrationEngine::Impl::skip_timed_out_target(const std::string& what) {
  EngineEvent e{EngineEvent::Kind::kTargetSkipped};
  e.message = what + " within " + std::to_string(opt.target_timeout_frames) + " frames";
  if (state == EngineState::kRefining) {
    e.parameter = estimate.param_names()[target_param];
    emit(e);
    set_target(next_pose(target_param), target_param);
  } else {
    // An initial pose nobody reaches would strand the session: offer it again, the tilted
    // one tilted less each time (PoseGenerator::initial_pose).
    const int index = state == EngineState::kInitialPose1 ? 0 : 1;
    emit(e);
    set_target(posegen.initial_pose(index, estimate, ++initial_retries), -1);
  }
}

// The board is where it was asked to be but part of it is out of view: the intrinsics used to
// place the target are off (a robot follows the literal pose). Move the target back along the
// line of sight so the whole board fits, in proportion to the part that is missing (10% .. 100%).
void CalibrationEngine::Impl::move_target_back(int corners) {
  crowded_frames = 0;
  TargetPose t = *target;
  const cv::Size2d bs = board.board_size_m();
  const Eigen::Vector3d c = t.T_cam_board.apply(Eigen::Vector3d(bs.width / 2, bs.height / 2, 0));
  const double factor =
      std::clamp(std::sqrt(board.num_corners() / std::max(1.0, static_cast<double>(corners))), 1.1, 2.0);
  t.T_cam_board.t += c * (factor - 1.0);
  t.note = "only " + std::to_string(corners) + " corners visible at the target: moved back " +
           percent_text(factor - 1.0);
  set_target(t, target_param);
}

void CalibrationEngine::Impl::capture(const Detection& det) {
  skipped_views.clear();  // the next estimate places every view anew
  keyframes.push_back(Observation::from(det));
  keyframe_target.push_back(state == EngineState::kRefining ? target_param : -1);
  EngineEvent ce{EngineEvent::Kind::kCaptured};
  ce.parameter = target_param >= 0 && state == EngineState::kRefining ? estimate.param_names()[target_param] : "";
  ce.message = target ? target_kind_name(target->kind) : "";
  emit(ce);
  robot_reached = false;

  if (keyframes.size() == 1 && !prior) {
    set_state(EngineState::kInitialPose2);
    initial_retries = 0;
    set_target(posegen.initial_pose(1, estimate), -1);
    return;
  }
  if (!recalibrate()) return;  // same target again
  after_calibration();
}

// After a keyframe's calibration (and after a restore): converged, failed at the cap, or the
// next refinement target.
void CalibrationEngine::Impl::after_calibration() {
  if (opt.accuracy_px) return continue_towards_accuracy();
  if (!all_converged() && static_cast<int>(keyframes.size()) < opt.max_keyframes) {
    set_state(EngineState::kRefining);
    choose_refinement_target();  // may converge parameters prospectively
  }
  if (all_converged() && !reopen_above_ceiling()) {
    target.reset();
    target_param = -1;
    set_state(EngineState::kConverged, "every parameter converged");
    return;
  }
  if (static_cast<int>(keyframes.size()) >= opt.max_keyframes) {
    std::string why = "keyframe cap (" + std::to_string(opt.max_keyframes) + ") reached before convergence";
    if (all_converged()) why = ceiling_shortfall();
    if (!result->solver_converged()) {
      why += "; the last bundle adjustment stopped at its iteration limit (" + result->termination_message + ")";
    }
    fail(why);
  }
}

// Corners of the newest keyframe that the calibration cannot explain: a residual above
// max(kOutlierFloorPx, kOutlierSigmas sigma), sigma robust, from the median residual over every
// keyframe's corners (the median of |r| for 2-D Gaussian noise is 1.177 sigma): a detector that
// confuses corners where the board is strongly foreshortened or distorted (seen: a 70-degree tilt
// on a 185-degree fisheye, 9 of 40 corners 1-10 px off, eps_gt 1.9 px instead of 0.1) would
// otherwise pull every parameter. Gaussian noise alone exceeds 6 sigma once in 10^8 corners.
// Indices into frames[frame], ascending; empty if none.
std::vector<size_t> CalibrationEngine::Impl::outlier_corners(const CalibrationResult& r,
                                                             const std::vector<Observation>& frames,
                                                             size_t frame) const {
  constexpr double kOutlierFloorPx = 1.0, kOutlierSigmas = 6.0;
  if (frames.size() < 2 || r.poses.size() != frames.size()) return {};
  std::vector<double> all, last;
  for (size_t f = 0; f < frames.size(); ++f) {
    const std::vector<cv::Point2d> proj =
        project_points(r.model, r.poses[f], frames[f].board_points);
    for (size_t i = 0; i < proj.size(); ++i) {
      const double e = cv::norm(proj[i] - frames[f].image_points[i]);
      all.push_back(std::isfinite(e) ? e : std::numeric_limits<double>::infinity());
      if (f == frame) last.push_back(all.back());
    }
  }
  const double sigma = median(std::move(all)) / 1.177;
  const double limit = std::max(kOutlierFloorPx, kOutlierSigmas * sigma);
  // The worst corners first: one bad corner pulls the pose, and with it its neighbours' residuals
  // past the limit; those above half the worst go this round, the rest are judged again after.
  double worst = 0;
  for (double e : last) worst = std::max(worst, e);
  // (A corner outside the estimate's field has an infinite residual: those go first.)
  const double cut =
      std::isfinite(worst) ? std::max(limit, 0.5 * worst) : std::numeric_limits<double>::max();
  std::vector<size_t> out;
  for (size_t i = 0; i < last.size(); ++i)
    if (!(last[i] <= cut)) out.push_back(i);
  return out;
}

bool CalibrationEngine::Impl::recalibrate() {
  // Warm-started from the previous solution.
  CalibrationResult now;
  CalibrationOptions co = opt.calibration;
  // The parameters a lens model adds to OpenCV's five (k4..k6, s1..s4, tau) are held at their
  // value while the keyframes do not determine them, rather than refusing every keyframe: two
  // views cannot determine 18 intrinsics, and a lens with little distortion never determines
  // k4..k6 (at k4 = 0, d/dk4 = -d/dk1). The five are never held: the paper's behaviour.
  co.hold_if_undetermined = extension_parameters(co.lens_model);
  auto reject = [&](const std::string& why) {
    keyframes.pop_back();
    keyframe_target.pop_back();
    EngineEvent re{EngineEvent::Kind::kKeyframeRejected};
    re.message = why;
    emit(re);
    return false;
  };
  // A solution that folds inside the image is not a lens: part of the image has no ray under it,
  // and the expected error leaves that part out (docs/pose-selection.md, "Estimates that fold
  // inside the image"). Seen on a wide rational lens whose keyframes reach 0.7-0.85 of the image
  // corners' radius: a warm start ending in a local minimum, or a held coefficient keeping an
  // early guess, and eps_gt 1.7-2.7 px against an expected p90 of 0.13-0.21 px. Then the
  // keyframes are solved again cold, and from the same solution with the held coefficients at
  // zero; the best-fitting solution that covers the image is kept (the folded one if none does).
  // (Not in the paper's presets, which stay the paper's.)
  auto solve = [&] {
    std::optional<WarmStart> ws;
    if (result) ws = WarmStart{result->model, result->poses};
    CalibrationResult first = calibrate(keyframes, size, co, ws ? &*ws : nullptr);
    if (opt.method != EngineOptions::Method::kPosecal ||
        grid_points_with_ray(first.model) == kExpectedErrorPoints)
      return first;
    std::optional<CalibrationResult> best;
    auto consider = [&](const WarmStart* from) {
      try {
        CalibrationResult r = calibrate(keyframes, size, co, from);
        if (grid_points_with_ray(r.model) == kExpectedErrorPoints &&
            (!best || r.rms_px < best->rms_px))
          best = std::move(r);
      } catch (const Error&) {
      }
    };
    if (result) consider(nullptr);
    if (!first.held.empty()) {
      std::vector<double> p(first.model.params().begin(), first.model.params().end());
      for (const int h : held_indices(first)) p[h] = 0.0;
      const WarmStart zeroed{
          CameraModel(first.model.width(), first.model.height(), first.model.lens_model(), p),
          first.poses};
      consider(&zeroed);
    }
    return best ? std::move(*best) : first;
  };
  std::string dropped;
  try {
    now = solve();
    // The new keyframe's corners the calibration cannot explain are dropped and the keyframe
    // solved again from the same start, until none is left (so a journal's replay of the kept
    // corners gives the same result); a keyframe with many of them is refused. At the first
    // calibration both keyframes are new: the first one's are dropped too (seen: a fisheye's
    // first keyframe with its rim corners 1.5 px off, kept to the end), never refused.
    const size_t last = keyframes.size() - 1, first_checked = result ? last : 0;
    std::vector<size_t> captured;
    for (size_t f = first_checked; f <= last; ++f) captured.push_back(keyframes[f].size());
    for (int round = 0;; ++round) {
      bool any = false;
      for (size_t f = first_checked; f <= last; ++f) {
        const std::vector<size_t> outliers = outlier_corners(now, keyframes, f);
        if (outliers.empty()) continue;
        any = true;
        Observation& o = keyframes[f];
        const size_t total = o.size(), had = captured[f - first_checked];
        if (f == last && (round == 8 || (had - total + outliers.size()) * 4 > had)) {
          return reject(
              std::to_string(had - total + outliers.size()) + " of its " + std::to_string(had) +
              " corners disagree with the calibration of the others (a misdetected board)");
        }
        if (round == 8 || total - outliers.size() < 4) continue;  // (an earlier keyframe stays)
        Observation kept;
        for (size_t i = 0, k = 0; i < total; ++i) {
          if (k < outliers.size() && outliers[k] == i) {
            ++k;
            continue;
          }
          kept.ids.push_back(o.ids[i]);
          kept.image_points.push_back(o.image_points[i]);
          kept.board_points.push_back(o.board_points[i]);
        }
        o = std::move(kept);
      }
      if (!any || round == 8) break;
      now = solve();
    }
    for (size_t f = first_checked; f <= last; ++f) {
      const size_t had = captured[f - first_checked];
      if (keyframes[f].size() == had) continue;
      dropped += "; dropped " + std::to_string(had - keyframes[f].size()) + " of keyframe " +
                 std::to_string(f + 1) + "'s " + std::to_string(had) +
                 " corners that disagree with the calibration (misdetected)";
    }
  } catch (const Error& e) {
    return reject(e.what());
  }
  const std::string lens_move = opt.auto_lens_model ? choose_lens_model(&now) : "";
  const int tgt = keyframe_target.back();
  const std::optional<CalibrationResult> prev = result ? result : prior;
  if (tgt >= 0) {
    ++param_targeted[tgt];
    ++group_keyframes[static_cast<int>(param_group(tgt))];
    const std::string& target_name = estimate.param_names()[tgt];
    if (prev && std::find(prev->held.begin(), prev->held.end(), target_name) != prev->held.end())
      ++held_keyframes;
  }
  result = now;
  estimate = now.model;
  expected = posecal::expected_error(now);
  EngineEvent ke{EngineEvent::Kind::kCalibrated};
  ke.message = "rms " + std::to_string(now.rms_px) + " px, expected error " +
               std::to_string(expected->rms_px) + " px" + dropped + lens_move;
  if (!expected->covers_image()) ke.message += "; " + fold_text(*expected);
  if (!now.held.empty()) {
    std::string held;
    for (const std::string& n : now.held) {
      if (!held.empty()) held += ", ";
      held += n;
    }
    ke.message += "; held at " + std::string(now.held.size() == 1 ? "its value" : "their values") +
                  ": " + held + " (the keyframes do not determine " +
                  (now.held.size() == 1 ? "it" : "them") + ")";
  }
  emit(ke);
  // (Not across a change of lens model: the variances are of different parameters.)
  if (prev && tgt >= 0 && prev->model.lens_model() == now.model.lens_model())
    update_convergence(*prev, now, tgt);
  const std::vector<std::string>& names = estimate.param_names();
  for (int i = 0; i < estimate.num_params(); ++i) {
    const bool held = std::find(now.held.begin(), now.held.end(), names[i]) != now.held.end();
    if (held && held_keyframes < kHeldKeyframeLimit) {
      param_converged[i] = false;  // a guess, not a value: targeted (held_pending)
    } else if (held) {
      if (!param_converged[i]) {
        mark_converged(i, "held at its value: " + std::to_string(held_keyframes) +
                              " keyframes aimed at the held parameters did not determine it");
      }
    } else if (now.fixed[i]) {
      param_converged[i] = true;  // nothing to refine
    } else if (prev &&
               std::find(prev->held.begin(), prev->held.end(), names[i]) != prev->held.end()) {
      param_converged[i] = false;  // held until now, determined by this keyframe: refine it
    }
  }
  return true;
}

CalibrationEngine::CalibrationEngine(cv::Size image_size, const EngineOptions& options) {
  std::string why;
  if (!options.is_valid(&why)) throw Error(ErrorCode::kInvalidArgument, "engine options: " + why);
  if (image_size.width < 16 || image_size.height < 16) {
    throw Error(ErrorCode::kInvalidArgument, "engine: image size must be at least 16x16");
  }
  impl_ = std::make_unique<Impl>(image_size, options);
}

CalibrationEngine::~CalibrationEngine() = default;

FrameReport CalibrationEngine::process(const cv::Mat& image) { return impl_->process(image); }

void CalibrationEngine::report_pose_reached() {
  const EngineState s = impl_->state;
  if (s == EngineState::kConverged || s == EngineState::kFailed) {
    throw Error(ErrorCode::kState, std::string("pose reached reported while ") + engine_state_name(s));
  }
  if (!impl_->target) throw Error(ErrorCode::kState, "pose reached reported but there is no target yet");
  impl_->robot_reached = true;
}

void CalibrationEngine::skip_target() {
  Impl& s = *impl_;
  if (s.state != EngineState::kRefining || s.target_param < 0) {
    throw Error(ErrorCode::kState, std::string("skip_target while ") + engine_state_name(s.state) +
                                       " (only refinement targets can be skipped)");
  }
  EngineEvent e{EngineEvent::Kind::kTargetSkipped};
  e.parameter = s.estimate.param_names()[s.target_param];
  e.message = "skipped by the host";
  s.emit(e);
  s.set_target(s.next_pose(s.target_param), s.target_param);
}

void CalibrationEngine::give_up(const std::string& why) {
  const EngineState s = impl_->state;
  if (s == EngineState::kConverged || s == EngineState::kFailed) {
    throw Error(ErrorCode::kState, std::string("give_up while ") + engine_state_name(s));
  }
  impl_->fail(why);
}

EngineState CalibrationEngine::state() const { return impl_->state; }
const std::string& CalibrationEngine::failure_reason() const { return impl_->failure; }
int CalibrationEngine::keyframes() const { return static_cast<int>(impl_->keyframes.size()); }
const std::optional<TargetPose>& CalibrationEngine::target() const { return impl_->target; }
int CalibrationEngine::target_parameter() const { return impl_->target_param; }
const CameraModel& CalibrationEngine::estimate() const { return impl_->estimate; }
const CalibrationResult* CalibrationEngine::result() const { return impl_->result ? &*impl_->result : nullptr; }
const std::vector<LensCandidate>& CalibrationEngine::lens_candidates() const {
  return impl_->lens_evidence;
}
const ExpectedError* CalibrationEngine::expected_error() const {
  return impl_->expected ? &*impl_->expected : nullptr;
}
const std::vector<Observation>& CalibrationEngine::keyframe_observations() const { return impl_->keyframes; }
const FrameReport& CalibrationEngine::last_report() const { return impl_->last; }
const BoardTracker::Counts& CalibrationEngine::board_search_counts() const {
  return impl_->tracker.counts();
}
const Board& CalibrationEngine::board() const { return impl_->board; }
const EngineOptions& CalibrationEngine::options() const { return impl_->opt; }
void CalibrationEngine::set_event_callback(std::function<void(const EngineEvent&)> cb) { impl_->callback = std::move(cb); }

std::vector<ParameterStatus> CalibrationEngine::parameters() const {
  const Impl& s = *impl_;
  std::vector<ParameterStatus> out;
  for (int i = 0; i < s.estimate.num_params(); ++i) {
    ParameterStatus p;
    p.name = s.estimate.param_names()[i];
    p.value = s.estimate.params()[i];
    if (s.result) {
      p.std = s.result->std_scaled[i];
      p.std_unit = s.result->std_unit[i];
      p.index_of_dispersion = s.result->index_of_dispersion[i];
    }
    p.converged = s.param_converged[i];
    p.targeted = s.param_targeted[i];
    out.push_back(p);
  }
  return out;
}

}  // namespace posecal
