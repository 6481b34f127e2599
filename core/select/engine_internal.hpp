// Internal to select/: the engine's state, shared by the files that implement it:
//   engine.cpp        the state machine: frames in, states, keyframe capture, recalibration
//   restore.cpp       keyframe records for the session journal, and the engine rebuilt from them
//   bootstrap.cpp     the single-view focal-length fit before the first target (paper §3.4)
//   convergence.cpp   the ratio test and the prospective test (paper §4.1)
//   target_choice.cpp MaxIOD and the choice of the next target among rule poses and views
//   guidance.cpp      what the operator is told, and what a guided camera is given
//   overlay.cpp       the drawing of the target over the camera image
//   lens_choice.cpp   the automatic lens model (EngineOptions::auto_lens_model)
#pragma once

#include <limits>
#include <optional>
#include <random>
#include <string>
#include <vector>

#include "board/tracking.hpp"
#include "calib/expected_error.hpp"
#include "select/engine.hpp"
#include "select/view_candidates.hpp"

namespace posecal {

struct CalibrationEngine::Impl {
  cv::Size size;
  EngineOptions opt;
  Board board;
  PoseGenerator posegen;
  std::function<void(const EngineEvent&)> callback;

  EngineState state = EngineState::kWaitingForBoard;
  std::string failure;
  CameraModel estimate;  // current intrinsics
  double best_bootstrap_rms = std::numeric_limits<double>::infinity();  // relative std of f
  bool have_bootstrap = false;
  // Distinct views seen while no single one could bootstrap (most recent last), fitted jointly;
  // and what the operator should change (empty: nothing known yet).
  std::vector<Observation> bootstrap_views;
  std::string bootstrap_hint;
  std::optional<TargetPose> target;
  int target_param = -1;
  uint64_t target_serial = 0;
  uint64_t target_since_frame = 0;
  int initial_retries = 0;  // initial poses offered again after a timeout (this initial pose)
  // The last frame's view was given to the bootstrap fit (or was a still copy of one that was):
  // a still board shows it again and is not fitted again.
  bool bootstrap_view_fitted = false;

  std::vector<Observation> keyframes;
  std::vector<int> keyframe_target;  // parameter each keyframe was captured for (-1: init)
  std::optional<CalibrationResult> result;
  // With a prior (CalibrationOptions::prior): what it alone says (prior_result), the basis of
  // the first target and of the first keyframe's ratio test.
  std::optional<CalibrationResult> prior;
  std::optional<ExpectedError> prior_expected;  // of `prior`
  // The calibration targets are chosen with: the last one, else the prior's.
  const CalibrationResult& basis() const { return result ? *result : *prior; }
  std::optional<ExpectedError> expected;  // of `result`
  Eigen::MatrixXd information;  // marginal information of the free intrinsics (scoring)
  // The intrinsics `information` and `gram` are over: the calibration's free ones, and while a
  // held parameter is targeted (held_pending) the held ones too, under a weak prior
  // (kHeldPriorStd): a candidate is then scored by how well it would determine them.
  std::vector<bool> scoring_fixed;
  Eigen::MatrixXd gram;         // projection_gram() of the estimate (projection scoring)
  // EngineOptions::view_candidates: the pool for the next choice, drawn frame by frame, and the
  // pool of the last choice (for replacing skipped targets).
  std::vector<ViewPose> view_pool, view_pool_used;
  std::mt19937_64 view_rng{0x5eed0000u};
  std::vector<Pose> skipped_views;  // view targets skipped since the last keyframe
  std::vector<bool> param_converged;
  std::vector<int> param_targeted;
  int group_keyframes[2] = {0, 0};  // refinement keyframes captured per parameter group
  // Refinement keyframes aimed at a parameter the calibration held because the keyframes did not
  // determine it (CalibrationResult::held). A held parameter is not converged: its value is a
  // guess the covariance, and with it expected_error_px, knows nothing of (seen: a rational lens
  // "converged" with k5 held at 0, eps_gt 7.5 px against an expected 0.52 px). It is targeted
  // first, until kHeldKeyframeLimit keyframes aimed at held parameters leave it still held; then
  // it converges as held, and the event says so.
  int held_keyframes = 0;
  static constexpr int kHeldKeyframeLimit = 3;
  bool is_held(int param) const;  // held in the calibration targets are chosen with
  int held_pending() const;       // the first held, unconverged parameter; -1 if none

  Detection previous;
  BoardTracker tracker;  // EngineOptions::track_board
  bool robot_reached = false;
  int crowded_frames = 0;  // consecutive still frames at the target with too few corners
  static constexpr int kCrowdedFrames = 3;
  uint64_t frame_index = 0;
  FrameReport last;

  Impl(cv::Size s, const EngineOptions& o);

  // --- engine.cpp: the state machine ---
  void emit(EngineEvent e);
  void set_state(EngineState s, const std::string& message = "");
  void fail(const std::string& why);
  void set_target(TargetPose t, int param);
  // Points needed per keyframe so that constraints >= factor x unknowns (paper §4.3).
  int corners_required() const;
  FrameReport process(const cv::Mat& image);
  // process() in steps.
  void measure_stillness(const Detection& det, FrameReport* r);
  void bootstrap_step(const Detection& det, const FrameReport& r);
  std::optional<Pose> current_pose(const Detection& det, FrameReport* r) const;
  void capture_step(const cv::Mat& image, const Detection& det, FrameReport* r);
  // The frame's board: tracked while the operator moves it to a target, else searched whole.
  Detection detect(const cv::Mat& image);
  void move_target_back(int corners);
  // The target after one that timed out (EngineOptions::target_timeout_frames): `what` says how
  // ("not reached", ...).
  void skip_timed_out_target(const std::string& what);
  void capture(const Detection& det);
  void after_calibration();
  // Recalibrates with the keyframes; false (keyframe dropped, event emitted) if it is rejected.
  bool recalibrate();
  std::vector<size_t> outlier_corners(const CalibrationResult& r,
                                      const std::vector<Observation>& frames, size_t frame) const;
  void start_from_prior();
  bool scoring() const { return opt.pose_candidates > 1 || opt.prospective_convergence; }

  // --- lens_choice.cpp: EngineOptions::auto_lens_model ---
  std::vector<LensCandidate> lens_evidence;                 // of the last calibration
  std::vector<std::optional<CalibrationResult>> lens_fits;  // per table model, its last fit
  // Fits every table model to the keyframes beside *now (the current model's) and moves to the
  // one with the lowest BIC if it leads by kLensSwitchMargin: *now becomes its fit, the
  // per-parameter state follows by name. Returns the event's text ("" if it stays).
  std::string choose_lens_model(CalibrationResult* now);
  // Makes `to` the lens model calibrated; the per-parameter state follows by name.
  void move_to_lens_model(LensModel to);

  // --- bootstrap.cpp ---
  int bootstrap_min_corners() const;
  bool try_bootstrap(const Detection& det);
  // Fits the focal lengths to `views` (principal point at the centre, no distortion); true and
  // the estimate replaced if it determines f and beats the best so far.
  bool fit_bootstrap(const std::vector<Observation>& views);
  bool remember_bootstrap_view(const Observation& view);

  // --- convergence.cpp ---
  // Relative reduction as the ratio test measures it (0 if there was no variance).
  double reduction(double var_before, double var_after) const;
  void mark_converged(int i, const std::string& why);
  bool all_converged() const;
  // Ratio test (paper §4.1) on the parameters of the targeted parameter's group.
  void update_convergence(const CalibrationResult& prev, const CalibrationResult& now, int tgt);
  // The prospective test: true (and the parameter converged) if even the pose about to be requested
  // would reduce its variance by less than the threshold.
  bool converges_prospectively(int param, double predicted_variance);
  // With accuracy_px, after each calibration: converged, failed at the keyframe cap, or the next
  // target for the intrinsic that holds the expected error back.
  void continue_towards_accuracy();
  std::string accuracy_shortfall() const;  // why the cap ended an accuracy_px session
  // The ratio test's stop above EngineOptions::ratio_stop_max_p90_px: true if the stop is
  // refused (the limiting parameter opened again and targeted, or the cap reached).
  bool reopen_above_ceiling();
  std::string ceiling_shortfall() const;  // why the cap ended such a session

  // --- target_choice.cpp ---
  void choose_refinement_target();
  void choose_accuracy_target();
  // The best candidate for `param`: rule candidates and, if `views`, the views' shortlist,
  // compared by the candidate score if `scoring` (else the first rule candidate).
  struct CandidatePick {
    std::vector<TargetPose> rules;
    std::vector<ViewCandidates::Exact> shortlisted;
    size_t pick = 0;  // < rules.size(): a rule candidate, else rules.size() + shortlist position
    double variance = std::numeric_limits<double>::infinity();  // of `param` after it
  };
  CandidatePick best_candidate(int param, ViewCandidates* views, bool scoring);
  void set_picked_target(const CandidatePick& p, int param);
  int max_iod_parameter() const;
  size_t pick_candidate(int param, const std::vector<TargetPose>& cands, ViewCandidates* views,
                        std::vector<ViewCandidates::Exact>* shortlisted, double* pick_var) const;
  ViewCandidates view_candidates();
  ViewCandidates screen_views(const std::vector<ViewPose>& pool) const;
  double view_margin_px() const;
  void grow_view_pool(int n, int pool_size);
  Eigen::MatrixXd predicted_covariance(const TargetPose& t) const;
  int free_position(int param) const;
  double predicted_variance(int param, const TargetPose& t) const;
  double predicted_projection(const TargetPose& t) const;
  void prepare_scoring();
  TargetPose next_pose(int param);
  static constexpr int kViewsPerFrame = 100;
  // The frames draw this many times view_candidates: a view drawn under the previous estimate
  // may not fit under the next one, and the choice takes the first view_candidates that do.
  static constexpr int kPoolFactor = 2;
  // Views predicted exactly per target: of 300 screened views the exact best was among the 8
  // best screened in 97% of 168 choices and among the 16 best in 99.4% (explore_information
  // --screening; docs/math.md); in closed loop, scoring all exactly changed no median.
  static constexpr int kExactViews = 12;

  // --- guidance.cpp ---
  std::string guidance_text(const FrameReport& r, const std::optional<Pose>& current) const;
  std::string alignment_hint(const Pose& current) const;
};

// "12.3%".
std::string percent_text(double fraction);

// Why an estimate that folds inside the image cannot stop, as every message about it says it.
std::string fold_text(const ExpectedError& e);

// The relative variance reduction the ratio test measures (var_before > 0): 1 - var'/var, or
// 1 - sigma'/sigma for kStd.
double variance_reduction(double var_before, double var_after, EngineOptions::ConvergenceMeasure measure);

}  // namespace posecal
