// The next target (paper §4.1 and docs/pose-selection.md): MaxIOD picks the parameter, the pose
// rules and (with view_candidates) generic views offer candidates, the predicted covariance after
// each decides.
#include <algorithm>
#include <cmath>
#include <limits>

#include "calib/information.hpp"
#include "common/error.hpp"
#include "select/engine_internal.hpp"

namespace posecal {

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

void CalibrationEngine::Impl::choose_refinement_target() {
  // The estimate does not change while parameters converge prospectively below, so the scoring
  // matrices are computed once per choice.
  const bool scoring = this->scoring();
  if (scoring) prepare_scoring();
  // Generic views do not depend on the targeted parameter: drawn and screened once per choice;
  // the few that compete exactly are predicted exactly once (cached across targets).
  std::optional<ViewCandidates> views;
  if (scoring && opt.view_candidates > 0) views.emplace(view_candidates());
  while (true) {
    const int best = max_iod_parameter();
    if (best < 0) return;
    // Predicted variance of `best` after the candidate that will be captured: the prospective
    // test asks whether the keyframe the engine is about to request would help it.
    const CandidatePick p = best_candidate(best, views ? &*views : nullptr, scoring);
    // (A held parameter has no variance to predict: its keyframe is captured.)
    if (opt.prospective_convergence && !is_held(best) &&
        converges_prospectively(best, p.variance)) {
      if (all_converged()) return;
      continue;
    }
    set_picked_target(p, best);
    return;
  }
}

// With accuracy_px: the next target is for the intrinsic that holds the expected error back
// (ExpectedError::limiting_param), the candidate the one that lowers the predicted error most
// (or the parameter's variance, by candidate_score). No parameter converges by the ratio test.
void CalibrationEngine::Impl::choose_accuracy_target() {
  prepare_scoring();
  std::optional<ViewCandidates> views;
  if (opt.view_candidates > 0) views.emplace(view_candidates());
  const ExpectedError* e = expected ? &*expected : prior_expected ? &*prior_expected : nullptr;
  const int held = held_pending();
  const int param = held >= 0                     ? held
                    : e && e->limiting_param >= 0 ? e->limiting_param
                                                  : max_iod_parameter();
  if (param < 0) throw Error(ErrorCode::kInternal, "accuracy target: no free intrinsic");
  set_picked_target(best_candidate(param, views ? &*views : nullptr, true), param);
}

CalibrationEngine::Impl::CandidatePick CalibrationEngine::Impl::best_candidate(int param, ViewCandidates* views,
                                                                             bool scoring) {
  CandidatePick p;
  p.rules = posegen.candidates(param, estimate, opt.pose_candidates);
  if (p.rules.empty()) throw Error(ErrorCode::kInternal, "pose generation produced no candidate");
  if (scoring) p.pick = pick_candidate(param, p.rules, views, &p.shortlisted, &p.variance);
  return p;
}

void CalibrationEngine::Impl::set_picked_target(const CandidatePick& p, int param) {
  if (p.pick < p.rules.size()) {
    posegen.commit(p.rules[p.pick]);
    set_target(p.rules[p.pick], param);
  } else {
    set_target(*p.shortlisted[p.pick - p.rules.size()].target, param);  // a view uses no sequence element or region
  }
}

// MaxIOD (paper §4.1): the parameter with the highest index of dispersion among those not
// converged; -1 if none is left.
int CalibrationEngine::Impl::max_iod_parameter() const {
  // A held parameter's dispersion is unbounded: it comes first.
  if (const int h = held_pending(); h >= 0) return h;
  int best = -1;
  double best_iod = -1;
  for (int i = 0; i < estimate.num_params(); ++i) {
    if (param_converged[i] || basis().fixed[i]) continue;
    if (basis().index_of_dispersion[i] > best_iod) {
      best_iod = basis().index_of_dispersion[i];
      best = i;
    }
  }
  return best;
}

bool CalibrationEngine::Impl::is_held(int param) const {
  if (!result && !prior) return false;
  const std::vector<std::string>& held = basis().held;
  return std::find(held.begin(), held.end(), estimate.param_names()[param]) != held.end();
}

int CalibrationEngine::Impl::held_pending() const {
  for (int i = 0; i < estimate.num_params(); ++i)
    if (!param_converged[i] && is_held(i)) return i;
  return -1;
}

// The best of the rule candidates `cands` for parameter `param` and, if `views` is given, the
// views' shortlist (less the views skipped since the last keyframe), by the candidate score
// (choose_candidate). Returns its index: < cands.size() a rule candidate, else
// cands.size() + its position in *shortlisted. *pick_var: its predicted variance of `param`.
size_t CalibrationEngine::Impl::pick_candidate(int param, const std::vector<TargetPose>& cands, ViewCandidates* views,
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
ViewCandidates CalibrationEngine::Impl::view_candidates() {
  grow_view_pool(opt.view_candidates, opt.view_candidates);
  view_pool_used = std::move(view_pool);
  view_pool.clear();
  view_rng.seed(0x5eed0000u + keyframes.size());
  return screen_views(view_pool_used);
}

ViewCandidates CalibrationEngine::Impl::screen_views(const std::vector<ViewPose>& pool) const {
  ViewCandidateOptions vo;
  vo.count = opt.view_candidates;
  vo.margin_px = view_margin_px();
  vo.shortlist = kExactViews;
  return ViewCandidates(estimate, board, scoring_fixed, information, gram, pool, vo);
}

double CalibrationEngine::Impl::view_margin_px() const {
  return opt.posegen.border_margin_fraction * std::max(size.width, size.height);
}

// Draws up to `n` more views into the pool, up to `pool_size` in all, under the current estimate
// (ViewSampler: tilt up to 40 deg, 40-80% of the width, anywhere the whole board fits).
// process() draws kViewsPerFrame per frame while a target choice is ahead, so the choice itself
// only screens them (docs/pose-selection.md, "Generic view candidates"). At most 200 draws per
// view: an estimate under which the board rarely fits yields fewer views, not a long search.
void CalibrationEngine::Impl::grow_view_pool(int n, int pool_size) {
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

// Predicted covariance of the free intrinsics after capturing `t` (Sigma_p = I), exact at the
// linearisation point (docs/math.md).
Eigen::MatrixXd CalibrationEngine::Impl::predicted_covariance(const TargetPose& t) const {
  const Eigen::MatrixXd info =
      information + frame_information(estimate, t.T_cam_board, board.corners(), scoring_fixed);
  return info.ldlt().solve(Eigen::MatrixXd::Identity(info.rows(), info.cols()));
}

// Position of `param` among the free intrinsics, -1 if it is fixed.
int CalibrationEngine::Impl::free_position(int param) const {
  const std::vector<bool>& fixed = scoring_fixed;
  if (fixed[param]) return -1;
  return static_cast<int>(std::count(fixed.begin(), fixed.begin() + param, false));
}

// Predicted variance of parameter `param` after capturing `t`.
double CalibrationEngine::Impl::predicted_variance(int param, const TargetPose& t) const {
  const int k = free_position(param);
  return k < 0 ? 0.0 : predicted_covariance(t)(k, k);
}

// Expected squared projection error over the image after capturing `t`: trace(G Sigma'), the
// expected eps_gt^2 up to the noise variance (docs/pose-selection.md).
double CalibrationEngine::Impl::predicted_projection(const TargetPose& t) const {
  return (gram * predicted_covariance(t)).trace();
}

void CalibrationEngine::Impl::prepare_scoring() {
  scoring_fixed = basis().fixed;
  if (held_pending() >= 0 && result && !prior && result->poses.size() == keyframes.size()) {
    // The held parameters freed: the keyframes' information (each frame's Schur complement onto
    // the intrinsics, as the calibration's own covariance is made) plus a weak prior on the held
    // ones, whose direction the keyframes leave (nearly) undetermined. Here the prior is relative
    // (1 / kHeldPriorStd^2 at unit noise: a standard deviation of kHeldPriorStd times the noise
    // in px), where held_covariance() and the expected error take it absolute; the scores only
    // rank candidates against each other. The absolute scale chose worse on the wide camera's
    // tuning seeds (changed 10 and 8 of 20 sessions, 7 and 6 of them worse: docs/math.md).
    information = information_with_held(*result, keyframes, 1.0 / (kHeldPriorStd * kHeldPriorStd),
                                        &scoring_fixed);
  } else {
    information = intrinsics_information(basis());
  }
  // 8x5 rays: the same choices as 16x9 in 46 of 48 closed-loop runs (24 benchmark cameras), at a
  // quarter of the cost (docs/performance.md).
  if (opt.candidate_score == EngineOptions::CandidateScore::kProjection)
    gram = projection_gram(estimate, scoring_fixed, 8, 5);
}

// A new target for the same parameter (skipped or timed-out target).
TargetPose CalibrationEngine::Impl::next_pose(int param) {
  if (opt.pose_candidates <= 1 || (!result && !prior)) return posegen.next_pose(param, estimate);
  prepare_scoring();
  if (opt.view_candidates > 0) {
    // Rule candidates and views together, as for a new target; a skipped view is not offered
    // again until the next keyframe (a skipped rule pose has used its sequence element or
    // region already).
    if (target && target->kind == TargetKind::kView) skipped_views.push_back(target->T_cam_board);
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

}  // namespace posecal
