// Closed-loop convergence over many seeds and three kinds of camera, both operators
// (issue: pose selection must converge every time). Label: slow.
#include <gtest/gtest.h>

#include <algorithm>
#include <atomic>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "calib/expected_error.hpp"
#include "calib/metrics.hpp"
#include "lens/reference_models.hpp"
#include "session/session.hpp"
#include "sim/sim_camera.hpp"

using namespace posecal;

namespace {

struct Case {
  const char* name;
  CameraModel reference;
  int seeds;
  int checked_params = 9;  // parameters held to the 5-sigma honesty check
  LensModel lens = LensModel::kOpenCV5;  // the model calibrated (the truth's by default)
  // The engine's defaults unless a case says otherwise.
  int view_candidates = EngineOptions{}.view_candidates;
  bool view_must_serve_target = EngineOptions{}.view_must_serve_target;
  EngineOptions::ConvergenceMeasure measure = EngineOptions{}.convergence_measure;
  double max_eps_gt = 0;  // > 0: every converged run's eps_gt must stay below it (pixels)
  // lens_model "auto" (EngineOptions::auto_lens_model): the model every run must end with; the
  // honesty check then needs it to be the truth's.
  bool auto_lens = false;
  std::vector<LensModel> expect_lens = {};  // any of these
  // A run may end at the keyframe cap because the ratio test's stop was refused above
  // EngineOptions::ratio_stop_max_p90_px (and must then say so) instead of converging.
  bool ceiling_may_refuse = false;
  // A run may end at the cap on an estimate that folds inside the image (and must say so).
  bool fold_may_refuse = false;
};

struct Run {
  int seed = 0;
  OperatorKind op = OperatorKind::kPerson;
  CameraModel truth;
  bool has_engine = false;
  bool converged = false;
  std::string state, failure;
  bool has_result = false;
  std::vector<double> params, sigma;
  int keyframes = 0;
  std::vector<std::string> held;
  unsigned long long frames = 0;
  double eps_gt = 0;
  LensModel lens = LensModel::kOpenCV5;  // calibrated
  int points_without_ray = 0;            // of the expected error's grid, under the estimate
};

Run run_one(const Case& c, int seed, OperatorKind op) {
  Run r;
  r.seed = seed;
  r.op = op;
  SimCameraOptions so;
  so.truth = sample_camera(c.reference, 0.1, 100 + seed);
  so.render.noise_sigma = 2.0;
  so.render.blur_sigma_px = 0.8;
  so.render.seed = seed;
  so.seed = seed;
  so.op.kind = op;
  r.truth = so.truth;
  EngineOptions eo;
  eo.robot = op == OperatorKind::kRobot;
  eo.view_candidates = c.view_candidates;
  eo.view_must_serve_target = c.view_must_serve_target;
  eo.convergence_measure = c.measure;
  eo.calibration.lens_model = c.lens;
  eo.auto_lens_model = c.auto_lens;
  eo.target_timeout_frames = (so.op.move_frames + so.op.hold_frames) * so.op.max_tries + 1;
  CalibrationSession s(make_sim_camera(so), eo);
  for (int f = 0; f < 1500 && !s.finished(); ++f) s.step(1000);
  r.frames = s.frames_processed();
  r.has_engine = s.has_engine();
  if (!r.has_engine) return r;
  const CalibrationEngine& e = s.engine();
  r.converged = e.converged();
  r.state = engine_state_name(e.state());
  r.failure = e.failure_reason();
  r.keyframes = e.keyframes();
  if (e.result() == nullptr) return r;
  r.has_result = true;
  r.params.assign(e.result()->model.params().begin(), e.result()->model.params().end());
  r.sigma.assign(e.result()->std_scaled.begin(), e.result()->std_scaled.end());
  r.eps_gt = ground_truth_error(so.truth, e.result()->model);
  r.held = e.result()->held;
  r.lens = e.result()->model.lens_model();
  r.points_without_ray = kExpectedErrorPoints - grid_points_with_ray(e.result()->model);
  return r;
}

// Every (seed, operator) run is independent and single-threaded, so they share the machine's
// cores; the checks run afterwards on the test's own thread.
void run_case(const Case& c) {
  std::vector<std::pair<int, OperatorKind>> jobs;
  for (int seed = 1; seed <= c.seeds; ++seed)
    for (OperatorKind op : {OperatorKind::kPerson, OperatorKind::kRobot}) jobs.emplace_back(seed, op);
  std::vector<Run> runs(jobs.size());
  std::atomic<size_t> next{0};
  auto worker = [&] {
    for (size_t i; (i = next++) < jobs.size();) runs[i] = run_one(c, jobs[i].first, jobs[i].second);
  };
  const unsigned n_threads = std::clamp(std::thread::hardware_concurrency(), 1u, 4u);
  std::vector<std::thread> pool;
  for (unsigned t = 0; t < n_threads; ++t) pool.emplace_back(worker);
  for (std::thread& t : pool) t.join();

  for (const Run& r : runs) {
    const char* who = r.op == OperatorKind::kRobot ? "robot" : "person";
    EXPECT_TRUE(r.has_engine) << c.name << " seed " << r.seed << " " << who << ": no engine";
    if (!r.has_engine) continue;
    if (r.points_without_ray > 0) {
      // An estimate that folds inside the image never converges, and the cap's failure says so.
      EXPECT_FALSE(r.converged) << c.name << " seed " << r.seed << " " << who;
      EXPECT_NE(r.failure.find("folds inside the image"), std::string::npos)
          << c.name << " seed " << r.seed << " " << who << ": " << r.state << " " << r.failure;
      EXPECT_TRUE(c.fold_may_refuse) << c.name << " seed " << r.seed << " " << who << ": "
                                     << r.points_without_ray << " grid points without a ray";
    } else if (c.ceiling_may_refuse && !r.converged) {
      EXPECT_NE(r.failure.find("above ratio_stop_max_p90_px"), std::string::npos)
          << c.name << " seed " << r.seed << " " << who << ": " << r.state << " " << r.failure;
    } else {
      EXPECT_TRUE(r.converged) << c.name << " seed " << r.seed << " " << who << ": " << r.state
                               << " " << r.failure;
    }
    EXPECT_TRUE(r.has_result) << c.name << " seed " << r.seed << " " << who << ": no calibration";
    if (!r.has_result) continue;
    // Converged means honest: every intrinsic within 5 sigma of the truth. (On an 8 degree
    // field of view k2 and k3 are unobservable: sigma in the hundreds, where the linearised
    // covariance no longer describes the error; docs/pose-selection.md.)
    if (!c.expect_lens.empty()) {
      EXPECT_NE(std::find(c.expect_lens.begin(), c.expect_lens.end(), r.lens), c.expect_lens.end())
          << c.name << " seed " << r.seed << " " << who << ": chose " << lens_model_name(r.lens);
    }
    const int checked = r.lens == r.truth.lens_model() ? c.checked_params : 0;
    for (int i = 0; i < checked; ++i) {
      EXPECT_LT(std::abs(r.params[i] - r.truth.params()[i]), 5 * r.sigma[i] + 1e-12)
          << c.name << " seed " << r.seed << " " << who << " " << r.truth.param_names()[i];
    }
    if (c.max_eps_gt > 0) {
      EXPECT_LT(r.eps_gt, c.max_eps_gt) << c.name << " seed " << r.seed << " " << who;
    }
    std::string held;
    for (const std::string& h : r.held) held += " " + h;
    std::printf("%s seed %d %s: %s, %s, %d keyframes, %llu frames, eps_gt %.3f px%s%s\n", c.name,
                r.seed, who, r.state.c_str(), lens_model_name(r.lens), r.keyframes, r.frames,
                r.eps_gt, held.empty() ? "" : ", held:", held.c_str());
  }
}

}  // namespace

TEST(ClosedLoop, CamerasAroundTheC525) { run_case({"c525", c525_reference_model(), 8}); }

TEST(ClosedLoop, IndustrialCameraWithStrongBarrelDistortion) {
  // 2448x2048, 8 mm lens on 3.45 um pixels, k1 = -0.3.
  run_case({"industrial", CameraModel::opencv5(2448, 2048, 2320, 2320, 1223.5, 1023.5, {-0.30, 0.12, 0.0005, -0.0004, -0.02}), 2});
}

TEST(ClosedLoop, LongFocalLowDistortionCamera) {
  // 1600x1200, 50 mm lens: 8 degree field of view. k2 and k3 are all but unobservable, and the
  // expected error's p90 stays near 5-6 px: 4 of these 8 runs end at the keyframe cap, refused by
  // the ceiling on the ratio test's stop, with a realised eps_gt of 1.0-4.0 px (all 8 "converged"
  // before the ceiling: the test asked for it).
  Case c{"tele",
         CameraModel::opencv5(1600, 1200, 11300, 11300, 799.5, 599.5, {-0.02, 0.05, 0.0, 0.0, 0.0}),
         4, 5};
  c.ceiling_may_refuse = true;
  run_case(c);
}

TEST(ClosedLoop, WideAngleRationalCamera) {
  // 2448x2048 with about 110 degrees horizontal field of view, OpenCV's rational model (the form
  // its calibrations of such lenses take: numerator and denominator both large), calibrated as
  // opencv8. The 5-sigma check covers the pinhole part: the rational coefficients are strongly
  // correlated (k1 with k4, ...), their linearised sigma does not describe their error. eps_gt
  // below 3 px: 0.05-1.29 px over these four runs since a held coefficient is a target (before:
  // up to 15.8 px, k4 and k5 held at 0 from the first keyframes on and "converged").
  Case c{
      "wide-rational",
      CameraModel(2448, 2048, LensModel::kOpenCV8,
                  {1224, 1226, 1230.5, 1020.2, 1.5, 0.3, 0.0005, -0.0003, 0.01, 1.85, 0.6, 0.05}),
      2, 4};
  c.lens = LensModel::kOpenCV8;
  c.max_eps_gt = 3.0;
  run_case(c);
}

TEST(ClosedLoop, Fisheye185Degrees) {
  // 1280x1024, 185 degrees across the image circle (Kannala-Brandt, cv::fisheye's k1..k4): the
  // boards go to the rim, beyond 90 degrees from the axis, facing the camera; the start is the
  // equidistant fit. eps_gt over the whole image circle (docs/pose-selection.md, "Fisheye").
  Case c{"fisheye-185",
         CameraModel(1280, 1024, LensModel::kFisheye,
                     {317.1, 317.8, 641.5, 509.3, 0.008, -0.0012, 0.0002, -0.00001}),
         2, 4};
  c.lens = LensModel::kFisheye;
  c.max_eps_gt = 3.0;
  run_case(c);
}

// lens_model "auto" (issue 14): the engine starts from opencv5 and moves by the BIC. On the
// C525 family it must stay with a model no richer than needed; on a 185-degree fisheye it must
// move to the fisheye and reach the forced model's accuracy class.
TEST(ClosedLoop, AutomaticLensModelOnTheC525StaysWithFiveCoefficients) {
  Case c{"c525-auto", c525_reference_model(), 3};
  c.auto_lens = true;
  c.expect_lens = {LensModel::kOpenCV5};
  run_case(c);
}

TEST(ClosedLoop, AutomaticLensModelFindsTheFisheye) {
  Case c{"fisheye-185-auto",
         CameraModel(1280, 1024, LensModel::kFisheye,
                     {317.1, 317.8, 641.5, 509.3, 0.008, -0.0012, 0.0002, -0.00001}),
         2, 4};
  c.auto_lens = true;
  c.expect_lens = {LensModel::kFisheye};
  c.max_eps_gt = 3.0;
  run_case(c);
}

TEST(ClosedLoop, CamerasAroundTheC525WithRulePosesAndTheVarianceTest) {
  // The default until 2026-12-02: the paper's variance ratio test, rule poses only; and the
  // default with views that must serve the targeted parameter.
  Case c{"c525-rules-variance", c525_reference_model(), 4};
  c.view_candidates = 0;
  c.measure = EngineOptions::ConvergenceMeasure::kVariance;
  run_case(c);
  Case serve{"c525-views-serving-std", c525_reference_model(), 2};
  serve.view_candidates = 300;
  serve.view_must_serve_target = true;
  serve.measure = EngineOptions::ConvergenceMeasure::kStd;
  run_case(serve);
}
