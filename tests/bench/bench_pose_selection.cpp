// Pose selection vs random poses, side by side on the same sampled cameras (docs/benchmarks.md).
//
//   build/bin/bench_pose_selection [--cameras N] [--camera c525|industrial|tele] [--threads T]
//       [--config default|default-std|paper|std] [--distortion-tilt DEG] [--score variance|projection]
//       [--accuracy-px PX] [--csv FILE]
//       [--figure3 FILE.png]
//
// Per camera (seed i): the camera is sampled around the reference with 10% std per parameter
// (paper §5.1); pose selection runs closed-loop with a simulated person and a simulated robot;
// the baselines calibrate with cv::calibrateCamera from 10 and 20 random well-spread poses
// (board fully visible, tilt up to 45 deg) rendered by the same synthetic camera with the same
// noise (2 grey levels, blur 0.8 px). Every method is scored on the same fixed 50-frame test set
// (eps_test) and against the ground truth (eps_gt).
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
#include <string>
#include <thread>
#include <vector>

#include "calib/metrics.hpp"
#include "session/session.hpp"
#include "sim/sim_camera.hpp"
#include "board/views.hpp"
#include "lens/reference_models.hpp"
#include "calib/information.hpp"

using namespace posecal;

namespace {

struct Options {
  int cameras = 20;
  std::string camera = "c525";
  int threads = 2;
  std::string config = "default";  // default | default-std | paper | std
  std::string csv;
  std::string figure3;
  int figure3_cameras = 20;
};

CameraModel reference_camera(const std::string& name) {
  if (name == "c525") return c525_reference_model();
  if (name == "industrial") {
    // 2448x2048 machine-vision camera, 8 mm lens on a 3.45 um sensor, strong barrel distortion.
    return CameraModel::opencv5(2448, 2048, 2320, 2320, 1223.5, 1023.5, {-0.30, 0.12, 0.0005, -0.0004, -0.02});
  }
  if (name == "tele") {
    // Long focal length, low distortion (50 mm lens on a 1/1.8" 1600x1200 sensor).
    return CameraModel::opencv5(1600, 1200, 11300, 11300, 799.5, 599.5, {-0.02, 0.05, 0.0, 0.0, 0.0});
  }
  throw Error(ErrorCode::kInvalidArgument, "unknown camera '" + name + "' (c525, industrial, tele)");
}

BoardSpec board_for(const std::string& camera) {
  // A board that fills a useful part of the view at a workable distance.
  if (camera == "tele") return BoardSpec::parse("charuco:9x6:0.028:0.0182:DICT_4X4_50");
  return BoardSpec{};
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
  std::map<std::string, AttemptStats> attempts;
};

struct CameraRuns {
  int seed = 0;
  Run person, robot, base10, base20;
};

RenderOptions render_options(uint64_t seed) {
  RenderOptions ro;
  ro.noise_sigma = 2.0;
  ro.blur_sigma_px = 0.8;
  ro.seed = seed;
  return ro;
}

// --distortion-tilt DEG: overrides PoseGenOptions::distortion_tilt_deg of any configuration.
double g_distortion_tilt_deg = -1;
// --score variance|projection: overrides EngineOptions::candidate_score of any configuration.
std::string g_score;
int g_views = 0;  // --views N: EngineOptions::view_candidates
bool g_serve = false;  // --views-serve-target: EngineOptions::view_must_serve_target
double g_accuracy_px = 0;  // --accuracy-px PX (> 0): EngineOptions::accuracy_px

// Engine configurations compared in docs/benchmarks.md.
void apply_config(const std::string& config, EngineOptions* eo) {
  if (g_distortion_tilt_deg >= 0) eo->posegen.distortion_tilt_deg = g_distortion_tilt_deg;
  if (g_score == "variance") eo->candidate_score = EngineOptions::CandidateScore::kParameterVariance;
  else if (g_score == "projection") eo->candidate_score = EngineOptions::CandidateScore::kProjection;
  else if (!g_score.empty()) throw Error(ErrorCode::kInvalidArgument, "unknown --score '" + g_score + "' (variance, projection)");
  eo->view_candidates = g_views;
  eo->view_must_serve_target = g_serve;
  if (g_accuracy_px > 0) eo->accuracy_px = g_accuracy_px;
  if (config == "default") return;
  if (config == "prospective" || config == "prospective-std") {
    // Convergence decided only by the predicted reduction of the best next pose.
    eo->measured_convergence = false;
    if (config == "prospective-std") eo->convergence_measure = EngineOptions::ConvergenceMeasure::kStd;
    return;
  }
  if (config == "default-std") {
    // posecal's engine with the reference implementation's std ratio test.
    eo->convergence_measure = EngineOptions::ConvergenceMeasure::kStd;
    return;
  }
  if (config == "paper" || config == "std") {
    // The paper's rules: one generated pose per target, measured ratio test only, the reference
    // implementation's board distance (about 0.53-0.6 of the view).
    eo->pose_candidates = 1;
    eo->prospective_convergence = false;
    eo->posegen.pinhole_fill = 0.6;
    if (config == "std") eo->convergence_measure = EngineOptions::ConvergenceMeasure::kStd;
    return;
  }
  throw Error(ErrorCode::kInvalidArgument, "unknown --config '" + config + "' (default, default-std, paper, std)");
}

void split_eps_gt(const CameraModel& truth, const CameraModel& estimate, Run* r) {
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

Run closed_loop(const CameraModel& truth, const BoardSpec& target, uint64_t seed, OperatorKind kind,
                const std::string& config, const std::vector<Observation>& test) {
  SimCameraOptions so;
  so.truth = truth;
  so.board = target;
  so.render = render_options(seed);
  so.op.kind = kind;
  so.seed = seed;
  EngineOptions eo;
  eo.board = target;
  eo.robot = kind == OperatorKind::kRobot;
  apply_config(config, &eo);
  eo.target_timeout_frames = (so.op.move_frames + so.op.hold_frames) * so.op.max_tries + 1;
  auto cam = make_sim_camera(so);
  SimCamera* sim = as_sim_camera(cam.get());
  CalibrationSession session(std::move(cam), eo);
  Run r;
  for (int f = 0; f < 3000 && !session.finished(); ++f) session.step(1000);
  const CalibrationEngine& eng = session.engine();
  r.converged = eng.converged();
  r.keyframes = eng.keyframes();
  r.frames = static_cast<int>(session.frames_processed());
  if (eng.result()) {
    const SimEvaluation ev = evaluate_synthetic(eng.estimate(), truth, test);
    r.eps_test = ev.eps_test;
    r.eps_gt = ev.eps_gt;
    split_eps_gt(truth, eng.estimate(), &r);
    r.eps_gt_predicted = predicted_eps_gt(*eng.result());
    r.eps_gt_edges = ground_truth_error_edges(truth, eng.estimate());
    r.expected_error_px = eng.expected_error()->rms_px;
    r.expected_mean_px = eng.expected_error()->mean_px;
    r.expected_p90_px = eng.expected_error()->p90_px;
  }
  r.attempts = sim->op().attempts();
  return r;
}

Run random_baseline(const CameraModel& truth, const BoardSpec& target, uint64_t seed, int n,
                    const std::vector<Observation>& test) {
  const Board board(target);
  SyntheticCamera sc(truth, board, render_options(seed + 1000003));
  ViewSampling vs;
  vs.max_tilt_deg = 45;
  std::vector<std::vector<cv::Point3f>> obj;
  std::vector<std::vector<cv::Point2f>> img;
  std::vector<Observation> frames;
  for (const Pose& p : random_board_views(seed * 7919 + n, n, truth, board, vs)) {
    const Detection d = board.detect(sc.render(p));
    if (d.size() < 6) continue;
    frames.push_back(Observation::from(d));
    obj.emplace_back(d.board_points.begin(), d.board_points.end());
    img.emplace_back(d.image_points.begin(), d.image_points.end());
  }
  Run r;
  r.keyframes = static_cast<int>(obj.size());
  r.frames = n;
  try {
    cv::Mat K, D;
    std::vector<cv::Mat> rv, tv;
    cv::calibrateCamera(obj, img, truth.size(), K, D, rv, tv);
    std::vector<double> d(D.begin<double>(), D.end<double>());
    const CameraModel m = CameraModel::from_opencv(truth.width(), truth.height(), cv::Matx33d(K.ptr<double>()), d);
    const SimEvaluation ev = evaluate_synthetic(m, truth, test);
    r.converged = true;
    r.eps_test = ev.eps_test;
    r.eps_gt = ev.eps_gt;
    split_eps_gt(truth, m, &r);
    r.eps_gt_edges = ground_truth_error_edges(truth, m);
    // Covariance of the same frames through posecal's calibration (equal to OpenCV's solution,
    // tests/core: Calibration.NoWorseThanOpenCVOnTheSameFrames).
    r.eps_gt_predicted = predicted_eps_gt(calibrate(frames, truth.size()));
  } catch (const std::exception&) {
    r.converged = false;
  }
  return r;
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
      SyntheticCamera sc(truth, board, render_options(seed));
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

}  // namespace

int main(int argc, char** argv) {
  Options o;
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
    else if (a == "--config") o.config = next();
    else if (a == "--distortion-tilt") g_distortion_tilt_deg = std::stod(next());
    else if (a == "--score") g_score = next();
    else if (a == "--views") g_views = std::stoi(next());
    else if (a == "--views-serve-target") g_serve = true;
    else if (a == "--accuracy-px") g_accuracy_px = std::stod(next());
    else if (a == "--csv") o.csv = next();
    else if (a == "--figure3") o.figure3 = next();
    else if (a == "--figure3-cameras") o.figure3_cameras = std::stoi(next());
    else {
      std::fprintf(stderr, "unknown option %s\n", a.c_str());
      return 1;
    }
  }
  if (!o.figure3.empty()) {
    figure3(o);
    return 0;
  }
  const CameraModel ref = reference_camera(o.camera);
  const BoardSpec target = board_for(o.camera);
  std::vector<CameraRuns> runs(o.cameras);
  std::atomic<int> next{0};
  std::mutex print;
  auto worker = [&]() {
    for (int i = next++; i < o.cameras; i = next++) {
      CameraRuns& cr = runs[i];
      cr.seed = i + 1;
      const CameraModel truth = sample_camera(ref, 0.1, cr.seed);
      SyntheticCamera test_cam(truth, Board(target), render_options(cr.seed + 7777));
      const std::vector<Observation> test = render_test_set(test_cam);
      cr.person = closed_loop(truth, target, cr.seed, OperatorKind::kPerson, o.config, test);
      cr.robot = closed_loop(truth, target, cr.seed, OperatorKind::kRobot, o.config, test);
      cr.base10 = random_baseline(truth, target, cr.seed, 10, test);
      cr.base20 = random_baseline(truth, target, cr.seed, 20, test);
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

  auto column = [&](auto get) {
    std::vector<double> v;
    for (const auto& r : runs) v.push_back(get(r));
    return v;
  };
  std::printf("\n%d cameras sampled around '%s' (10%% std per parameter), noise 2 grey levels, blur 0.8 px, "
              "engine config '%s'\n\n", o.cameras, o.camera.c_str(), o.config.c_str());
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
  if (!o.csv.empty()) {
    FILE* f = std::fopen(o.csv.c_str(), "w");
    if (!f) {
      std::fprintf(stderr, "cannot write %s\n", o.csv.c_str());
      return 1;
    }
    std::fprintf(f, "seed,method,converged,keyframes,frames,eps_test,eps_gt,eps_gt_pinhole,eps_gt_distortion,eps_gt_predicted,"
                 "eps_gt_edges,expected_error_px,expected_mean_px,expected_p90_px\n");
    for (const auto& r : runs) {
      for (const M m : {M{"person", &CameraRuns::person}, M{"robot", &CameraRuns::robot}, M{"random10", &CameraRuns::base10},
                        M{"random20", &CameraRuns::base20}}) {
        const Run& x = r.*(m.run);
        std::fprintf(f, "%d,%s,%d,%d,%d,%.6f,%.6f,%.6f,%.6f,%.6f,%.6f,%.6f,%.6f,%.6f\n", r.seed, m.name, x.converged,
                     x.keyframes, x.frames, x.eps_test, x.eps_gt, x.eps_gt_pinhole, x.eps_gt_distortion,
                     x.eps_gt_predicted, x.eps_gt_edges, x.expected_error_px, x.expected_mean_px, x.expected_p90_px);
      }
    }
    std::fclose(f);
  }
  return 0;
}
