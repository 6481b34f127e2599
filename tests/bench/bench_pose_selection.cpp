// Pose selection vs random poses, side by side on the same sampled cameras (docs/benchmarks.md).
//
//   build/bin/bench_pose_selection [--cameras N] [--camera c525|industrial|tele|longfocal|vga]
//       [--threads T] [--config NAME[,NAME...]] [--distortion-tilt DEG] [--max-tilt DEG]
//       [--score variance|projection] [--accuracy-px PX] [--max-keyframes N] [--csv FILE]
//       [--figure3 FILE.png]
//       [--world camera=C,operator=O,noise=N,renderer=R]... [--worlds standard]
//       [--seeds tune|report|FIRST-LAST] [--robot] [--compactness] [--random-match N]
//
// Per camera (seed i): the camera is sampled around the reference with 10% std per parameter
// (paper §5.1); pose selection runs closed-loop with a simulated person (and a simulated robot);
// the baselines calibrate with cv::calibrateCamera from 10 and 20 random well-spread poses
// (board fully visible, tilt up to 45 deg) rendered by the same synthetic camera with the same
// noise. Every method is scored on the same fixed 50-frame test set (eps_test) and against the
// ground truth (eps_gt).
//
// Without --world/--worlds: one world, the camera family of --camera, today's person
// ("approach"), noise 2 grey levels and blur 0.8 px, the ray-casting renderer, seeds 1..N, and
// the robot; the tables of docs/benchmarks.md up to 2026-12-02.
// With worlds: each world is a camera family, an operator (sim/operator.hpp presets), a noise
// level and a renderer (sim/synthetic.hpp); every configuration of --config runs on the same
// cameras and operator draws, so methods compare paired; eps_gt is the edge-to-edge grid's mean
// (corners included). Seeds: "tune" = 1..30 (what the engine may be tuned on), "report" =
// 1001..1100 (what docs/benchmarks.md reports; never tuned on). --compactness runs the paper's
// compactness test (§5.3) on every session's keyframes against its test set; --random-match N
// counts the random views (up to N) OpenCV needs to reach each session's realised eps_gt.
#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <map>
#include <mutex>
#include <opencv2/calib3d.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <random>
#include <sstream>
#include <string>
#include <thread>
#include <tuple>
#include <vector>

#include "board/views.hpp"
#include "calib/compactness.hpp"
#include "calib/information.hpp"
#include "calib/metrics.hpp"
#include "camera_families.hpp"
#include "lens/reference_models.hpp"
#include "session/session.hpp"
#include "sim/sim_camera.hpp"

using namespace posecal;

namespace {

struct Options {
  int cameras = 20;
  std::string camera = "c525";
  int threads = 2;
  std::vector<std::string> configs = {"default"};  // default | default-std | paper | std | ...
  std::string csv;
  std::string figure3;
  int figure3_cameras = 20;
  int first_seed = 1;
  bool robot = true;
};

// One world of the benchmark: what the engine is tested against.
struct World {
  std::string camera = "c525";
  std::string op = "approach";   // an operator_preset name
  std::string noise = "std";     // clean | std | noisy | webcam
  Renderer renderer = Renderer::kRayCast;
  std::string name() const {
    return camera + "/" + op + "/" + noise + "/" + (renderer == Renderer::kWarp ? "warp" : "raycast");
  }
};

const char* const kNoiseLevels = "clean, std, noisy, webcam";

// Noise levels: grey-level noise, optics blur, contrast. "webcam" is tuned so that eps_res is
// about 0.3 px as on real webcams (docs/benchmarks.md).
void apply_noise(const std::string& level, RenderOptions* ro) {
  if (level == "clean") {
    ro->noise_sigma = 0.5;
    ro->blur_sigma_px = 0.5;
  } else if (level == "std") {
    ro->noise_sigma = 2.0;
    ro->blur_sigma_px = 0.8;
  } else if (level == "noisy") {
    ro->noise_sigma = 8.0;
    ro->blur_sigma_px = 1.2;
  } else if (level == "webcam") {
    ro->noise_sigma = 10.0;
    ro->blur_sigma_px = 1.5;
    ro->paper_white = 190;
    ro->ink_black = 60;
  } else {
    throw Error(ErrorCode::kInvalidArgument, "unknown noise level '" + level + "' (" + kNoiseLevels + ")");
  }
}

World parse_world(const std::string& text) {
  World w;
  std::stringstream ss(text);
  std::string item;
  while (std::getline(ss, item, ',')) {
    const size_t eq = item.find('=');
    const std::string k = item.substr(0, eq), v = eq == std::string::npos ? "" : item.substr(eq + 1);
    if (k == "camera") w.camera = v;
    else if (k == "operator") w.op = v;
    else if (k == "noise") w.noise = v;
    else if (k == "renderer" && (v == "raycast" || v == "warp")) w.renderer = v == "warp" ? Renderer::kWarp : Renderer::kRayCast;
    else throw Error(ErrorCode::kInvalidArgument, "--world: bad item '" + item + "' (camera=, operator=, noise=, renderer=raycast|warp)");
  }
  reference_camera(w.camera);
  operator_preset(w.op);
  RenderOptions ro;
  apply_noise(w.noise, &ro);
  return w;
}

// The standard worlds: the base world (C525 family, hold-only person, today's noise, ray
// casting) and one axis changed at a time.
std::vector<World> standard_worlds() {
  std::vector<World> out;
  const World base{"c525", "hold-only", "std", Renderer::kRayCast};
  out.push_back(base);
  for (const char* op : {"approach", "sloppy", "careless"}) {
    World w = base;
    w.op = op;
    out.push_back(w);
  }
  for (const char* n : {"clean", "noisy", "webcam"}) {
    World w = base;
    w.noise = n;
    out.push_back(w);
  }
  for (const char* c : {"industrial", "longfocal", "vga"}) {
    World w = base;
    w.camera = c;
    out.push_back(w);
  }
  World warp = base;
  warp.renderer = Renderer::kWarp;
  out.push_back(warp);
  return out;
}

struct Run {
  bool converged = false;
  int keyframes = 0;
  int frames = 0;
  double eps_test = NAN, eps_gt = NAN;
  // eps_gt with only the pinhole part (fx fy cx cy) or only the distortion part estimated, the
  // other part set to the truth: which group the remaining error comes from (--csv).
  double eps_gt_pinhole = NAN, eps_gt_distortion = NAN;
  // eps_gt predicted from the calibration's own covariance (scaled by its residual variance):
  // sqrt(mean over the 40x23 grid of trace(J Sigma J^T)), J = d projection / d intrinsics. It is
  // what eps_gt is in expectation over the image noise, without the one random draw each
  // calibration realises, so methods compare with far less spread (--csv, summary line).
  double eps_gt_predicted = NAN;
  // eps_gt over the edge-to-edge grid (corners included; mean distance), and the session's own
  // expected_error_px (an RMS over that grid): the stop figure of --accuracy-px.
  double eps_gt_edges = NAN, expected_error_px = NAN, expected_mean_px = NAN, expected_p90_px = NAN;
  // Of the expected error's 40x23 grid, the points whose ray exists under the estimate (fewer: the
  // estimated model folds inside the image and the figure leaves those points out).
  int expected_points = -1;
  // A fisheye world's eps_gt over the edge grid's pixels whose true ray lies within 80 degrees of
  // the axis: where cv::fisheye's baselines have data (random_observations).
  double eps_gt_inner = NAN;
  // eps_gt with the camera frame's rotation taken out (ground_truth_error_aligned): a tilted
  // sensor is a rotation plus a principal-point shift to first order, which plain eps_gt counts.
  double eps_gt_aligned = NAN;
  double eps_res = NAN;  // the calibration's residual RMS
  // How far the keyframes' corners reach (keyframe_reach): the largest corner radius about the
  // principal point over the largest image corner's, and the share of the edge grid's points
  // inside some keyframe's corner hull (the rest is extrapolated).
  double reach_radius = NAN, reach_hull = NAN;
  // --restarts: the same keyframes calibrated from the true model (same lens model only): its
  // residual RMS and eps_gt over the edge grid. Lower than eps_res: the session's solution is a
  // local minimum.
  double truth_start_rms = NAN, truth_start_eps_gt = NAN;
  // The same from a cold start (calibrate() without a warm start, as the engine's first solve).
  double cold_start_rms = NAN, cold_start_eps_gt = NAN;
  std::string lens_model;     // the model calibrated (config "auto": the one chosen)
  int bootstrap_frames = -1;  // frames until the engine had a first target (-1: never)
  // --compactness: keyframes the paper's greedy test keeps for the same eps_test (§5.3).
  int compact_kept = -1;
  double compact_eps_test = NAN, compact_eps_test_all = NAN;
  std::map<std::string, AttemptStats> attempts;
};

// Random views needed to reach a realised eps_gt (--random-match): the smallest prefix of one
// random view sequence whose OpenCV calibration is at least as accurate; 0 = not within the
// sequence.
struct RandomMatch {
  double target_eps_gt = NAN;
  int views = -1;  // -1: not measured
  int calibrations = 0;
};

struct CameraRuns {
  int seed = 0;
  Run person, robot, base10, base20;  // person and robot: the first configuration
  std::vector<Run> persons;           // the person with every configuration, in --config order
  RandomMatch match;                  // --random-match, against persons[0]
};

RenderOptions render_options(const World& w, uint64_t seed) {
  RenderOptions ro;
  apply_noise(w.noise, &ro);
  ro.renderer = w.renderer;
  ro.seed = seed;
  return ro;
}

// --distortion-tilt DEG: overrides PoseGenOptions::distortion_tilt_deg of any configuration.
double g_distortion_tilt_deg = -1;
double g_max_tilt_deg = -1;  // --max-tilt: the pinhole rule's tilt range
// --score variance|projection: overrides EngineOptions::candidate_score of any configuration.
std::string g_score;
int g_views = -1;  // --views N (>= 0): EngineOptions::view_candidates
bool g_serve = false;  // --views-serve-target: EngineOptions::view_must_serve_target
double g_accuracy_px = 0;  // --accuracy-px PX (> 0): EngineOptions::accuracy_px
int g_max_keyframes = 0;   // --max-keyframes N (> 0): EngineOptions::max_keyframes
bool g_compactness = false;  // --compactness: run the paper's compactness test on every session
bool g_restarts =
    false;  // --restarts: solve the final keyframes again from the truth and cold (--csv)
// --random-match N: per camera, how many random views (prefixes of one N-view sequence) OpenCV
// needs to reach the first configuration's realised eps_gt (the "keyframes needed").
int g_random_match = 0;

// Engine configurations compared in docs/benchmarks.md.
void apply_named_config(const std::string& config, EngineOptions* eo) {
  if (config == "default") return;
  if (config == "auto") {
    // The automatic lens model (issue 14): from opencv5, moved by the BIC (lens_choice.cpp).
    eo->auto_lens_model = true;
    eo->calibration.lens_model = LensModel::kOpenCV5;
    return;
  }
  if (config == "prospective" || config == "prospective-std") {
    // Convergence decided only by the predicted reduction of the best next pose.
    eo->measured_convergence = false;
    if (config == "prospective-std") eo->convergence_measure = EngineOptions::ConvergenceMeasure::kStd;
    return;
  }
  if (config == "std-views") {
    // The std ratio test with 300 generic view candidates per target choice: the default since
    // 2026-12-02, kept under its old name so earlier commands still run.
    eo->convergence_measure = EngineOptions::ConvergenceMeasure::kStd;
    eo->view_candidates = 300;
    return;
  }
  if (config == "default-std") {
    // posecal's engine with the std ratio test and rule poses only.
    eo->convergence_measure = EngineOptions::ConvergenceMeasure::kStd;
    eo->view_candidates = 0;
    return;
  }
  if (config == "variance" || config == "variance-views") {
    // The default until 2026-12-02 (the paper's variance ratio test, rule poses only), and the
    // variance test with the view candidates.
    eo->convergence_measure = EngineOptions::ConvergenceMeasure::kVariance;
    eo->view_candidates = config == "variance" ? 0 : 300;
    return;
  }
  // The session's methods (EngineOptions::set_method): the paper's rules, and with the
  // reference implementation's std test.
  if (config == "paper") return eo->set_method(EngineOptions::Method::kPaper);
  if (config == "std") return eo->set_method(EngineOptions::Method::kReferenceStd);
  throw Error(ErrorCode::kInvalidArgument,
              "unknown --config '" + config +
                  "' (default, auto, std-views, default-std, variance, variance-views, "
                  "prospective, prospective-std, paper, std)");
}

// The configuration, then the flags that override any configuration.
void apply_config(const std::string& config, EngineOptions* eo) {
  apply_named_config(config, eo);
  if (g_distortion_tilt_deg >= 0) eo->posegen.distortion_tilt_deg = g_distortion_tilt_deg;
  if (g_max_tilt_deg > 0) eo->posegen.max_tilt_deg = g_max_tilt_deg;
  if (g_score == "variance") eo->candidate_score = EngineOptions::CandidateScore::kParameterVariance;
  else if (g_score == "projection") eo->candidate_score = EngineOptions::CandidateScore::kProjection;
  else if (!g_score.empty()) throw Error(ErrorCode::kInvalidArgument, "unknown --score '" + g_score + "' (variance, projection)");
  if (g_views >= 0) eo->view_candidates = g_views;
  if (g_serve) eo->view_must_serve_target = true;
  if (g_accuracy_px > 0) eo->accuracy_px = g_accuracy_px;
  if (g_max_keyframes > 0) eo->max_keyframes = g_max_keyframes;
}

void split_eps_gt(const CameraModel& truth, const CameraModel& estimate, Run* r) {
  if (truth.lens_model() != estimate.lens_model()) return;  // (no split across models)
  CameraModel k_only = estimate, d_only = estimate;
  for (int i = 0; i < truth.num_params(); ++i) {
    if (i < 4) d_only.params()[i] = truth.params()[i];
    else k_only.params()[i] = truth.params()[i];
  }
  r->eps_gt_pinhole = ground_truth_error(truth, k_only, 40, 23);
  r->eps_gt_distortion = ground_truth_error(truth, d_only, 40, 23);
}

double predicted_eps_gt(const CalibrationResult& res) {
  std::vector<int> free_idx;
  for (size_t i = 0; i < res.fixed.size(); ++i)
    if (!res.fixed[i]) free_idx.push_back(static_cast<int>(i));
  const Eigen::MatrixXd cov = res.covariance_scaled()(free_idx, free_idx);
  return std::sqrt((projection_gram(res.model, res.fixed, 40, 23) * cov).trace());
}

// eps_gt (mean distance) over the 40x23 edge grid's pixels whose true ray is within max_deg of
// the axis; NaN for a model that is not a ray model.
// Diagnostic (--csv reach_radius, reach_hull): where the keyframes' corners are, against the
// image the expected error is taken over.
void keyframe_reach(const CameraModel& m, const std::vector<Observation>& frames, Run* r) {
  const cv::Point2d c(m.cx(), m.cy());
  double r_image = 0, r_data = 0;
  for (const cv::Point2d q :
       {cv::Point2d(0, 0), cv::Point2d(m.width() - 1.0, 0), cv::Point2d(0, m.height() - 1.0),
        cv::Point2d(m.width() - 1.0, m.height() - 1.0)})
    r_image = std::max(r_image, cv::norm(q - c));
  std::vector<std::vector<cv::Point2f>> hulls;
  for (const Observation& o : frames) {
    std::vector<cv::Point2f> pts;
    for (const cv::Point2d& p : o.image_points) {
      r_data = std::max(r_data, cv::norm(p - c));
      pts.emplace_back(static_cast<float>(p.x), static_cast<float>(p.y));
    }
    if (pts.size() < 3) continue;
    std::vector<cv::Point2f> h;
    cv::convexHull(pts, h);
    hulls.push_back(h);
  }
  const int cols = kExpectedErrorCols, rows = kExpectedErrorRows;
  int inside = 0;
  for (int j = 0; j < rows; ++j) {
    for (int i = 0; i < cols; ++i) {
      const cv::Point2f g(static_cast<float>(i * (m.width() - 1.0) / (cols - 1)),
                          static_cast<float>(j * (m.height() - 1.0) / (rows - 1)));
      for (const auto& h : hulls) {
        if (cv::pointPolygonTest(h, g, false) >= 0) {
          ++inside;
          break;
        }
      }
    }
  }
  r->reach_radius = r_data / r_image;
  r->reach_hull = static_cast<double>(inside) / (cols * rows);
}

double eps_gt_within(const CameraModel& truth, const CameraModel& estimate, double max_deg) {
  if (!is_ray_model(truth.lens_model())) return NAN;
  double sum = 0;
  int n = 0;
  for (int j = 0; j < 23; ++j)
    for (int i = 0; i < 40; ++i) {
      const Eigen::Vector2d p(i * (truth.width() - 1.0) / 39, j * (truth.height() - 1.0) / 22);
      Eigen::Vector3d ray;
      Eigen::Vector2d q;
      if (!truth.unproject_ray(p, &ray) ||
          std::acos(std::clamp(ray.z(), -1.0, 1.0)) > max_deg * M_PI / 180)
        continue;
      if (!estimate.project(ray, &q)) continue;
      sum += (q - p).norm();
      ++n;
    }
  return n ? sum / n : NAN;
}

Run closed_loop(const World& world, const CameraModel& truth, const BoardSpec& target, uint64_t seed,
                const std::string& op, const std::string& config, const std::vector<Observation>& test) {
  SimCameraOptions so;
  so.truth = truth;
  so.board = target;
  so.render = render_options(world, seed);
  so.op = operator_preset(op);
  so.seed = seed;
  EngineOptions eo;
  eo.board = target;
  eo.robot = so.op.kind == OperatorKind::kRobot;
  eo.calibration.lens_model = truth.lens_model();  // the camera's own model (issue 14)
  apply_config(config, &eo);
  eo.target_timeout_frames = (so.op.move_frames + so.op.hold_frames) * so.op.max_tries + 1;
  auto cam = make_sim_camera(so);
  SimCamera* sim = as_sim_camera(cam.get());
  CalibrationSession session(std::move(cam), eo);
  // POSECAL_BENCH_TRACE=1: every engine event of every closed loop on stderr (one run at a time
  // makes sense: --threads 1).
  static const bool trace = std::getenv("POSECAL_BENCH_TRACE") != nullptr;
  if (trace) {
    session.set_event_callback([seed, config, &session](const SessionEvent& e) {
      if (e.kind != SessionEvent::Kind::kEngine) return;
      std::fprintf(stderr, "[%llu %s] %s kf=%d %s %s\n", static_cast<unsigned long long>(seed),
                   config.c_str(), engine_event_name(e.engine->kind), e.engine->keyframes,
                   e.engine->parameter.c_str(), e.engine->message.c_str());
      if (e.engine->kind != EngineEvent::Kind::kCalibrated) return;
      std::fprintf(stderr, "    %s:", lens_model_name(session.engine().estimate().lens_model()));
      for (double v : session.engine().estimate().params()) std::fprintf(stderr, " %.5g", v);
      std::fprintf(stderr, "\n");
    });
  }
  // POSECAL_BENCH_TRACE=frames: every frame's report too (corners, Jaccard against the target,
  // stillness, capture).
  static const bool trace_frames =
      trace && std::string(std::getenv("POSECAL_BENCH_TRACE")) == "frames";
  Run r;
  for (int f = 0; f < 3000 && !session.finished(); ++f) {
    session.step(1000);
    if (session.frames_processed() == 0) continue;
    if (trace_frames && session.has_engine()) {
      const FrameReport& fr = session.engine().last_report();
      std::fprintf(stderr,
                   "[%llu %s]   frame %llu %s target %s corners %d/%d jaccard %.3f still %d "
                   "reached %d captured %d\n",
                   static_cast<unsigned long long>(seed), config.c_str(),
                   static_cast<unsigned long long>(fr.frame_index), engine_state_name(fr.state),
                   fr.target_parameter.c_str(), fr.corners, fr.corners_required, fr.jaccard,
                   fr.still ? 1 : 0, fr.pose_reached ? 1 : 0, fr.captured ? 1 : 0);
    }
    const EngineState st = session.engine().state();
    if (r.bootstrap_frames < 0 && st != EngineState::kWaitingForBoard && st != EngineState::kBootstrapping)
      r.bootstrap_frames = static_cast<int>(session.frames_processed());
  }
  const CalibrationEngine& eng = session.engine();
  r.converged = eng.converged();
  r.keyframes = eng.keyframes();
  r.frames = static_cast<int>(session.frames_processed());
  r.lens_model = lens_model_name(eng.estimate().lens_model());
  if (eng.result()) {
    const SimEvaluation ev = evaluate_synthetic(eng.estimate(), truth, test);
    r.eps_test = ev.eps_test;
    r.eps_gt = ev.eps_gt;
    split_eps_gt(truth, eng.estimate(), &r);
    r.eps_gt_predicted = predicted_eps_gt(*eng.result());
    r.eps_gt_edges = ground_truth_error_edges(truth, eng.estimate());
    r.eps_gt_inner = eps_gt_within(truth, eng.estimate(), 80);
    r.eps_gt_aligned = ground_truth_error_aligned(truth, eng.estimate());
    r.expected_error_px = eng.expected_error()->rms_px;
    r.expected_mean_px = eng.expected_error()->mean_px;
    r.expected_p90_px = eng.expected_error()->p90_px;
    r.expected_points = eng.expected_error()->points;
    r.eps_res = eng.result()->rms_px;
    keyframe_reach(eng.estimate(), eng.keyframe_observations(), &r);
    if (g_restarts && eng.estimate().lens_model() == truth.lens_model()) {
      try {
        const WarmStart from_truth{truth, {}};
        const CalibrationResult t = calibrate(eng.keyframe_observations(), truth.size(),
                                              eng.options().calibration, &from_truth);
        r.truth_start_rms = t.rms_px;
        r.truth_start_eps_gt = ground_truth_error_edges(truth, t.model);
      } catch (const std::exception&) {
      }
    }
    if (g_restarts) try {
        const CalibrationResult c =
            calibrate(eng.keyframe_observations(), truth.size(), eng.options().calibration);
        r.cold_start_rms = c.rms_px;
        r.cold_start_eps_gt = ground_truth_error_edges(truth, c.model);
      } catch (const std::exception&) {
      }
    if (g_compactness && eng.keyframes() >= 2 && !test.empty()) {
      const CompactSubset c = greedy_compact_subset(eng.keyframe_observations(), test, truth.size(), eng.options().calibration);
      r.compact_kept = static_cast<int>(c.keyframes.size());
      r.compact_eps_test = c.eps_test;
      r.compact_eps_test_all = c.eps_test_all;
    }
  }
  r.attempts = sim->op().attempts();
  return r;
}

// Random well-spread views (board fully visible, tilt up to 45 deg) rendered by the world's
// renderer and detected; views with fewer than 6 corners are left out.
std::vector<Observation> random_observations(const World& world, const CameraModel& truth, const BoardSpec& target,
                                             uint64_t view_seed, uint64_t render_seed, int n) {
  const Board board(target);
  SyntheticCamera sc(truth, board, render_options(world, render_seed));
  ViewSampling vs;
  vs.max_tilt_deg = 45;
  std::vector<Observation> frames;
  std::vector<Pose> views = random_board_views(view_seed, n, truth, board, vs);
  if (truth.lens_model() == LensModel::kFisheye) {
    // cv::fisheye takes theta = atan(r) of the plane Z = 1: it cannot use a corner 90 degrees or
    // more from the axis, and its fit degrades well before (its calibrations of views reaching the
    // rim of a 185-degree lens end with residuals of 170 px or throw). Its best case: views whose
    // corners all lie within 80 degrees of the axis, drawn from a longer sequence.
    const std::vector<Pose> all = random_board_views(view_seed, 20 * n, truth, board, vs);
    views.clear();
    for (const Pose& p : all) {
      bool inside = true;
      for (const cv::Point3d& c : board.corners()) {
        const Eigen::Vector3d q = p.apply(Eigen::Vector3d(c.x, c.y, c.z));
        inside = inside && std::atan2(q.head<2>().norm(), q.z()) < 80 * M_PI / 180;
      }
      if (inside) views.push_back(p);
      if (static_cast<int>(views.size()) == n) break;
    }
  }
  for (const Pose& p : views) {
    const Detection d = board.detect(sc.render(p));
    if (d.size() >= 6) frames.push_back(Observation::from(d));
  }
  return frames;
}

// OpenCV's calibration of `frames`, scored like the closed loop; converged = false if OpenCV
// throws. with_covariance: also the covariance-predicted eps_gt through posecal's calibration.
Run opencv_calibration(const CameraModel& truth, const std::vector<Observation>& frames,
                       const std::vector<Observation>& test, bool with_covariance) {
  std::vector<std::vector<cv::Point3f>> obj;
  std::vector<std::vector<cv::Point2f>> img;
  for (const Observation& f : frames) {
    obj.emplace_back();
    img.emplace_back();
    for (size_t j = 0; j < f.image_points.size(); ++j) {
      obj.back().emplace_back(f.board_points[j].x, f.board_points[j].y, f.board_points[j].z);
      img.back().emplace_back(f.image_points[j].x, f.image_points[j].y);
    }
  }
  Run r;
  r.keyframes = static_cast<int>(obj.size());
  try {
    cv::Mat K, D;
    std::vector<cv::Mat> rv, tv;
    CameraModel m;
    const LensModel lens = truth.lens_model();
    if (lens == LensModel::kFisheye) {
      // cv::fisheye::calibrate with its usual flags (skew fixed, extrinsics recomputed each
      // iteration). It sees only points less than 90 degrees from the axis (atan(r)); it throws
      // (CALIB_CHECK_COND) or fails on some view sets: counted as not converged.
      const int flags = cv::fisheye::CALIB_RECOMPUTE_EXTRINSIC | cv::fisheye::CALIB_FIX_SKEW;
      K = cv::Mat::eye(3, 3, CV_64F);
      D = cv::Mat::zeros(4, 1, CV_64F);
      r.eps_res = cv::fisheye::calibrate(
          obj, img, truth.size(), K, D, rv, tv, flags,
          cv::TermCriteria(cv::TermCriteria::COUNT + cv::TermCriteria::EPS, 100, 1e-10));
      std::vector<double> d(D.begin<double>(), D.end<double>());
      m = CameraModel::from_opencv_fisheye(truth.width(), truth.height(),
                                           cv::Matx33d(K.ptr<double>()), d);
    } else {
      int flags = 0;
      if (lens == LensModel::kOpenCV8) flags = cv::CALIB_RATIONAL_MODEL;
      if (lens == LensModel::kOpenCV12)
        flags = cv::CALIB_RATIONAL_MODEL | cv::CALIB_THIN_PRISM_MODEL;
      if (lens == LensModel::kOpenCV14)
        flags = cv::CALIB_RATIONAL_MODEL | cv::CALIB_THIN_PRISM_MODEL | cv::CALIB_TILTED_MODEL;
      r.eps_res = cv::calibrateCamera(obj, img, truth.size(), K, D, rv, tv, flags);
      std::vector<double> d(D.begin<double>(), D.end<double>());
      // OpenCV returns its longer vector with the flags; the model's coefficients come first.
      if (lens != LensModel::kOpenCV5) d.resize(static_cast<size_t>(truth.num_params() - 4));
      m = CameraModel::from_opencv(truth.width(), truth.height(), cv::Matx33d(K.ptr<double>()), d);
    }
    const SimEvaluation ev = evaluate_synthetic(m, truth, test);
    r.converged = true;
    r.eps_test = ev.eps_test;
    r.eps_gt = ev.eps_gt;
    split_eps_gt(truth, m, &r);
    r.eps_gt_edges = ground_truth_error_edges(truth, m);
    r.eps_gt_inner = eps_gt_within(truth, m, 80);
    r.eps_gt_aligned = ground_truth_error_aligned(truth, m);
    // Covariance of the same frames through posecal's calibration (equal to OpenCV's solution,
    // tests/core: Calibration.NoWorseThanOpenCVOnTheSameFrames).
    if (with_covariance) {
      CalibrationOptions co;
      co.lens_model = truth.lens_model();
      co.hold_if_undetermined = extension_parameters(co.lens_model);
      try {
        r.eps_gt_predicted = predicted_eps_gt(calibrate(frames, truth.size(), co));
      } catch (const std::exception&) {  // ours, not OpenCV's: the baseline stands
      }
    }
  } catch (const std::exception&) {
    r.converged = false;
  }
  return r;
}

Run random_baseline(const World& world, const CameraModel& truth, const BoardSpec& target, uint64_t seed, int n,
                    const std::vector<Observation>& test) {
  Run r = opencv_calibration(truth, random_observations(world, truth, target, seed * 7919 + n, seed + 1000003, n),
                             test, true);
  r.frames = n;
  return r;
}

// --random-match: the smallest prefix of one random sequence of g_random_match views whose OpenCV
// calibration reaches `target` (edge-grid eps_gt). Prefix lengths grow by 10% until one reaches
// it, then the lengths in between are tried one by one.
RandomMatch match_random_views(const World& world, const CameraModel& truth, const BoardSpec& target_board,
                               uint64_t seed, double target, const std::vector<Observation>& test) {
  RandomMatch m;
  m.target_eps_gt = target;
  if (!std::isfinite(target)) return m;
  const std::vector<Observation> pool =
      random_observations(world, truth, target_board, seed * 7919 + 424242, seed + 2000003, g_random_match);
  auto reaches = [&](int n) {
    ++m.calibrations;
    const std::vector<Observation> prefix(pool.begin(), pool.begin() + n);
    const Run r = opencv_calibration(truth, prefix, test, false);
    return r.converged && r.eps_gt_edges <= target;
  };
  const int total = static_cast<int>(pool.size());
  int below = 2;  // prefixes up to `below` views are known not to reach the target
  for (int n = 3; n <= total; n = std::max(n + 1, static_cast<int>(std::lround(n * 1.1)))) {
    if (!reaches(n)) {
      below = n;
      continue;
    }
    m.views = n;
    for (int k = below + 1; k < n; ++k)
      if (reaches(k)) {
        m.views = k;
        break;
      }
    return m;
  }
  m.views = total == g_random_match && reaches(total) ? total : 0;
  return m;
}

struct Stats {
  double median = NAN, p25 = NAN, p75 = NAN, min = NAN, max = NAN;
};

Stats stats(std::vector<double> v) {
  v.erase(std::remove_if(v.begin(), v.end(), [](double x) { return !std::isfinite(x); }), v.end());
  Stats s;
  if (v.empty()) return s;
  std::sort(v.begin(), v.end());
  auto q = [&](double p) {
    const double i = p * (v.size() - 1);
    const size_t lo = static_cast<size_t>(std::floor(i)), hi = static_cast<size_t>(std::ceil(i));
    return v[lo] + (v[hi] - v[lo]) * (i - lo);
  };
  s.median = q(0.5);
  s.p25 = q(0.25);
  s.p75 = q(0.75);
  s.min = v.front();
  s.max = v.back();
  return s;
}

std::string fmt(const Stats& s, const char* f) {
  char buf[256], a[32], b[32], c[32], d[32], e[32];
  std::snprintf(a, sizeof a, f, s.median);
  std::snprintf(b, sizeof b, f, s.p25);
  std::snprintf(c, sizeof c, f, s.p75);
  std::snprintf(d, sizeof d, f, s.min);
  std::snprintf(e, sizeof e, f, s.max);
  std::snprintf(buf, sizeof buf, "%s [%s, %s] (%s-%s)", a, b, c, d, e);
  return buf;
}

// The honesty of the stop figure: expected_error_px against the realised edge-grid eps_gt, and
// with --accuracy-px how often the realised error stays within 1.2 x the requested accuracy.
template <class Column>
void print_accuracy(const std::vector<CameraRuns>& runs, Column column) {
  std::printf("| method | expected_error_px (RMS) | expected mean eps_gt | expected p90 | realised eps_gt, edge grid [px] "
              "| realised / expected mean | realised <= expected p90 |");
  if (g_accuracy_px > 0) std::printf(" converged | realised <= 1.2 x %.3f px (of converged) |", g_accuracy_px);
  std::printf("\n|---|---|---|---|---|---|---|%s\n", g_accuracy_px > 0 ? "---|---|" : "");
  for (auto run : {&CameraRuns::person, &CameraRuns::robot}) {
    std::printf("| pose selection, %s | %s | %s | %s | %s | %s |", run == &CameraRuns::person ? "person" : "robot",
                fmt(stats(column([&](const CameraRuns& r) { return (r.*run).expected_error_px; })), "%.3f").c_str(),
                fmt(stats(column([&](const CameraRuns& r) { return (r.*run).expected_mean_px; })), "%.3f").c_str(),
                fmt(stats(column([&](const CameraRuns& r) { return (r.*run).expected_p90_px; })), "%.3f").c_str(),
                fmt(stats(column([&](const CameraRuns& r) { return (r.*run).eps_gt_edges; })), "%.3f").c_str(),
                fmt(stats(column([&](const CameraRuns& r) { return (r.*run).eps_gt_edges / (r.*run).expected_mean_px; })),
                    "%.2f").c_str());
    int within_p90 = 0, with_result = 0;
    for (const CameraRuns& r : runs) {
      if (!std::isfinite((r.*run).eps_gt_edges)) continue;
      ++with_result;
      within_p90 += (r.*run).eps_gt_edges <= (r.*run).expected_p90_px;
    }
    std::printf(" %d/%d |", within_p90, with_result);
    if (g_accuracy_px > 0) {
      int converged = 0, within = 0;
      for (const CameraRuns& r : runs) {
        if (!(r.*run).converged) continue;
        ++converged;
        within += (r.*run).eps_gt_edges <= 1.2 * g_accuracy_px;
      }
      std::printf(" %d/%zu | %d/%d (%.0f%%) |", converged, runs.size(), within, converged,
                  converged ? 100.0 * within / converged : 0.0);
    }
    std::printf("\n");
  }
  std::printf("\n");
}

// Paper Figure 3: 2 initial poses, then 8 C_Delta then 10 C_K poses (or the reverse), mean sigma
// of each parameter after each pose, over several sampled cameras.
void figure3(const Options& o) {
  const CameraModel ref = reference_camera(o.camera);
  const BoardSpec target = board_for(o.camera);
  const Board board(target);
  // sums[order][pose][param]
  std::vector<std::vector<std::vector<double>>> sums(2, std::vector<std::vector<double>>(20, std::vector<double>(9, 0.0)));
  std::vector<std::vector<int>> counts(2, std::vector<int>(20, 0));
  for (int order = 0; order < 2; ++order) {
    for (int cam = 0; cam < o.figure3_cameras; ++cam) {
      const uint64_t seed = 500 + cam;
      const CameraModel truth = sample_camera(ref, 0.1, seed);
      SyntheticCamera sc(truth, board, render_options(World{}, seed));
      PoseGenerator pg(board, truth.size());
      std::vector<Observation> frames;
      std::optional<CalibrationResult> res;
      CameraModel estimate = truth;  // poses are generated from the current estimate below
      for (int k = 0; k < 20; ++k) {
        TargetPose tp;
        if (k < 2) {
          tp = pg.initial_pose(k, estimate);
        } else {
          const bool distortion_phase = (order == 0) == (k < 10);
          // Rotate through the parameters of the phase's group.
          const int param = distortion_phase ? 4 + (k - 2) % 5 : (k - 2) % 4;
          tp = pg.next_pose(param, estimate);
        }
        const Detection d = board.detect(sc.render(tp.T_cam_board));
        if (d.size() < 6) continue;
        frames.push_back(Observation::from(d));
        if (frames.size() < 2) continue;
        try {
          if (res) {
            const WarmStart ws{res->model, res->poses};
            res = calibrate(frames, truth.size(), {}, &ws);
          } else {
            res = calibrate(frames, truth.size());
          }
          estimate = res->model;
          for (int i = 0; i < 9; ++i) sums[order][k][i] += res->std_unit[i];  // Sigma_p = I, as the paper
          ++counts[order][k];
        } catch (const Error&) {
          frames.pop_back();
        }
      }
    }
  }
  // Plot: two panels (order), 9 curves each, sigma relative to its value after pose 2, log y.
  const int W = 1400, H = 560, left = 70, top = 40, pw = 600, ph = 420;
  cv::Mat img(H, W, CV_8UC3, cv::Scalar(255, 255, 255));
  const cv::Scalar colors[9] = {{200, 0, 0},   {255, 120, 0}, {0, 140, 0},  {0, 200, 120}, {0, 0, 220},
                                {160, 0, 200}, {0, 120, 255}, {120, 80, 0}, {80, 80, 80}};
  const char* names[9] = {"fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"};
  std::printf("\nFigure 3 data (mean sigma per pose, %d cameras)\n", o.figure3_cameras);
  for (int order = 0; order < 2; ++order) {
    const int x0 = left + order * (pw + 100);
    cv::rectangle(img, cv::Rect(x0, top, pw, ph), cv::Scalar(0, 0, 0), 1);
    const std::string title = order == 0 ? "poses 3-10: C_Delta, 11-20: C_K" : "poses 3-10: C_K, 11-20: C_Delta";
    cv::putText(img, title, cv::Point(x0 + 10, top - 12), cv::FONT_HERSHEY_SIMPLEX, 0.6, cv::Scalar(0, 0, 0), 1, cv::LINE_AA);
    // log10(sigma / sigma_at_pose2) from -2 to +0.5
    auto ypix = [&](double rel) { return top + static_cast<int>((0.5 - std::log10(rel)) / 2.5 * ph); };
    for (int e = -2; e <= 0; ++e) {
      const int y = ypix(std::pow(10.0, e));
      cv::line(img, cv::Point(x0, y), cv::Point(x0 + pw, y), cv::Scalar(220, 220, 220), 1);
      cv::putText(img, "1e" + std::to_string(e), cv::Point(x0 - 45, y + 5), cv::FONT_HERSHEY_SIMPLEX, 0.45, cv::Scalar(0, 0, 0), 1, cv::LINE_AA);
    }
    const int xsplit = x0 + static_cast<int>((10 - 1.5) / 18.0 * pw);
    cv::line(img, cv::Point(xsplit, top), cv::Point(xsplit, top + ph), cv::Scalar(150, 150, 150), 1);
    for (int k = 1; k < 20; k += 2) {
      cv::putText(img, std::to_string(k + 1), cv::Point(x0 + static_cast<int>((k - 1) / 18.0 * pw) - 5, top + ph + 18),
                  cv::FONT_HERSHEY_SIMPLEX, 0.4, cv::Scalar(0, 0, 0), 1, cv::LINE_AA);
    }
    std::printf("%s\n pose", title.c_str());
    for (int i = 0; i < 9; ++i) std::printf(" %9s", names[i]);
    std::printf("\n");
    for (int k = 1; k < 20; ++k) {
      if (!counts[order][k]) continue;
      std::printf(" %4d", k + 1);
      for (int i = 0; i < 9; ++i) std::printf(" %9.3g", sums[order][k][i] / counts[order][k]);
      std::printf("\n");
    }
    for (int i = 0; i < 9; ++i) {
      const double base = sums[order][1][i] / std::max(1, counts[order][1]);
      std::vector<cv::Point> pts;
      for (int k = 1; k < 20; ++k) {
        if (!counts[order][k] || !(base > 0)) continue;
        const double rel = std::max(1e-2, sums[order][k][i] / counts[order][k] / base);
        pts.emplace_back(x0 + static_cast<int>((k - 1) / 18.0 * pw), ypix(rel));
      }
      cv::polylines(img, std::vector<std::vector<cv::Point>>{pts}, false, colors[i], 2, cv::LINE_AA);
      if (order == 1) {
        cv::putText(img, names[i], cv::Point(x0 + pw + 10, top + 20 + 22 * i), cv::FONT_HERSHEY_SIMPLEX, 0.55, colors[i], 2, cv::LINE_AA);
      }
    }
  }
  cv::putText(img, "mean sigma (Sigma_p = I) relative to pose 2, log scale, vs pose number; 20 cameras around the C525", cv::Point(left, H - 15), cv::FONT_HERSHEY_SIMPLEX,
              0.55, cv::Scalar(0, 0, 0), 1, cv::LINE_AA);
  cv::imwrite(o.figure3, img);
  std::printf("written %s\n", o.figure3.c_str());
}

// The runs of one world: every camera of the seed range, the person with every configuration
// (and the robot with the first), and both random baselines.
std::vector<CameraRuns> run_world(const World& world, const Options& o, bool quiet) {
  const CameraModel ref = reference_camera(world.camera);
  const BoardSpec target = board_for(world.camera);
  std::vector<CameraRuns> runs(o.cameras);
  std::atomic<int> next{0};
  std::mutex print;
  auto worker = [&]() {
    for (int i = next++; i < o.cameras; i = next++) {
      CameraRuns& cr = runs[i];
      cr.seed = o.first_seed + i;
      const CameraModel truth = sample_camera(ref, 0.1, cr.seed);
      SyntheticCamera test_cam(truth, Board(target), render_options(world, cr.seed + 7777));
      const std::vector<Observation> test = render_test_set(test_cam);
      for (const std::string& config : o.configs)
        cr.persons.push_back(closed_loop(world, truth, target, cr.seed, world.op, config, test));
      cr.person = cr.persons.front();
      if (o.robot) cr.robot = closed_loop(world, truth, target, cr.seed, "robot", o.configs.front(), test);
      cr.base10 = random_baseline(world, truth, target, cr.seed, 10, test);
      cr.base20 = random_baseline(world, truth, target, cr.seed, 20, test);
      if (g_random_match > 0)
        cr.match = match_random_views(world, truth, target, cr.seed, cr.persons.front().eps_gt_edges, test);
      if (quiet) continue;
      std::lock_guard<std::mutex> lock(print);
      std::fprintf(stderr, "camera %2d: person %s kf %2d gt %.3f | robot %s kf %2d gt %.3f | rnd10 gt %.3f | rnd20 gt %.3f\n",
                   cr.seed, cr.person.converged ? "ok" : "NO", cr.person.keyframes, cr.person.eps_gt,
                   cr.robot.converged ? "ok" : "NO", cr.robot.keyframes, cr.robot.eps_gt, cr.base10.eps_gt,
                   cr.base20.eps_gt);
    }
  };
  std::vector<std::thread> pool;
  for (int t = 0; t < std::max(1, o.threads); ++t) pool.emplace_back(worker);
  for (auto& t : pool) t.join();
  return runs;
}

// The tables of one world without --world: docs/benchmarks.md up to 2026-12-02.
void print_single_world(const std::vector<CameraRuns>& runs, const Options& o) {
  auto column = [&](auto get) {
    std::vector<double> v;
    for (const auto& r : runs) v.push_back(get(r));
    return v;
  };
  std::printf("\n%d cameras sampled around '%s' (10%% std per parameter), noise 2 grey levels, blur 0.8 px, "
              "engine config '%s'\n\n", o.cameras, o.camera.c_str(), o.configs.front().c_str());
  std::printf("| method | converged | keyframes | operator frames | eps_test [px] | eps_gt [px] | eps_gt / random-10 |\n");
  std::printf("|---|---|---|---|---|---|---|\n");
  struct M {
    const char* name;
    Run CameraRuns::*run;
  };
  for (const M m : {M{"pose selection, person", &CameraRuns::person}, M{"pose selection, robot", &CameraRuns::robot},
                    M{"OpenCV, 10 random poses", &CameraRuns::base10}, M{"OpenCV, 20 random poses", &CameraRuns::base20}}) {
    int conv = 0;
    for (const auto& r : runs) conv += (r.*(m.run)).converged;
    std::printf("| %s | %d/%d | %s | %s | %s | %s | %s |\n", m.name, conv, o.cameras,
                fmt(stats(column([&](const CameraRuns& r) { return double((r.*(m.run)).keyframes); })), "%.0f").c_str(),
                fmt(stats(column([&](const CameraRuns& r) { return double((r.*(m.run)).frames); })), "%.0f").c_str(),
                fmt(stats(column([&](const CameraRuns& r) { return (r.*(m.run)).eps_test; })), "%.3f").c_str(),
                fmt(stats(column([&](const CameraRuns& r) { return (r.*(m.run)).eps_gt; })), "%.3f").c_str(),
                fmt(stats(column([&](const CameraRuns& r) { return (r.*(m.run)).eps_gt / r.base10.eps_gt; })), "%.2f").c_str());
  }
  std::printf("\nmedian [25%%, 75%%] (min-max) over cameras; ratios are per camera.\n\n");
  std::printf("| method | predicted eps_gt [px] | predicted eps_gt / random-10 |\n|---|---|---|\n");
  for (const M m : {M{"pose selection, person", &CameraRuns::person}, M{"pose selection, robot", &CameraRuns::robot},
                    M{"OpenCV, 10 random poses", &CameraRuns::base10}, M{"OpenCV, 20 random poses", &CameraRuns::base20}}) {
    std::printf("| %s | %s | %s |\n", m.name,
                fmt(stats(column([&](const CameraRuns& r) { return (r.*(m.run)).eps_gt_predicted; })), "%.3f").c_str(),
                fmt(stats(column([&](const CameraRuns& r) {
                      return (r.*(m.run)).eps_gt_predicted / r.base10.eps_gt_predicted;
                    })), "%.2f").c_str());
  }
  std::printf("\n");
  print_accuracy(runs, column);
  // Targets reached per attempt, by target kind.
  for (const M m : {M{"person", &CameraRuns::person}, M{"robot", &CameraRuns::robot}}) {
    std::map<std::string, AttemptStats> total;
    for (const auto& r : runs)
      for (const auto& [k, a] : (r.*(m.run)).attempts) {
        total[k].attempts += a.attempts;
        total[k].reached += a.reached;
      }
    std::printf("%s: targets reached per attempt:", m.name);
    for (const auto& [k, a] : total) {
      std::printf("  %s %d/%d (%.0f%%)", k.c_str(), a.reached, a.attempts, a.attempts ? 100.0 * a.reached / a.attempts : 0.0);
    }
    std::printf("\n");
  }
}

// Percentile of the finite values (linear interpolation), NaN if none.
double percentile(std::vector<double> v, double p) {
  v.erase(std::remove_if(v.begin(), v.end(), [](double x) { return !std::isfinite(x); }), v.end());
  if (v.empty()) return NAN;
  std::sort(v.begin(), v.end());
  const double i = p * (v.size() - 1);
  const size_t lo = static_cast<size_t>(std::floor(i)), hi = static_cast<size_t>(std::ceil(i));
  return v[lo] + (v[hi] - v[lo]) * (i - lo);
}

// Median with a 95% percentile-bootstrap interval (2000 resamples, fixed seed): "m [lo, hi]".
std::string median_ci(const std::vector<double>& v, const char* f) {
  std::vector<double> x;
  for (double a : v)
    if (std::isfinite(a)) x.push_back(a);
  if (x.empty()) return "-";
  std::mt19937_64 rng(12345);
  std::uniform_int_distribution<size_t> pick(0, x.size() - 1);
  std::vector<double> medians, sample(x.size());
  for (int b = 0; b < 2000; ++b) {
    for (double& a : sample) a = x[pick(rng)];
    medians.push_back(percentile(sample, 0.5));
  }
  char m[32], lo[32], hi[32], buf[128];
  std::snprintf(m, sizeof m, f, percentile(x, 0.5));
  std::snprintf(lo, sizeof lo, f, percentile(medians, 0.025));
  std::snprintf(hi, sizeof hi, f, percentile(medians, 0.975));
  std::snprintf(buf, sizeof buf, "%s [%s, %s]", m, lo, hi);
  return buf;
}

// Every configuration against the first, per camera: eps_gt ratio and keyframe difference.
void print_paired(const std::vector<CameraRuns>& runs, const Options& o) {
  for (size_t c = 1; c < o.configs.size(); ++c) {
    std::vector<double> ratio, dkf;
    int better = 0, both = 0;
    for (const CameraRuns& r : runs) {
      const double a = r.persons[0].eps_gt_edges, b = r.persons[c].eps_gt_edges;
      ratio.push_back(b / a);
      dkf.push_back(r.persons[c].keyframes - r.persons[0].keyframes);
      if (std::isfinite(a) && std::isfinite(b)) {
        ++both;
        better += b < a;
      }
    }
    std::printf("paired, %s vs %s: eps_gt ratio %s (p90 %.2f), keyframes %s, better on %d of %d\n",
                o.configs[c].c_str(), o.configs[0].c_str(), median_ci(ratio, "%.2f").c_str(), percentile(ratio, 0.9),
                median_ci(dkf, "%+.1f").c_str(), better, both);
  }
}

// The honesty of the stop figure in one world: realised eps_gt (edge grid, mean distance)
// against the session's expected_error_px (an RMS over the same grid) and its predicted mean;
// with --accuracy-px, how often a converged run's realised error stays within 1.2 x (and 1.5 x)
// the requested accuracy.
// Against the right model's OpenCV calibration (issue 14): eps_gt aligned, the ratio to 20 random
// views; a fisheye world's eps_gt within 80 degrees of the axis, where cv::fisheye has data.
void print_against_right_model(const std::vector<CameraRuns>& runs, size_t c,
                               const std::string& config, const std::string& first) {
  std::vector<double> ours, r10, r20;
  for (const CameraRuns& r : runs) {
    if (std::isfinite(r.persons[c].eps_gt_inner)) ours.push_back(r.persons[c].eps_gt_inner);
    if (std::isfinite(r.base10.eps_gt_inner)) r10.push_back(r.base10.eps_gt_inner);
    if (std::isfinite(r.base20.eps_gt_inner)) r20.push_back(r.base20.eps_gt_inner);
  }
  std::vector<double> al, al10, al20, ratio20;
  for (const CameraRuns& r : runs) {
    if (std::isfinite(r.persons[c].eps_gt_aligned)) al.push_back(r.persons[c].eps_gt_aligned);
    if (std::isfinite(r.base10.eps_gt_aligned)) al10.push_back(r.base10.eps_gt_aligned);
    if (std::isfinite(r.base20.eps_gt_aligned)) al20.push_back(r.base20.eps_gt_aligned);
    if (r.persons[c].converged && std::isfinite(r.persons[c].eps_gt_edges) && r.base20.converged &&
        r.base20.eps_gt_edges > 0)
      ratio20.push_back(r.persons[c].eps_gt_edges / r.base20.eps_gt_edges);
  }
  if (!al.empty())
    std::printf(
        "eps_gt aligned (the camera rotation taken out), %s: %s px; OpenCV 10 views %s px, 20 "
        "views %s px\n",
        config.c_str(), median_ci(al, "%.3f").c_str(), median_ci(al10, "%.3f").c_str(),
        median_ci(al20, "%.3f").c_str());
  if (!ratio20.empty())
    std::printf("eps_gt / random-20 (edge grid, per camera), %s: %s (p90 %.2f)\n", config.c_str(),
                median_ci(ratio20, "%.2f").c_str(), percentile(ratio20, 0.9));
  std::map<std::string, int> chosen;
  for (const CameraRuns& r : runs) ++chosen[r.persons[c].lens_model];
  std::printf("lens model calibrated, %s:", config.c_str());
  for (const auto& [name, count] : chosen) std::printf(" %s x%d", name.c_str(), count);
  std::printf("\n");
  if (c > 0) {  // paired with the first configuration, camera by camera
    const auto print_paired = [&](double Run::*eps, const char* label) {
      std::vector<double> paired;
      for (const CameraRuns& r : runs)
        if (r.persons[c].converged && r.persons[0].converged && r.persons[0].*eps > 0)
          paired.push_back(r.persons[c].*eps / r.persons[0].*eps);
      if (!paired.empty())
        std::printf("%s %s / %s (paired per camera): %s (p90 %.2f)\n", label, config.c_str(),
                    first.c_str(), median_ci(paired, "%.2f").c_str(), percentile(paired, 0.9));
    };
    print_paired(&Run::eps_gt_edges, "eps_gt (edge grid)");
    print_paired(&Run::eps_gt_aligned, "eps_gt aligned");
  }
  if (ours.empty()) return;
  std::printf(
      "eps_gt within 80 degrees of the axis (where cv::fisheye has data), %s: %s px; OpenCV 10 "
      "views %s px, "
      "20 views %s px\n",
      config.c_str(), median_ci(ours, "%.3f").c_str(), median_ci(r10, "%.3f").c_str(),
      median_ci(r20, "%.3f").c_str());
}

void print_honesty(const std::vector<CameraRuns>& runs, size_t c, const std::string& config) {
  std::vector<double> to_rms, to_mean;
  int within_15 = 0, with_result = 0, converged = 0, within_12acc = 0, above_15acc = 0;
  for (const CameraRuns& r : runs) {
    const Run& x = r.persons[c];
    if (!std::isfinite(x.eps_gt_edges) || !std::isfinite(x.expected_error_px)) continue;
    ++with_result;
    const double q = x.eps_gt_edges / x.expected_error_px;
    to_rms.push_back(q);
    to_mean.push_back(x.eps_gt_edges / x.expected_mean_px);
    within_15 += q <= 1.5 && q >= 1 / 1.5;
    if (!x.converged) continue;
    ++converged;
    within_12acc += x.eps_gt_edges <= 1.2 * g_accuracy_px;
    above_15acc += x.eps_gt_edges > 1.5 * g_accuracy_px;
  }
  if (with_result == 0) return;
  std::printf("honesty, %s: realised eps_gt / expected_error_px %s (p10 %.2f, p90 %.2f), within 1.5x either way in %d of "
              "%d; realised / expected mean %s (p90 %.2f)\n",
              config.c_str(), median_ci(to_rms, "%.2f").c_str(), percentile(to_rms, 0.1), percentile(to_rms, 0.9),
              within_15, with_result, median_ci(to_mean, "%.2f").c_str(), percentile(to_mean, 0.9));
  if (g_accuracy_px > 0)
    std::printf("accuracy_px %.3f, %s: %d of %zu converged; realised <= 1.2 x accuracy_px in %d of %d converged (%.1f%%), "
                "> 1.5 x in %d\n",
                g_accuracy_px, config.c_str(), converged, runs.size(), within_12acc, converged,
                converged ? 100.0 * within_12acc / converged : 0.0, above_15acc);
}

// --random-match: random views OpenCV needs for the first configuration's realised eps_gt, and
// the session's keyframes as a share of them.
void print_random_match(const std::vector<CameraRuns>& runs, const std::string& config) {
  std::vector<double> views, share;  // an unreached target counts as infinitely many views
  int half = 0, unreached = 0;
  for (const CameraRuns& r : runs) {
    if (r.match.views < 0) continue;
    const int kf = r.persons[0].keyframes;
    if (r.match.views == 0) ++unreached;
    views.push_back(r.match.views > 0 ? r.match.views : INFINITY);
    // Unreached: the share is below keyframes / N; N is what is counted (conservative).
    share.push_back(double(kf) / (r.match.views > 0 ? r.match.views : g_random_match));
    half += kf <= 0.5 * (r.match.views > 0 ? r.match.views : g_random_match);
  }
  if (views.empty()) return;
  std::sort(views.begin(), views.end());
  auto at = [&](double p) {
    const double v = views[static_cast<size_t>(p * (views.size() - 1) + 0.5)];
    return std::isfinite(v) ? std::to_string(static_cast<int>(v)) : std::string("more than ") + std::to_string(g_random_match);
  };
  std::printf("random views for the same eps_gt, %s: median %s (p10 %s, p90 %s); keyframes / random views %s "
              "(p90 %.2f); keyframes <= 0.5 x random views in %d of %zu; %d not reached within %d views\n",
              config.c_str(), at(0.5).c_str(), at(0.1).c_str(), at(0.9).c_str(), median_ci(share, "%.2f").c_str(),
              percentile(share, 0.9), half, views.size(), unreached, g_random_match);
}

// What a world's summary keeps for the table of all worlds.
struct WorldSummary {
  std::string name;
  std::vector<double> ratio;  // per configuration: median eps_gt / random-10 (edge grid)
  std::vector<double> converged_fraction;
};

// One world's table: per configuration and baseline, converged, keyframes, operator frames,
// eps_gt over the edge grid (median with interval, p90), the per-camera ratio to random-10; then
// every configuration paired against the first.
WorldSummary print_world(const World& w, const std::vector<CameraRuns>& runs, const Options& o) {
  WorldSummary ws;
  ws.name = w.name();
  const int n = static_cast<int>(runs.size());
  std::printf("\n### %s: %d cameras, seeds %d-%d\n\n", ws.name.c_str(), n, o.first_seed, o.first_seed + n - 1);
  std::printf("| method | converged | keyframes | operator frames | eps_gt [px] | eps_gt p90 | eps_gt / random-10 | ratio p90 | eps_res "
              "| bootstrap frames (max) |\n");
  std::printf("|---|---|---|---|---|---|---|---|---|---|\n");
  auto row = [&](const std::string& name, auto get) {
    std::vector<double> kf, fr, gt, ratio, res, boot;
    int conv = 0, stranded = 0;
    for (const CameraRuns& r : runs) {
      const Run& x = get(r);
      conv += x.converged;
      if (x.bootstrap_frames >= 0) boot.push_back(x.bootstrap_frames);
      else stranded += x.frames > 0 && !x.attempts.empty();
      kf.push_back(x.keyframes);
      fr.push_back(x.frames);
      gt.push_back(x.eps_gt_edges);
      ratio.push_back(x.eps_gt_edges / r.base10.eps_gt_edges);
      res.push_back(x.eps_res);
    }
    char b[64] = "-";
    if (!boot.empty() || stranded)
      std::snprintf(b, sizeof b, "%.0f (%.0f)%s", percentile(boot, 0.5), percentile(boot, 1.0),
                    stranded ? (", " + std::to_string(stranded) + " never").c_str() : "");
    std::printf("| %s | %d/%d | %s | %s | %s | %.3f | %s | %.2f | %.3f | %s |\n", name.c_str(), conv, n,
                median_ci(kf, "%.1f").c_str(), median_ci(fr, "%.0f").c_str(), median_ci(gt, "%.3f").c_str(),
                percentile(gt, 0.9), median_ci(ratio, "%.2f").c_str(), percentile(ratio, 0.9), percentile(res, 0.5), b);
    return std::make_pair(percentile(ratio, 0.5), double(conv) / n);
  };
  for (size_t c = 0; c < o.configs.size(); ++c) {
    const auto [ratio, conv] = row("posecal " + o.configs[c] + ", " + w.op, [&](const CameraRuns& r) -> const Run& { return r.persons[c]; });
    ws.ratio.push_back(ratio);
    ws.converged_fraction.push_back(conv);
  }
  if (o.robot) row("posecal " + o.configs.front() + ", robot", [](const CameraRuns& r) -> const Run& { return r.robot; });
  row("OpenCV, 10 random views", [](const CameraRuns& r) -> const Run& { return r.base10; });
  row("OpenCV, 20 random views", [](const CameraRuns& r) -> const Run& { return r.base20; });
  std::printf("\nmedian [95%% bootstrap interval]; eps_gt: mean over the 40x23 edge-to-edge grid; ratios per camera.\n");
  print_paired(runs, o);
  for (size_t c = 0; c < o.configs.size() && g_compactness; ++c) {
    std::vector<double> kept, share, eps;
    for (const CameraRuns& r : runs) {
      const Run& x = r.persons[c];
      if (x.compact_kept < 0) continue;
      kept.push_back(x.compact_kept);
      share.push_back(double(x.compact_kept) / x.keyframes);
      eps.push_back(x.compact_eps_test / x.compact_eps_test_all);
    }
    std::printf("compactness test (paper §5.3), %s: keeps %s keyframes, %s of them; its eps_test / the session's %s\n",
                o.configs[c].c_str(), median_ci(kept, "%.1f").c_str(), median_ci(share, "%.2f").c_str(),
                median_ci(eps, "%.3f").c_str());
  }
  for (size_t c = 0; c < o.configs.size(); ++c) print_honesty(runs, c, o.configs[c]);
  for (size_t c = 0; c < o.configs.size(); ++c)
    print_against_right_model(runs, c, o.configs[c], o.configs.front());
  if (g_random_match > 0) print_random_match(runs, o.configs.front());
  std::map<std::string, AttemptStats> total;
  for (const auto& r : runs)
    for (const auto& [k, a] : r.person.attempts) {
      total[k].attempts += a.attempts;
      total[k].reached += a.reached;
    }
  std::printf("%s, %s: targets reached per attempt:", w.op.c_str(), o.configs.front().c_str());
  for (const auto& [k, a] : total)
    std::printf("  %s %d/%d (%.0f%%)", k.c_str(), a.reached, a.attempts, a.attempts ? 100.0 * a.reached / a.attempts : 0.0);
  std::printf("\n");
  std::fflush(stdout);
  return ws;
}

void print_worlds_summary(const std::vector<WorldSummary>& all, const Options& o) {
  std::printf("\n### All worlds: median eps_gt / random-10 (converged)\n\n| world |");
  for (const auto& c : o.configs) std::printf(" %s |", c.c_str());
  std::printf("\n|---|");
  for (size_t c = 0; c < o.configs.size(); ++c) std::printf("---|");
  std::printf("\n");
  for (const WorldSummary& w : all) {
    std::printf("| %s |", w.name.c_str());
    for (size_t c = 0; c < o.configs.size(); ++c) std::printf(" %.2f (%.0f%%) |", w.ratio[c], 100 * w.converged_fraction[c]);
    std::printf("\n");
  }
  std::printf("| **worst** |");
  for (size_t c = 0; c < o.configs.size(); ++c) {
    double worst = 0, worst_conv = 1;
    for (const WorldSummary& w : all) {
      worst = std::max(worst, w.ratio[c]);
      worst_conv = std::min(worst_conv, w.converged_fraction[c]);
    }
    std::printf(" %.2f (%.0f%%) |", worst, 100 * worst_conv);
  }
  std::printf("\n");
}

bool write_csv(const std::string& path, const std::vector<std::pair<World, std::vector<CameraRuns>>>& worlds,
               const Options& o) {
  FILE* f = std::fopen(path.c_str(), "w");
  if (!f) {
    std::fprintf(stderr, "cannot write %s\n", path.c_str());
    return false;
  }
  std::fprintf(f,
               "seed,method,converged,keyframes,frames,eps_test,eps_gt,eps_gt_pinhole,eps_gt_"
               "distortion,eps_gt_predicted,"
               "eps_gt_edges,expected_error_px,expected_mean_px,expected_p90_px,eps_res,world,"
               "config,bootstrap_frames,reach_radius,reach_hull,truth_start_rms,truth_start_eps_gt,"
               "cold_start_rms,cold_start_eps_gt,expected_points\n");
  for (const auto& [world, runs] : worlds) {
    for (const auto& r : runs) {
      std::vector<std::tuple<std::string, std::string, const Run*>> rows;
      rows.emplace_back("person", o.configs.front(), &r.person);
      if (o.robot) rows.emplace_back("robot", o.configs.front(), &r.robot);
      rows.emplace_back("random10", "", &r.base10);
      rows.emplace_back("random20", "", &r.base20);
      for (size_t c = 1; c < o.configs.size(); ++c) rows.emplace_back("person", o.configs[c], &r.persons[c]);
      for (const auto& [method, config, x] : rows) {
        std::fprintf(f,
                     "%d,%s,%d,%d,%d,%.6f,%.6f,%.6f,%.6f,%.6f,%.6f,%.6f,%.6f,%.6f,%.6f,%s,%s,%d,%."
                     "4f,%.4f,%.6f,%.6f,%.6f,%.6f,%d\n",
                     r.seed, method.c_str(), x->converged, x->keyframes, x->frames, x->eps_test,
                     x->eps_gt, x->eps_gt_pinhole, x->eps_gt_distortion, x->eps_gt_predicted,
                     x->eps_gt_edges, x->expected_error_px, x->expected_mean_px, x->expected_p90_px,
                     x->eps_res, world.name().c_str(), config.c_str(), x->bootstrap_frames,
                     x->reach_radius, x->reach_hull, x->truth_start_rms, x->truth_start_eps_gt,
                     x->cold_start_rms, x->cold_start_eps_gt, x->expected_points);
      }
    }
  }
  return std::fclose(f) == 0;
}

std::vector<std::string> split_commas(const std::string& text) {
  std::vector<std::string> out;
  std::stringstream ss(text);
  std::string item;
  while (std::getline(ss, item, ',')) out.push_back(item);
  return out;
}

}  // namespace

int main(int argc, char** argv) {
  Options o;
  std::vector<World> worlds;
  std::string seeds;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    auto next = [&]() -> std::string {
      if (i + 1 >= argc) {
        std::fprintf(stderr, "%s needs a value\n", a.c_str());
        std::exit(1);
      }
      return argv[++i];
    };
    if (a == "--cameras") o.cameras = std::stoi(next());
    else if (a == "--camera") o.camera = next();
    else if (a == "--threads") o.threads = std::stoi(next());
    else if (a == "--config") o.configs = split_commas(next());
    else if (a == "--distortion-tilt") g_distortion_tilt_deg = std::stod(next());
    else if (a == "--max-tilt") g_max_tilt_deg = std::stod(next());
    else if (a == "--score") g_score = next();
    else if (a == "--views") g_views = std::stoi(next());
    else if (a == "--views-serve-target") g_serve = true;
    else if (a == "--accuracy-px") g_accuracy_px = std::stod(next());
    else if (a == "--max-keyframes") g_max_keyframes = std::stoi(next());
    else if (a == "--csv") o.csv = next();
    else if (a == "--figure3") o.figure3 = next();
    else if (a == "--figure3-cameras") o.figure3_cameras = std::stoi(next());
    else if (a == "--world") worlds.push_back(parse_world(next()));
    else if (a == "--worlds" && next() == "standard") worlds = standard_worlds();
    else if (a == "--seeds") seeds = next();
    else if (a == "--robot") o.robot = true;
    else if (a == "--compactness") g_compactness = true;
    else if (a == "--restarts")
      g_restarts = true;
    else if (a == "--random-match") g_random_match = std::stoi(next());
    else {
      std::fprintf(stderr, "unknown option %s\n", a.c_str());
      return 1;
    }
  }
  if (o.configs.empty()) {
    std::fprintf(stderr, "--config needs at least one configuration\n");
    return 1;
  }
  for (const std::string& c : o.configs) {
    EngineOptions probe;
    apply_config(c, &probe);  // throws for an unknown name
  }
  if (!o.figure3.empty()) {
    figure3(o);
    return 0;
  }
  const bool world_mode = !worlds.empty();
  if (world_mode) {
    // Worlds: the robot only when asked; seeds from --seeds (default: the tuning set).
    o.robot = false;
    for (int i = 1; i < argc; ++i) o.robot = o.robot || std::string(argv[i]) == "--robot";
    if (seeds.empty() || seeds == "tune") {
      o.first_seed = 1;
      o.cameras = seeds.empty() ? std::min(o.cameras, 30) : 30;
    } else if (seeds == "report") {
      o.first_seed = 1001;
      o.cameras = 100;
    } else {
      const size_t dash = seeds.find('-');
      o.first_seed = std::stoi(seeds.substr(0, dash));
      o.cameras = dash == std::string::npos ? 1 : std::stoi(seeds.substr(dash + 1)) - o.first_seed + 1;
    }
  } else {
    World w;
    w.camera = o.camera;
    worlds.push_back(w);
  }
  std::vector<std::pair<World, std::vector<CameraRuns>>> results;
  std::vector<WorldSummary> summaries;
  for (const World& w : worlds) {
    results.emplace_back(w, run_world(w, o, world_mode));
    if (world_mode) summaries.push_back(print_world(w, results.back().second, o));
    else print_single_world(results.back().second, o);
  }
  if (world_mode) print_worlds_summary(summaries, o);
  if (!o.csv.empty() && !write_csv(o.csv, results, o)) return 1;
  return 0;
}
