#include "select/engine.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <limits>
#include <map>
#include <optional>
#include <random>
#include <opencv2/imgproc.hpp>

#include "calib/information.hpp"
#include "common/error.hpp"
#include "select/view_candidates.hpp"
#include "board/views.hpp"

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

const char* engine_event_name(EngineEvent::Kind k) {
  switch (k) {
    case EngineEvent::Kind::kStateChanged: return "state_changed";
    case EngineEvent::Kind::kCaptured: return "captured";
    case EngineEvent::Kind::kKeyframeRejected: return "keyframe_rejected";
    case EngineEvent::Kind::kCalibrated: return "calibrated";
    case EngineEvent::Kind::kParameterConverged: return "parameter_converged";
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
  if (!(convergence_threshold > 0 && convergence_threshold < 1)) return fail("convergence_threshold must be in (0, 1)");
  if (max_keyframes < 3 || max_keyframes > 1000) return fail("max_keyframes must be in [3, 1000]");
  if (!(constraint_factor >= 1 && constraint_factor <= 50)) return fail("constraint_factor must be in [1, 50]");
  if (!(still_motion_px > 0 && still_motion_px < 100)) return fail("still_motion_px must be in (0, 100)");
  if (!(jaccard_threshold > 0 && jaccard_threshold < 1)) return fail("jaccard_threshold must be in (0, 1)");
  if (target_timeout_frames < 0) return fail("target_timeout_frames must be >= 0");
  if (pose_candidates < 1 || pose_candidates > 64) return fail("pose_candidates must be in [1, 64]");
  if (view_candidates < 0 || view_candidates > 4096) return fail("view_candidates must be in [0, 4096]");
  if (!measured_convergence && !prospective_convergence)
    return fail("measured_convergence and prospective_convergence cannot both be off");
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

size_t choose_candidate(const std::vector<double>& score, const std::vector<double>& target_var, size_t n_rule,
                        bool must_serve_target) {
  if (score.size() != target_var.size() || n_rule == 0 || n_rule > score.size()) {
    throw Error(ErrorCode::kInvalidArgument, "choose_candidate: sizes");
  }
  size_t pick = 0;
  for (size_t i = 1; i < n_rule; ++i)
    if (score[i] < score[pick]) pick = i;
  const double rule_var = target_var[pick];
  for (size_t i = n_rule; i < score.size(); ++i)
    if ((!must_serve_target || target_var[i] <= rule_var) && score[i] < score[pick]) pick = i;
  return pick;
}

std::vector<int> ratio_test(const std::vector<double>& var_before, const std::vector<double>& var_after,
                            int targeted, const std::vector<bool>& converged, const int group_keyframes[2],
                            double threshold, EngineOptions::ConvergenceMeasure measure) {
  const size_t n = var_before.size();
  if (var_after.size() != n || converged.size() != n || targeted < 0 || targeted >= static_cast<int>(n)) {
    throw Error(ErrorCode::kInvalidArgument, "ratio_test: inconsistent sizes");
  }
  std::vector<int> out;
  const ParamGroup g = param_group(targeted);
  for (size_t i = 0; i < n; ++i) {
    if (converged[i] || param_group(static_cast<int>(i)) != g) continue;  // only the targeted group
    const double v0 = var_before[i], v1 = var_after[i];
    if (!(v0 > 0) || !std::isfinite(v1)) continue;
    const double red = measure == EngineOptions::ConvergenceMeasure::kStd ? 1.0 - std::sqrt(std::max(0.0, v1) / v0)
                                                                          : 1.0 - v1 / v0;
    // Deviation from the reference implementation: the comparison must be between two
    // keyframes of the group's own strategy, so the first keyframe of a group after
    // initialisation cannot converge parameters it did not target (otherwise p1 and p2
    // "converge" at the first distortion keyframe whatever it taught about them).
    const bool evidence = static_cast<int>(i) == targeted || group_keyframes[static_cast<int>(g)] >= 2;
    if (red >= 0 && red < threshold && evidence) out.push_back(static_cast<int>(i));
  }
  return out;
}

struct CalibrationEngine::Impl {
  cv::Size size;
  EngineOptions opt;
  Board board;
  PoseGenerator posegen;
  std::function<void(const EngineEvent&)> callback;

  EngineState state = EngineState::kWaitingForBoard;
  std::string failure;
  CameraModel estimate;            // current intrinsics
  double best_bootstrap_rms = std::numeric_limits<double>::infinity();  // relative std of f
  bool have_bootstrap = false;
  std::optional<TargetPose> target;
  int target_param = -1;
  uint64_t target_serial = 0;
  uint64_t target_since_frame = 0;

  std::vector<Observation> keyframes;
  std::vector<int> keyframe_target;  // parameter each keyframe was captured for (-1: init)
  std::optional<CalibrationResult> result;
  Eigen::MatrixXd information;       // marginal information of the free intrinsics (scoring)
  Eigen::MatrixXd gram;              // projection_gram() of the estimate (projection scoring)
  // EngineOptions::view_candidates: the pool for the next choice, drawn frame by frame, and the
  // pool of the last choice (for replacing skipped targets).
  std::vector<ViewPose> view_pool, view_pool_used;
  std::mt19937_64 view_rng{0x5eed0000u};
  std::vector<Pose> skipped_views;     // view targets skipped since the last keyframe
  std::vector<bool> param_converged;
  std::vector<int> param_targeted;
  int group_keyframes[2] = {0, 0};   // refinement keyframes captured per parameter group

  Detection previous;
  bool robot_reached = false;
  int crowded_frames = 0;  // consecutive still frames at the target with too few corners
  static constexpr int kCrowdedFrames = 3;
  uint64_t frame_index = 0;
  FrameReport last;

  Impl(cv::Size s, const EngineOptions& o)
      : size(s), opt(o), board(o.board), posegen(board, s, o.posegen) {
    const double f = o.initial_focal_guess > 0 ? o.initial_focal_guess : std::max(s.width, s.height);
    estimate = CameraModel::pinhole(o.calibration.lens_model, s.width, s.height, f, f, (s.width - 1) * 0.5,
                                    (s.height - 1) * 0.5);
    const int n = estimate.num_params();
    param_converged.assign(n, false);
    param_targeted.assign(n, 0);
  }

  void emit(EngineEvent e) {
    e.keyframes = static_cast<int>(keyframes.size());
    if (callback) callback(e);
  }

  void set_state(EngineState s, const std::string& message = "") {
    if (s == state) return;
    EngineEvent e{EngineEvent::Kind::kStateChanged};
    e.from = state;
    e.to = s;
    e.message = message;
    state = s;
    emit(e);
  }

  void fail(const std::string& why) {
    failure = why;
    target.reset();
    set_state(EngineState::kFailed, why);
  }

  void set_target(TargetPose t, int param) {
    target = std::move(t);
    target_param = param;
    ++target_serial;
    target_since_frame = frame_index;
    robot_reached = false;
    crowded_frames = 0;
    EngineEvent e{EngineEvent::Kind::kTargetChanged};
    e.parameter = param >= 0 ? estimate.param_names()[param] : "";
    e.message = target->kind + (target->note.empty() ? "" : ": " + target->note);
    emit(e);
  }

  // Points needed per keyframe so that constraints >= factor x unknowns (paper §4.3): for the
  // two initial frames the unknowns are the intrinsics plus 6 per frame, spread over both
  // frames; afterwards every frame only adds its own 6 pose parameters.
  int corners_required() const {
    const double n_intr = estimate.num_params();
    double pts;
    if (keyframes.size() < 2) {
      pts = opt.constraint_factor * (n_intr + 2 * 6) / 2.0 / 2.0;
    } else {
      pts = opt.constraint_factor * 6 / 2.0;
    }
    return static_cast<int>(std::ceil(pts - 1e-9));
  }

  int bootstrap_min_corners() const {
    return opt.bootstrap_min_corners > 0 ? opt.bootstrap_min_corners : std::max(6, board.num_corners() / 2);
  }

  // Paper §3.4: a single-frame calibration of the focal length only (principal point at the
  // centre, no distortion); the best by residual is kept.
  bool try_bootstrap(const Detection& det) {
    if (static_cast<int>(det.size()) < bootstrap_min_corners()) return false;
    CalibrationOptions co = opt.calibration;
    // Focal lengths only: fx and fy both free. The paper's sampling protocol varies them
    // independently by 10%; forcing fx = fy turns the aspect ratio into a false tilt seen from
    // far away (seen: f 4.5x too large), which sends a robot to an invisible target.
    co.fix_principal_point = true;
    co.fix_aspect_ratio = false;
    co.zero_distortion = true;
    co.fixed.clear();
    try {
      const CalibrationResult r = calibrate({Observation::from(det)}, size, co);
      // Uncertainty at the measured noise level, floored at 0.1 px so that a perfect fit of a
      // weak view cannot pass: telephoto lenses see little perspective, so at 1 px noise even a
      // 60 degree tilt leaves f 5% uncertain, while their real corner noise is ~0.05 px.
      const double sigma = std::max(0.1, std::sqrt(r.residual_variance));
      const double rel_std = r.std_unit[0] * sigma / r.model.fx();
      if (rel_std > opt.bootstrap_max_relative_std) return false;
      // Bias: the principal point is assumed at the centre. A weak view lets that assumption
      // move f a lot (seen: f 5x too large from a 10 degree view of a camera whose principal
      // point was 100 px off); a robot sent to a target computed with such an f sees nothing.
      // Refit with the principal point moved by 5% of the image; f must stay within 10%.
      for (const cv::Point2d d : {cv::Point2d(0.05, 0), cv::Point2d(-0.05, 0), cv::Point2d(0, 0.05), cv::Point2d(0, -0.05)}) {
        CameraModel shifted = r.model;
        shifted.params()[2] += d.x * size.width;
        shifted.params()[3] += d.y * size.height;
        const WarmStart ws{shifted, r.poses};
        const CalibrationResult rs = calibrate({Observation::from(det)}, size, co, &ws);
        if (std::abs(rs.model.fx() - r.model.fx()) > opt.bootstrap_max_pp_sensitivity * r.model.fx()) return false;
      }
      // Deviation from the paper (which keeps the best by residual): keep the view that
      // determines f best. A weak view fits any f with a low residual (docs/pose-selection.md).
      if (rel_std < best_bootstrap_rms) {
        best_bootstrap_rms = rel_std;
        estimate = r.model;
        have_bootstrap = true;
        return true;
      }
    } catch (const Error&) {
      // Degenerate view (e.g. fronto-parallel): the focal length is unobservable from it.
    }
    return false;
  }

  // Relative reduction as the ratio test measures it.
  double reduction(double var_before, double var_after) const {
    if (!(var_before > 0)) return 0.0;
    return opt.convergence_measure == EngineOptions::ConvergenceMeasure::kStd
               ? 1.0 - std::sqrt(std::max(0.0, var_after) / var_before)
               : 1.0 - var_after / var_before;
  }

  void mark_converged(int i, const std::string& why) {
    param_converged[i] = true;
    EngineEvent e{EngineEvent::Kind::kParameterConverged};
    e.parameter = estimate.param_names()[i];
    e.message = why;
    emit(e);
  }

  static std::string percent(double v) {
    char buf[32];
    std::snprintf(buf, sizeof buf, "%.1f%%", v * 100.0);
    return buf;
  }

  void choose_refinement_target() {
    // The estimate does not change while parameters converge prospectively below, so the scoring
    // matrices are computed once per choice.
    const bool scoring = opt.pose_candidates > 1 || opt.prospective_convergence;
    if (scoring) prepare_scoring();
    // Generic views do not depend on the targeted parameter: drawn and screened once per choice;
    // the few that compete exactly are predicted exactly once (cached across targets).
    std::optional<ViewCandidates> views;
    if (scoring && opt.view_candidates > 0) views.emplace(view_candidates());
    while (true) {
      // MaxIOD (paper §4.1): the parameter with the highest index of dispersion among those not
      // converged.
      int best = -1;
      double best_iod = -1;
      for (int i = 0; i < estimate.num_params(); ++i) {
        if (param_converged[i] || result->fixed[i]) continue;
        if (result->index_of_dispersion[i] > best_iod) {
          best_iod = result->index_of_dispersion[i];
          best = i;
        }
      }
      if (best < 0) return;
      const std::vector<TargetPose> cands = posegen.candidates(best, estimate, opt.pose_candidates);
      if (cands.empty()) throw Error(ErrorCode::kInternal, "pose generation produced no candidate");
      const size_t n_rule = cands.size();
      size_t pick = 0;
      // Predicted variance of `best` after the candidate that will be captured: the prospective
      // test asks whether the keyframe the engine is about to request would help it.
      double pick_var = std::numeric_limits<double>::infinity();
      std::vector<ViewCandidates::Exact> shortlisted;
      if (scoring) pick = pick_candidate(best, cands, views ? &*views : nullptr, &shortlisted, &pick_var);
      if (opt.prospective_convergence) {
        const double now = result->std_unit[best] * result->std_unit[best];
        const double red = reduction(now, pick_var);
        if (red < opt.convergence_threshold) {
          mark_converged(best, "best pose would reduce its variance by only " + percent(red) +
                                   ": converged without capturing it");
          if (std::all_of(param_converged.begin(), param_converged.end(), [](bool b) { return b; })) return;
          continue;
        }
      }
      if (pick < n_rule) {
        posegen.commit(cands[pick]);
        set_target(cands[pick], best);
      } else {
        set_target(*shortlisted[pick - n_rule].target, best);  // a view uses no sequence element or region
      }
      return;
    }
  }

  // The best of the rule candidates `cands` for parameter `param` and, if `views` is given, the
  // views' shortlist (less the views skipped since the last keyframe), by the candidate score
  // (choose_candidate). Returns its index: < cands.size() a rule candidate, else
  // cands.size() + its position in *shortlisted. *pick_var: its predicted variance of `param`.
  size_t pick_candidate(int param, const std::vector<TargetPose>& cands, ViewCandidates* views,
                        std::vector<ViewCandidates::Exact>* shortlisted, double* pick_var) const {
    const bool by_projection = opt.candidate_score == EngineOptions::CandidateScore::kProjection;
    const int k = free_position(param);
    std::vector<double> score, var;
    for (const TargetPose& c : cands) {
      const Eigen::MatrixXd cov = predicted_covariance(c);
      var.push_back(k < 0 ? 0.0 : cov(k, k));
      score.push_back(by_projection ? (gram * cov).trace() : var.back());
    }
    // The views that compete exactly: the shortlist by the screened score, and with
    // view_must_serve_target also by the screened variance of the target.
    shortlisted->clear();
    if (views && (by_projection || k >= 0)) {
      for (const ViewCandidates::Exact& v :
           views->shortlist(by_projection || k < 0 ? -1 : k, opt.view_must_serve_target && by_projection ? k : -1)) {
        const bool skipped = std::any_of(skipped_views.begin(), skipped_views.end(), [&](const Pose& p) {
          return (p.r - v.target->T_cam_board.r).norm() < 1e-12 && (p.t - v.target->T_cam_board.t).norm() < 1e-12;
        });
        if (skipped) continue;
        shortlisted->push_back(v);
        var.push_back(k < 0 ? 0.0 : v.prediction.variance(k));
        score.push_back(by_projection ? v.prediction.projection : var.back());
      }
    }
    const size_t pick = choose_candidate(score, var, cands.size(), opt.view_must_serve_target);
    *pick_var = var[pick];
    return pick;
  }

  // The view candidates of a choice: the pool drawn in the frames since the last choice (topped
  // up here if those frames did not draw all of it), screened under the current estimate. The
  // pool is then kept for skipped targets and a new one starts, seeded by the keyframe count (a
  // run is reproducible).
  ViewCandidates view_candidates() {
    grow_view_pool(opt.view_candidates, opt.view_candidates);
    view_pool_used = std::move(view_pool);
    view_pool.clear();
    view_rng.seed(0x5eed0000u + keyframes.size());
    return screen_views(view_pool_used);
  }

  ViewCandidates screen_views(const std::vector<ViewPose>& pool) const {
    ViewCandidateOptions vo;
    vo.count = opt.view_candidates;
    vo.margin_px = view_margin_px();
    vo.shortlist = kExactViews;
    return ViewCandidates(estimate, board, result->fixed, information, gram, pool, vo);
  }

  double view_margin_px() const { return opt.posegen.border_margin_fraction * std::max(size.width, size.height); }

  // Draws up to `n` more views into the pool, up to `pool_size` in all, under the current estimate
  // (ViewSampler: tilt up to 40 deg, 40-80% of the width, anywhere the whole board fits).
  // process() draws kViewsPerFrame per frame while a target choice is ahead, so the choice itself
  // only screens them (docs/pose-selection.md, "Generic view candidates"). At most 200 draws per
  // view: an estimate under which the board rarely fits yields fewer views, not a long search.
  void grow_view_pool(int n, int pool_size) {
    const int want = std::min(n, pool_size - static_cast<int>(view_pool.size()));
    if (want <= 0) return;
    ViewSampling vs;
    // Where the best views of a large random pool lie (explore_information: median tilt 22 deg,
    // 56% of the width); sampling there beats sampling wider with the same count.
    vs.max_tilt_deg = 40;
    vs.min_width_fraction = 0.4;
    vs.max_width_fraction = 0.8;
    vs.margin_px = view_margin_px();
    const ViewSampler sampler(estimate, board, vs);
    for (int i = 0; i < want; ++i) {
      ViewPose v;
      if (!sampler.draw(view_rng, &v.R, &v.t, nullptr, 200)) break;
      view_pool.push_back(v);
    }
  }
  static constexpr int kViewsPerFrame = 100;
  // The frames draw this many times view_candidates: a view drawn under the previous estimate
  // may not fit under the next one, and the choice takes the first view_candidates that do.
  static constexpr int kPoolFactor = 2;

  // Views predicted exactly per target: of 300 screened views the exact best was among the 8
  // best screened in 97% of 168 choices and among the 16 best in 99.4% (explore_information
  // --screening; docs/math.md); in closed loop, scoring all exactly changed no median.
  static constexpr int kExactViews = 12;

  // Predicted covariance of the free intrinsics after capturing `t` (Sigma_p = I), exact at the
  // linearisation point (docs/math.md).
  Eigen::MatrixXd predicted_covariance(const TargetPose& t) const {
    const Eigen::MatrixXd info = information + frame_information(estimate, t.T_cam_board, board.corners(), result->fixed);
    return info.ldlt().solve(Eigen::MatrixXd::Identity(info.rows(), info.cols()));
  }

  // Position of `param` among the free intrinsics, -1 if it is fixed.
  int free_position(int param) const {
    if (result->fixed[param]) return -1;
    return static_cast<int>(std::count(result->fixed.begin(), result->fixed.begin() + param, false));
  }

  // Predicted variance of parameter `param` after capturing `t`.
  double predicted_variance(int param, const TargetPose& t) const {
    const int k = free_position(param);
    return k < 0 ? 0.0 : predicted_covariance(t)(k, k);
  }

  // Expected squared projection error over the image after capturing `t`: trace(G Sigma'), the
  // expected eps_gt^2 up to the noise variance (docs/pose-selection.md).
  double predicted_projection(const TargetPose& t) const { return (gram * predicted_covariance(t)).trace(); }

  void prepare_scoring() {
    information = intrinsics_information(*result);
    // 8x5 rays: the same choices as 16x9 in 46 of 48 closed-loop runs (24 benchmark cameras), at a
    // quarter of the cost (docs/performance.md).
    if (opt.candidate_score == EngineOptions::CandidateScore::kProjection) gram = projection_gram(estimate, result->fixed, 8, 5);
  }

  // A new target for the same parameter (skipped or timed-out target).
  TargetPose next_pose(int param) {
    if (opt.pose_candidates <= 1 || !result) return posegen.next_pose(param, estimate);
    prepare_scoring();
    if (opt.view_candidates > 0) {
      // Rule candidates and views together, as for a new target; a skipped view is not offered
      // again until the next keyframe (a skipped rule pose has used its sequence element or
      // region already).
      if (target && target->kind == "view") skipped_views.push_back(target->T_cam_board);
      const std::vector<TargetPose> cands = posegen.candidates(param, estimate, opt.pose_candidates);
      if (cands.empty()) throw Error(ErrorCode::kInternal, "pose generation produced no candidate");
      ViewCandidates views = screen_views(view_pool_used);
      std::vector<ViewCandidates::Exact> shortlisted;
      double var = 0;
      const size_t pick = pick_candidate(param, cands, &views, &shortlisted, &var);
      if (pick < cands.size()) {
        posegen.commit(cands[pick]);
        return cands[pick];
      }
      return *shortlisted[pick - cands.size()].target;
    }
    if (opt.candidate_score == EngineOptions::CandidateScore::kProjection) {
      return posegen.next_pose(param, estimate, [&](const TargetPose& t) { return predicted_projection(t); },
                               opt.pose_candidates);
    }
    return posegen.next_pose(param, estimate, [&](const TargetPose& t) { return predicted_variance(param, t); },
                             opt.pose_candidates);
  }

  // Ratio test (paper §4.1) on the parameters of the targeted parameter's group.
  void update_convergence(const CalibrationResult& prev, const CalibrationResult& now, int tgt) {
    if (tgt < 0 || !opt.measured_convergence) return;
    std::vector<double> v0, v1;
    std::vector<bool> skip = param_converged;
    for (int i = 0; i < estimate.num_params(); ++i) {
      v0.push_back(prev.std_unit[i] * prev.std_unit[i]);
      v1.push_back(now.std_unit[i] * now.std_unit[i]);
      if (now.fixed[i]) skip[i] = true;
    }
    for (int i : ratio_test(v0, v1, tgt, skip, group_keyframes, opt.convergence_threshold, opt.convergence_measure)) {
      mark_converged(i, "variance reduced by only " + percent(reduction(v0[i], v1[i])) + " by the last keyframe");
    }
  }

  void capture(const Detection& det) {
    skipped_views.clear();  // the next estimate places every view anew
    keyframes.push_back(Observation::from(det));
    keyframe_target.push_back(state == EngineState::kRefining ? target_param : -1);
    EngineEvent ce{EngineEvent::Kind::kCaptured};
    ce.parameter = target_param >= 0 && state == EngineState::kRefining ? estimate.param_names()[target_param] : "";
    ce.message = target ? target->kind : "";
    emit(ce);
    robot_reached = false;

    if (keyframes.size() == 1) {
      set_state(EngineState::kInitialPose2);
      set_target(posegen.initial_pose(1, estimate), -1);
      return;
    }
    // Recalibrate with every keyframe, warm-started from the previous solution.
    CalibrationResult now;
    try {
      if (result) {
        const WarmStart ws{result->model, result->poses};
        now = calibrate(keyframes, size, opt.calibration, &ws);
      } else {
        now = calibrate(keyframes, size, opt.calibration);
      }
    } catch (const Error& e) {
      keyframes.pop_back();
      keyframe_target.pop_back();
      EngineEvent re{EngineEvent::Kind::kKeyframeRejected};
      re.message = e.what();
      emit(re);
      return;  // same target again
    }
    const int tgt = keyframe_target.back();
    if (tgt >= 0) {
      ++param_targeted[tgt];
      ++group_keyframes[static_cast<int>(param_group(tgt))];
    }
    const std::optional<CalibrationResult> prev = result;
    result = now;
    estimate = now.model;
    EngineEvent ke{EngineEvent::Kind::kCalibrated};
    ke.message = "rms " + std::to_string(now.rms_px) + " px";
    emit(ke);
    if (prev && tgt >= 0) update_convergence(*prev, now, tgt);
    for (int i = 0; i < estimate.num_params(); ++i)
      if (now.fixed[i]) param_converged[i] = true;  // nothing to refine

    auto all_converged = [&] {
      return std::all_of(param_converged.begin(), param_converged.end(), [](bool b) { return b; });
    };
    if (!all_converged() && static_cast<int>(keyframes.size()) < opt.max_keyframes) {
      set_state(EngineState::kRefining);
      choose_refinement_target();  // may converge parameters prospectively
    }
    if (all_converged()) {
      target.reset();
      target_param = -1;
      set_state(EngineState::kConverged, "every parameter converged");
      return;
    }
    if (static_cast<int>(keyframes.size()) >= opt.max_keyframes) {
      fail("keyframe cap (" + std::to_string(opt.max_keyframes) + ") reached before convergence");
    }
  }

  std::string guidance_text(const FrameReport& r, const std::optional<Pose>& current) const {
    switch (state) {
      case EngineState::kConverged: return "calibration converged";
      case EngineState::kFailed: return "calibration stopped: " + failure;
      case EngineState::kWaitingForBoard: return "show the calibration board to the camera";
      case EngineState::kBootstrapping:
        return r.corners < bootstrap_min_corners() ? "show more of the board"
                                                   : "tilt the board slightly so the focal length can be estimated";
      default: break;
    }
    if (r.captured) return "captured keyframe " + std::to_string(keyframes.size());
    if (!r.board_visible) return "show the calibration board to the camera";
    if (r.corners < r.corners_required) {
      return "show the whole board (" + std::to_string(r.corners) + " of " + std::to_string(r.corners_required) +
             " corners needed)";
    }
    if (r.pose_reached) return "hold still";
    if (opt.robot) return "waiting for the robot to reach the target pose";
    if (!current || !target) return "align the board with the overlay";
    const auto a = projected_outline(estimate, board, target->T_cam_board, 4);
    const auto b = projected_outline(estimate, board, *current, 4);
    if (a.empty() || b.empty()) return "align the board with the overlay";
    const double area_a = std::abs(cv::contourArea(std::vector<cv::Point2f>(a.begin(), a.end())));
    const double area_b = std::abs(cv::contourArea(std::vector<cv::Point2f>(b.begin(), b.end())));
    cv::Point2d ca(0, 0), cb(0, 0);
    for (const auto& p : a) ca += p;
    for (const auto& p : b) cb += p;
    ca /= static_cast<double>(a.size());
    cb /= static_cast<double>(b.size());
    const cv::Point2d d = ca - cb;
    const double tol = 0.04 * std::max(size.width, size.height);
    if (std::abs(d.x) > tol || std::abs(d.y) > tol) {
      if (std::abs(d.x) >= std::abs(d.y)) return d.x > 0 ? "move right" : "move left";
      return d.y > 0 ? "move down" : "move up";
    }
    if (area_a > 1.15 * area_b) return "move closer";
    if (area_a < 0.87 * area_b) return "move further away";
    const Eigen::Vector3d n_t = target->T_cam_board.R().col(2), n_c = current->R().col(2);
    const double tilt_t = std::acos(std::clamp(n_t.z(), -1.0, 1.0)), tilt_c = std::acos(std::clamp(n_c.z(), -1.0, 1.0));
    if (tilt_t > tilt_c + 0.09) return "tilt the board further";
    if (tilt_t < tilt_c - 0.09) return "tilt the board back towards the camera";
    if (rotation_angle_between(target->T_cam_board.R(), current->R()) > 0.09) return "rotate the board to match the overlay";
    return "align the board with the overlay";
  }

  FrameReport process(const cv::Mat& image) {
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
    const Detection det = board.detect(image, opt.detector);
    r.corners = static_cast<int>(det.size());
    r.board_visible = det.size() >= 4;
    r.corners_required = corners_required();

    // Stillness (paper §4.3): every corner of the previous frame re-detected, mean motion small.
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
        r.motion_px = sum / static_cast<double>(previous.size());
        r.still = r.motion_px < opt.still_motion_px;
      }
    }
    previous = det;

    if (state == EngineState::kWaitingForBoard && r.board_visible) set_state(EngineState::kBootstrapping);
    if (state == EngineState::kBootstrapping || state == EngineState::kInitialPose1 ||
        state == EngineState::kInitialPose2) {
      // Until two keyframes exist, keep improving the bootstrap (paper §3.4).
      const double f_before = estimate.fx();
      // Robots: only still frames (not the ones taken while moving); the strong view at the
      // first target (tilted 45 degrees) then replaces a weaker start view.
      const bool may_bootstrap = !opt.robot || r.still;
      if (keyframes.empty() && may_bootstrap && try_bootstrap(det)) {
        const bool first = state == EngineState::kBootstrapping;
        if (first) set_state(EngineState::kInitialPose1);
        // Regenerate the target only when the focal length moved noticeably, so the overlay
        // does not jitter with every slightly better bootstrap.
        if (first || !target || std::abs(estimate.fx() - f_before) > 0.02 * f_before) {
          set_target(posegen.initial_pose(0, estimate), -1);
        }
      }
    }

    std::optional<Pose> current;
    const bool active = state == EngineState::kInitialPose1 || state == EngineState::kInitialPose2 ||
                        state == EngineState::kRefining || (opt.robot && state == EngineState::kBootstrapping);
    if (active && target && r.board_visible) {
      Pose p;
      if (estimate_pose(estimate, Observation::from(det), &p)) {
        current = p;
        r.pose_estimated = true;
        r.jaccard = board_jaccard(estimate, board, target->T_cam_board, p);
      }
    }
    const bool can_capture = state == EngineState::kInitialPose1 || state == EngineState::kInitialPose2 ||
                             state == EngineState::kRefining;
    if (can_capture && target) {
      // Robots: the host's report decides, the Jaccard index (which needs good intrinsics) is
      // only reported. People: the projected areas must overlap (paper §4.2).
      r.pose_reached = opt.robot ? robot_reached : (r.jaccard > opt.jaccard_threshold);
      if (r.pose_reached && r.still && r.corners >= r.corners_required) {
        r.captured = true;
        crowded_frames = 0;
        capture(det);
      } else if (r.pose_reached && r.still && r.corners < r.corners_required &&
                 ++crowded_frames >= kCrowdedFrames) {
        // The board is where it was asked to be but part of it is out of view: the intrinsics
        // used to place the target are off (a robot follows the literal pose). Move the target
        // back along the line of sight so the whole board fits.
        crowded_frames = 0;
        TargetPose t = *target;
        const cv::Size2d bs = board.board_size_m();
        const Eigen::Vector3d c = t.T_cam_board.apply(Eigen::Vector3d(bs.width / 2, bs.height / 2, 0));
        // Back off in proportion to the part of the board that is missing (10% .. 100%).
        const double factor =
            std::clamp(std::sqrt(board.num_corners() / std::max(1.0, static_cast<double>(r.corners))), 1.1, 2.0);
        t.T_cam_board.t += c * (factor - 1.0);
        t.note = "only " + std::to_string(r.corners) + " corners visible at the target: moved back " +
                 percent(factor - 1.0);
        set_target(t, target_param);
      } else if (state == EngineState::kRefining && opt.target_timeout_frames > 0 &&
                 frame_index - target_since_frame > static_cast<uint64_t>(opt.target_timeout_frames)) {
        EngineEvent e{EngineEvent::Kind::kTargetSkipped};
        e.parameter = estimate.param_names()[target_param];
        e.message = "not reached within " + std::to_string(opt.target_timeout_frames) + " frames";
        emit(e);
        set_target(next_pose(target_param), target_param);
      }
    }
    // A target choice is ahead: draw part of its view candidates now, spread over the frames in
    // which the board is moved to the current target.
    const bool scoring = opt.pose_candidates > 1 || opt.prospective_convergence;  // views are scored
    if (opt.view_candidates > 0 && scoring && (state == EngineState::kInitialPose2 || state == EngineState::kRefining)) {
      grow_view_pool(kViewsPerFrame, kPoolFactor * opt.view_candidates);
    }
    r.state = state;
    r.keyframes = static_cast<int>(keyframes.size());
    r.target_parameter = (state == EngineState::kRefining && target_param >= 0) ? estimate.param_names()[target_param] : "";
    r.guidance = guidance_text(r, current);
    last = r;
    return r;
  }
};

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

EngineState CalibrationEngine::state() const { return impl_->state; }
const std::string& CalibrationEngine::failure_reason() const { return impl_->failure; }
int CalibrationEngine::keyframes() const { return static_cast<int>(impl_->keyframes.size()); }
const std::optional<TargetPose>& CalibrationEngine::target() const { return impl_->target; }
int CalibrationEngine::target_parameter() const { return impl_->target_param; }
const CameraModel& CalibrationEngine::estimate() const { return impl_->estimate; }
const CalibrationResult* CalibrationEngine::result() const { return impl_->result ? &*impl_->result : nullptr; }
const std::vector<Observation>& CalibrationEngine::keyframe_observations() const { return impl_->keyframes; }
const FrameReport& CalibrationEngine::last_report() const { return impl_->last; }
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

GuidanceInfo CalibrationEngine::guidance_info() const {
  const Impl& s = *impl_;
  GuidanceInfo g;
  g.has_target = s.target.has_value();
  g.bootstrapping = !s.have_bootstrap && s.keyframes.empty();
  g.robot = s.opt.robot;
  if (s.target) g.T_cam_board_target = s.target->T_cam_board;
  g.estimate = s.estimate;
  g.target_serial = s.target_serial;
  g.target_kind = s.target ? s.target->kind : "";
  g.keyframes = static_cast<int>(s.keyframes.size());
  g.finished = s.state == EngineState::kConverged || s.state == EngineState::kFailed;
  return g;
}

void CalibrationEngine::draw_overlay(cv::Mat& image) const {
  const Impl& s = *impl_;
  if (image.empty() || image.depth() != CV_8U || (image.channels() != 1 && image.channels() != 3)) {
    throw Error(ErrorCode::kInvalidArgument, "overlay: image must be 8-bit grey or BGR");
  }
  if (image.size() != s.size) throw Error(ErrorCode::kInvalidArgument, "overlay: image size differs from the camera's");
  const bool color = image.channels() == 3;
  const cv::Scalar target_col = color ? cv::Scalar(255, 160, 0) : cv::Scalar(255);
  const cv::Scalar corner_col = color ? cv::Scalar(0, 220, 0) : cv::Scalar(0);
  const cv::Scalar text_col = color ? cv::Scalar(0, 255, 255) : cv::Scalar(255);
  if (s.target) {
    // The target board, projected with the current intrinsics and distortion: a translucent
    // sheet plus its square grid (lines sampled densely so distortion bends them).
    const auto outline = projected_outline(s.estimate, s.board, s.target->T_cam_board, 24);
    if (!outline.empty()) {
      std::vector<cv::Point> poly;
      for (const auto& p : outline) poly.emplace_back(cvRound(p.x), cvRound(p.y));
      cv::Mat layer = image.clone();
      cv::fillPoly(layer, std::vector<std::vector<cv::Point>>{poly}, target_col, cv::LINE_AA);
      cv::addWeighted(layer, 0.35, image, 0.65, 0, image);
      const cv::Size2d bs = s.board.board_size_m();
      const double sq = s.board.spec().square_length_m;
      const int nx = static_cast<int>(std::lround(bs.width / sq)), ny = static_cast<int>(std::lround(bs.height / sq));
      auto line3d = [&](cv::Point3d a, cv::Point3d b) {
        std::vector<cv::Point3d> pts;
        for (int k = 0; k <= 16; ++k) pts.push_back(a + (b - a) * (k / 16.0));
        const auto pr = project_points(s.estimate, s.target->T_cam_board, pts);
        std::vector<cv::Point> pl;
        for (const auto& p : pr)
          if (std::isfinite(p.x)) pl.emplace_back(cvRound(p.x), cvRound(p.y));
        if (pl.size() > 1) cv::polylines(image, std::vector<std::vector<cv::Point>>{pl}, false, target_col, 1, cv::LINE_AA);
      };
      for (int i = 0; i <= nx; ++i) line3d({i * sq, 0, 0}, {i * sq, bs.height, 0});
      for (int j = 0; j <= ny; ++j) line3d({0, j * sq, 0}, {bs.width, j * sq, 0});
    }
  }
  for (const auto& p : s.previous.image_points) cv::circle(image, cv::Point(cvRound(p.x), cvRound(p.y)), 3, corner_col, 1, cv::LINE_AA);
  const double scale = std::max(0.5, s.size.width / 1280.0);
  const std::string status = std::string(engine_state_name(s.state)) + "  keyframes " + std::to_string(s.keyframes.size()) +
                             (s.last.target_parameter.empty() ? "" : "  target " + s.last.target_parameter) +
                             (s.last.jaccard >= 0 ? "  J " + std::to_string(s.last.jaccard).substr(0, 4) : "");
  cv::putText(image, status, cv::Point(10, static_cast<int>(30 * scale)), cv::FONT_HERSHEY_SIMPLEX, 0.7 * scale, text_col, 2, cv::LINE_AA);
  cv::putText(image, s.last.guidance, cv::Point(10, static_cast<int>(62 * scale)), cv::FONT_HERSHEY_SIMPLEX, 0.8 * scale, text_col, 2, cv::LINE_AA);
}

}  // namespace posecal
