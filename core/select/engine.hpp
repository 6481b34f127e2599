// The calibration engine: efficient pose selection (paper §3-§4) as an explicit state machine
// fed one frame at a time. It knows nothing of where frames come from.
//
//   WaitingForBoard --board seen--> Bootstrapping --focal-only fit ok--> InitialPose1
//   WaitingForBoard --board seen, with a prior (CalibrationOptions::prior)--> Refining
//   InitialPose1 --keyframe 1--> InitialPose2 --keyframe 2 + calibration--> Refining(param)
//   Refining --keyframe, all converged--> Converged
//   Refining --keyframe cap reached--> Failed (result kept, reported as not converged)
//   any state --fatal error, or give_up() (no board within board_timeout_s)--> Failed
// A keyframe the calibration rejects (degenerate) is dropped and the same target stays.
// docs/pose-selection.md draws this with every transition and its event.
#pragma once

#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "board/board.hpp"
#include "board/tracking.hpp"
#include "calib/calibration.hpp"
#include "calib/expected_error.hpp"
#include "device/camera.hpp"
#include "select/pose_rules.hpp"

namespace posecal {

enum class EngineState {
  kWaitingForBoard,
  kBootstrapping,
  kInitialPose1,
  kInitialPose2,
  kRefining,
  kConverged,
  kFailed,
};
const char* engine_state_name(EngineState s);
// The state of a name engine_state_name gives; false for an unknown name.
bool engine_state_from_name(const std::string& name, EngineState* s);

// What a journal keeps of one keyframe so that the engine can be rebuilt from it
// (CalibrationEngine::restore): the detection, the state and target it was captured in, and
// what the engine concluded after it.
struct KeyframeRecord {
  Observation observation;
  EngineState state_before = EngineState::kInitialPose1;  // the state it was captured in
  int target_param = -1;                   // the parameter it was captured for (-1: initial)
  EngineState state_after = EngineState::kInitialPose2;
  std::vector<double> estimate_after;      // the intrinsics after it (bit for bit)
  std::vector<bool> converged_after;       // per parameter
  std::string failure;                     // state_after kFailed: why
};

struct EngineOptions {
  // A named method: the members it sets (pose_candidates, prospective_convergence,
  // measured_convergence, convergence_measure, view_candidates, view_must_serve_target,
  // candidate_score, posegen.pinhole_fill) come from it; set_method() applies it, and members set
  // afterwards override it (the session key "method" is applied before every other key).
  //   kPosecal       posecal's engine, these members' defaults below (docs/pose-selection.md)
  //   kPaper         the paper's method: one rule pose per target, the variance ratio test on
  //                  captured keyframes only, boards at the reference code's distance
  //   kReferenceStd  kPaper with the reference implementation's std ratio test
  enum class Method { kPosecal, kPaper, kReferenceStd } method = Method::kPosecal;
  void set_method(Method m);
  BoardSpec board;                     // the board
  double convergence_threshold = 0.1;    // ratio test: relative variance reduction (paper §4.1)
  int max_keyframes = 20;                // cap; reaching it ends the run as not converged
  double constraint_factor = 5.0;        // constraints >= factor x unknowns (paper §4.3)
  double still_motion_px = 1.5;          // mean corner motion between frames (paper §4.3)
  double jaccard_threshold = 0.8;        // target reached (paper §4.2)
  bool robot = false;                    // robot mode: the host reports "pose reached"
  // > 0: skip a refinement target after this many frames; an initial pose is offered anew (the
  // tilted one less tilted, PoseGenerator::initial_pose)
  int target_timeout_frames = 0;
  int bootstrap_min_corners = 0;         // 0: half the board's corners (reference implementation)
  // A bootstrap is accepted only if its focal length is determined to this relative standard
  // deviation (at the measured noise, at least 0.1 px); among accepted ones the lowest residual
  // wins (paper §3.4). A nearly
  // fronto-parallel view fits any focal length with a low residual, so the residual alone would
  // prefer exactly the views that cannot tell f (docs/pose-selection.md).
  double bootstrap_max_relative_std = 0.05;
  // ... and only if moving the assumed principal point by 5% of the image changes f by less than
  // this fraction (a weak view turns the unknown principal point into a biased f).
  double bootstrap_max_pp_sensitivity = 0.2;
  double initial_focal_guess = 0.0;      // f before any estimate; 0: max(width, height)
  // Refinement targets: 1 = the paper's rule (next sequence element / most distorted region);
  // n > 1 = the best of the first n rule-generated candidates by predicted variance of the
  // targeted parameter (docs/pose-selection.md).
  int pose_candidates = 6;
  // How the candidates are compared: kProjection = the lowest expected projection error over the
  // whole image after the pose (trace(G Sigma'), see projection_gram()); kParameterVariance =
  // the lowest predicted variance of the targeted parameter. The prospective test uses the
  // targeted parameter's predicted variance after the chosen candidate (docs/pose-selection.md).
  enum class CandidateScore { kProjection, kParameterVariance } candidate_score = CandidateScore::kProjection;
  // Generic board views scored alongside the rule candidates (default 300; 0 = the paper's pose
  // families only): this many random views with the whole board in view (tilt up to
  // 40 degrees about any in-plane axis, 40-80% of the image width, anywhere in the image, the
  // pose generator's border margin), drawn 100 per frame in the frames before a choice (seeded by
  // the keyframe count), screened cheaply, the best few scored exactly. The best score wins, view
  // or rule candidate, also when a skipped target is replaced (docs/pose-selection.md, "Generic
  // view candidates").
  int view_candidates = 300;
  // With view candidates: a view may win only if it would also reduce the targeted (MaxIOD)
  // parameter's variance at least as much as the best rule candidate does. Off by default:
  // measured, the free choice needs fewer keyframes for the same accuracy (docs/benchmarks.md).
  bool view_must_serve_target = false;
  // Ratio test measure: kVariance = 1 - sigma'^2 / sigma^2 (paper §4.1); kStd = 1 - sigma' /
  // sigma (the reference implementation; at 10% it equals a 19% variance reduction). kStd with
  // the view candidates is the default since 2026-12-02: 7 keyframes instead of 11 for the same
  // accuracy, better in 9 of the benchmark's 11 worlds (docs/benchmarks.md).
  enum class ConvergenceMeasure { kVariance, kStd } convergence_measure = ConvergenceMeasure::kStd;
  // Before capturing a pose for a parameter, predict the ratio test: if even the best pose the
  // rules generate for it would reduce its variance by less than the threshold, the parameter
  // converges without that keyframe (docs/pose-selection.md).
  bool prospective_convergence = true;
  // The paper's ratio test on the keyframe just captured. Off: parameters converge only
  // prospectively (needs prospective_convergence), i.e. by what the best pose the rules can
  // generate would add, not by what an imperfectly reached pose did add.
  bool measured_convergence = true;
  // The stop rule in pixels: converged when the expected projection error (expected_error(),
  // at the measured noise) is at most this; the targets then go to the intrinsic that holds it
  // back and the ratio test stops nothing. Unset: the ratio test (paper §4.1).
  std::optional<double> accuracy_px;
  // With the ratio test (accuracy_px unset): "every parameter converged" is not accepted while
  // the expected error's 90th percentile is above this many pixels (or not a number); the
  // parameter that holds it back (ExpectedError::limiting_param) is opened again and targeted,
  // and a run that reaches the keyframe cap so ends as failed, naming the figure. The ratio test
  // stops when the keyframes stop teaching, which a degenerate model (seen: the rational model's
  // common factor on a 110-degree lens, "converged" at 5 keyframes with a p90 of 50 px and a
  // realised error of 5 px) reaches long before it is determined (docs/pose-selection.md,
  // "A ceiling on the ratio test's stop"). 0: off (the paper's methods).
  double ratio_stop_max_p90_px = 5.0;
  // A session (session/session.hpp, not the engine itself, which has no clock) ends as failed
  // when no board has been seen for this many seconds of wall time: since the first frame, the
  // last frame showing the board (>= 4 corners) or the camera's return after a disconnect. 0:
  // never. Wall time, not frames: what it bounds is how long a station waits for a camera, and
  // frame rates differ between cameras (and are unknown for fed frames and image folders).
  double board_timeout_s = 120;
  PoseGenOptions posegen;
  // calibration.lens_model is the lens model calibrated. With auto_lens_model it is only the
  // first: after every keyframe's calibration the engine also fits each model of the lens table
  // to the keyframes and moves to the one with the lowest Bayesian information criterion once it
  // beats the current one by kLensSwitchMargin (kFamilySwitchMargin between the pinhole and the
  // fisheye family, which the bootstrap chooses) (docs/pose-selection.md, "Automatic lens model");
  // the targets then serve the model chosen. lens_candidates() gives the evidence.
  CalibrationOptions calibration;
  bool auto_lens_model = false;
  // The session key "lens_model": a model of the table, or "auto" (auto_lens_model).
  struct LensModelKey {
    LensModel& model;
    bool& automatic;
  };
  struct ConstLensModelKey {
    const LensModel& model;
    const bool& automatic;
  };
  LensModelKey lens_model_key() { return {calibration.lens_model, auto_lens_model}; }
  ConstLensModelKey lens_model_key() const { return {calibration.lens_model, auto_lens_model}; }
  DetectorOptions detector;
  // While the operator moves the board to a target, search it around where it was in the last
  // frame, on a shrunk copy when its markers are large (core/board/tracking.hpp): a third of the
  // CPU of a whole-frame search per 1280x720 frame (docs/performance.md). Whenever that finds
  // fewer corners than the last frame, every 15 frames, before the first target and for every
  // keyframe the whole frame is searched, so keyframes are what tracking off would measure.
  bool track_board = true;
  bool is_valid(std::string* error) const;
};

// One lens model's fit to the keyframes, the evidence of the automatic model choice
// (EngineOptions::auto_lens_model).
struct LensCandidate {
  LensModel model = LensModel::kOpenCV5;
  bool fitted = false;
  std::string failure;  // why it could not be fitted (!fitted)
  double rms_px = 0;
  int free_intrinsics = 0;  // held and fixed ones excluded
  int residuals = 0;        // 2 per corner
  // Bayesian information criterion of the corners, N ln(SSR / N) + k ln N with N residuals and
  // k free intrinsics (the board poses are common to every candidate and left out): lower is
  // better; a difference above 10 is very strong evidence (Kass and Raftery 1995).
  double bic = 0;
  double expected_error_px = -1;
  std::vector<std::string> held;
};
// The BIC lead a lens model needs over the current one before the engine moves to it: within a
// family (OpenCV's models, or the fisheye), and across (the bootstrap chose the family).
inline constexpr double kLensSwitchMargin = 10.0;
inline constexpr double kFamilySwitchMargin = 100.0;

struct FrameReport {
  uint64_t frame_index = 0;
  EngineState state = EngineState::kWaitingForBoard;
  bool board_visible = false;
  int corners = 0;
  int corners_required = 0;   // for a keyframe now (paper §4.3 heuristic)
  bool pose_estimated = false;
  double jaccard = -1;        // -1 when no target or no pose
  bool still = false;
  double motion_px = -1;      // mean corner motion since the previous frame, -1 if not comparable
  bool pose_reached = false;
  bool captured = false;
  int keyframes = 0;
  std::string target_parameter;  // "" during initialisation and after the end
  std::string guidance;          // what the person should do now
};

struct EngineEvent {
  enum class Kind {
    kStateChanged,        // from -> to
    kCaptured,            // a keyframe was taken
    kKeyframeRejected,    // the calibration could not use it (message says why)
    kCalibrated,          // recalibrated after a keyframe
    kParameterConverged,  // `parameter` converged
    kParameterReopened,   // `parameter` is no longer converged (message says why)
    kTargetChanged,       // a new target pose (note says what was adjusted)
    kTargetSkipped,       // target not reached within target_timeout_frames
    kError,               // a problem worth reporting that did not stop the engine
  };
  explicit EngineEvent(Kind k) : kind(k) {}
  Kind kind;
  EngineState from = EngineState::kWaitingForBoard;
  EngineState to = EngineState::kWaitingForBoard;
  int keyframes = 0;
  std::string parameter;
  std::string message;
};
const char* engine_event_name(EngineEvent::Kind k);

struct ParameterStatus {
  std::string name;
  double value = 0;
  double std = -1;       // scaled by the residual variance (honest); -1 before calibration
  double std_unit = -1;  // Sigma_p = I (paper eq. 5)
  double index_of_dispersion = -1;
  bool converged = false;
  int targeted = 0;      // keyframes captured for this parameter
};

// Which candidate pose to capture, given each candidate's score (lower is better) and the
// targeted parameter's predicted variance after it: the best-scored of the rule candidates
// [0, n_rule), replaced by a generic view [n_rule, size) that scores lower — with
// `must_serve_target`, only by a view that also leaves the targeted parameter's variance no higher
// than the rule pick does (EngineOptions::view_candidates, view_must_serve_target). Ties keep the
// earlier candidate. Throws Error(kInvalidArgument) on inconsistent sizes or no rule candidate.
size_t choose_candidate(const std::vector<double>& score, const std::vector<double>& target_var, size_t n_rule,
                        bool must_serve_target);

// The ratio test (paper §4.1) after a keyframe captured for parameter `targeted`: returns the
// parameters of the targeted parameter's group that converge, given each parameter's variance
// before and after the keyframe. `group_keyframes` counts the refinement keyframes captured per
// group (pinhole, distortion) including this one: a parameter other than the target converges
// only once its group has had two keyframes of its own strategy (docs/pose-selection.md).
std::vector<int> ratio_test(const std::vector<double>& var_before, const std::vector<double>& var_after,
                            int targeted, const std::vector<bool>& converged, const int group_keyframes[2],
                            double threshold, EngineOptions::ConvergenceMeasure measure);

class CalibrationEngine {
 public:
  CalibrationEngine(cv::Size image_size, const EngineOptions& options = {});
  ~CalibrationEngine();
  CalibrationEngine(const CalibrationEngine&) = delete;
  CalibrationEngine& operator=(const CalibrationEngine&) = delete;

  // Processes one frame (8-bit grey or BGR, the engine's image size) and advances the state
  // machine. Throws Error(kInvalidArgument) for an image of the wrong size or type.
  FrameReport process(const cv::Mat& image);

  // Robot mode: the host says the robot has reached the current target; the next still frame
  // with enough corners is captured. Error(kState) outside the initial/refining states.
  void report_pose_reached();
  // Gives up on the current refinement target and generates the next one.
  void skip_target();
  // Ends the run as failed with `why` as the failure reason, in any state but the final ones
  // (Error(kState) there); a calibration already made is kept (reported as not converged).
  void give_up(const std::string& why);

  EngineState state() const;
  const std::string& failure_reason() const;
  int keyframes() const;
  bool converged() const { return state() == EngineState::kConverged; }
  // The current target (none while waiting for the board and after the end).
  const std::optional<TargetPose>& target() const;
  int target_parameter() const;  // index, -1 if none
  // Current intrinsics: the initial guess, then the bootstrap, then the calibration.
  const CameraModel& estimate() const;
  // The last full calibration (nullptr before the second keyframe).
  const CalibrationResult* result() const;
  // Its expected projection error (calib/expected_error.hpp; nullptr before the second keyframe).
  const ExpectedError* expected_error() const;
  // With EngineOptions::auto_lens_model: every table model's fit at the last calibration, in
  // table order (empty before the first calibration and without auto_lens_model).
  const std::vector<LensCandidate>& lens_candidates() const;
  std::vector<ParameterStatus> parameters() const;
  const std::vector<Observation>& keyframe_observations() const;
  // The record of keyframe i (0-based) as the engine stands now: call it right after the
  // process() that captured it, as the session's journal does.
  KeyframeRecord keyframe_record(int i, EngineState state_before) const;
  // Rebuilds the engine from journalled keyframes (in order) before any frame is processed:
  // each calibration is recomputed with the same warm starts, so the last one equals the one
  // before the journal was cut bit for bit (returns whether it does: the recomputed intrinsics
  // equal the last record's estimate_after), then the convergence flags and the state are
  // taken from the last record and the next target is chosen. Events are not emitted while
  // restoring. Error(kState) after a frame was processed, kInvalidArgument for records that do
  // not fit the engine (parameter counts, states).
  bool restore(const std::vector<KeyframeRecord>& records);
  const FrameReport& last_report() const;
  // How the frames' boards were searched (EngineOptions::track_board): tracked, the whole frame
  // after a tracked search found fewer corners, the whole frame only.
  const BoardTracker::Counts& board_search_counts() const;
  const Board& board() const;
  const EngineOptions& options() const;
  // What a guided camera (simulated operator) needs.
  GuidanceInfo guidance_info() const;

  // Draws the guidance overlay into an 8-bit grey or BGR image of the engine's size: the target
  // board projected with the current intrinsics and distortion, the detected corners, the text.
  void draw_overlay(cv::Mat& image) const;

  void set_event_callback(std::function<void(const EngineEvent&)> cb);

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace posecal
