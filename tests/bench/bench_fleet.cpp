// The fleet benchmark (issue 15; docs/benchmarks.md, "The fleet prior and fleet outliers"):
// what a production line's earlier units buy the next ones.
//
//   build/bin/bench_fleet [--fleet N] [--next N] [--defects N] [--normal N] [--threads T]
//       [--operator NAME] [--pp-spread PX] [--focal-spread REL] [--k-spread REL]
//       [--alpha A] [--csv FILE]
//
// A production lot of one camera model and lens: units sampled around the C525 reference with a
// unit-to-unit spread (focal length 0.5%, aspect 0.1%, principal point --pp-spread px per axis,
// k1..k3 3% of their value, p1 p2 0.0002; docs/benchmarks.md says why), each calibrated
// closed-loop on the synthetic camera (ray casting, noise 2 grey levels, blur 0.8 px) by a
// simulated person ("hold-only" by default: holds 3 frames per try, bootstraps with a centred
// board tilted 10-25 degrees).
//   1. The fleet: --fleet units (seeds 2001..) calibrated with the default engine, no prior; the
//      converged ones are the passed units (the records' fleet).
//   2. The next --next units (seeds 3001..), each three ways on the same camera and operator
//      draws: "none" the default engine; "prior@unit" the fleet prior stopping at the expected
//      error (90th percentile) that this unit reached without it; "prior" the fleet prior with
//      the session's default stop, the fleet's median expected error. Keyframes, the realised
//      eps_gt (edge-to-edge 40x23 grid, mean distance) and the expected error.
//   3. Outliers: --defects units with cx 3% larger and --defects with k1 of the opposite sign
//      (seeds 4001..), and --normal normal units (seeds 5001..), each calibrated without and with
//      the prior, tested against the fleet at probability --alpha (records/fleet.hpp).
#include <Eigen/Dense>
#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <functional>
#include <mutex>
#include <optional>
#include <random>
#include <string>
#include <thread>
#include <vector>

#include "calib/expected_error.hpp"
#include "calib/metrics.hpp"
#include "lens/reference_models.hpp"
#include "records/fleet.hpp"
#include "session/session.hpp"
#include "sim/sim_camera.hpp"

using namespace posecal;

namespace {

struct Options {
  int fleet = 30, next = 30, defects = 10, normal = 100, threads = 2;
  std::string op = "hold-only";
  double pp_spread_px = 1.5, focal_spread = 0.005, k_spread = 0.03, alpha = 0.001;
  std::string csv;
  // --deconvolve F: the prior's covariance is the fleet's minus its units' mean own covariance
  // (empirical Bayes), its eigenvalues relative to the fleet's floored at F (an experiment).
  double deconvolve = -1;
};

// One unit of the lot: the reference with this unit's deviations.
CameraModel sample_unit(const Options& o, uint64_t seed) {
  const CameraModel ref = c525_reference_model();
  std::mt19937_64 rng(seed * 7919 + 17);
  std::normal_distribution<double> z;
  for (int attempt = 0;; ++attempt) {
    std::vector<double> p = ref.params();
    const double f = 1 + o.focal_spread * z(rng);
    p[0] *= f;
    p[1] *= f * (1 + 0.001 * z(rng));
    p[2] += o.pp_spread_px * z(rng);
    p[3] += o.pp_spread_px * z(rng);
    p[4] *= 1 + o.k_spread * z(rng);
    p[5] *= 1 + o.k_spread * z(rng);
    p[6] += 0.0002 * z(rng);
    p[7] += 0.0002 * z(rng);
    p[8] *= 1 + o.k_spread * z(rng);
    CameraModel m(ref.width(), ref.height(), ref.lens_model(), p);
    if (m.is_valid() || attempt > 100) return m;
  }
}

bool g_trace = false;

struct Run {
  std::optional<CalibrationResult> result;
  std::vector<Observation> observations;  // the keyframes (outlier phase only)
  CalibrationOptions options;
  bool calibrated = false, converged = false;
  int keyframes = 0, frames = 0;
  double eps_gt = NAN, p90 = NAN, sigma = NAN;
  std::vector<double> values;
};

Run calibrate_unit(const Options& o, const CameraModel& truth, uint64_t seed,
                   const std::optional<IntrinsicsPrior>& prior, std::optional<double> accuracy_px) {
  SimCameraOptions so;
  so.truth = truth;
  so.render.noise_sigma = 2.0;
  so.render.blur_sigma_px = 0.8;
  so.render.renderer = Renderer::kRayCast;
  so.render.seed = seed;
  so.op = operator_preset(o.op);
  so.seed = seed;
  so.board = BoardSpec{};
  EngineOptions eo;
  eo.board = so.board;
  eo.robot = so.op.kind == OperatorKind::kRobot;
  eo.target_timeout_frames = (so.op.move_frames + so.op.hold_frames) * so.op.max_tries + 1;
  eo.calibration.prior = prior;
  eo.accuracy_px = accuracy_px;
  CalibrationSession session(make_sim_camera(so), eo);
  if (g_trace) {
    session.set_event_callback([](const SessionEvent& e) {
      if (e.engine && (e.engine->kind == EngineEvent::Kind::kCalibrated ||
                       e.engine->kind == EngineEvent::Kind::kTargetChanged ||
                       e.engine->kind == EngineEvent::Kind::kKeyframeRejected))
        std::printf("  [%d] %s %s: %s\n", e.engine->keyframes, engine_event_name(e.engine->kind),
                    e.engine->parameter.c_str(), e.engine->message.c_str());
    });
  }
  for (int f = 0; f < 3000 && !session.finished(); ++f) session.step(1000);
  Run r;
  const CalibrationEngine& eng = session.engine();
  r.converged = eng.converged();
  r.keyframes = eng.keyframes();
  r.frames = static_cast<int>(session.frames_processed());
  if (eng.result()) {
    r.calibrated = true;
    r.eps_gt = ground_truth_error_edges(truth, eng.estimate());
    r.p90 = eng.expected_error()->p90_px;
    r.sigma = std::sqrt(eng.result()->residual_variance);
    r.values = eng.estimate().params();
    r.result = *eng.result();
    r.observations = eng.keyframe_observations();
    r.options = eng.options().calibration;
  }
  return r;
}

// Runs job(i) for i in [0, n) on `threads` threads.
void parallel(int n, int threads, const std::function<void(int)>& job) {
  std::atomic<int> next{0};
  std::vector<std::thread> pool;
  for (int t = 0; t < threads; ++t) {
    pool.emplace_back([&] {
      for (int i; (i = next++) < n;) job(i);
    });
  }
  for (auto& t : pool) t.join();
}

double quantile(std::vector<double> v, double q) {
  v.erase(std::remove_if(v.begin(), v.end(), [](double x) { return !std::isfinite(x); }), v.end());
  if (v.empty()) return NAN;
  std::sort(v.begin(), v.end());
  const double pos = q * static_cast<double>(v.size() - 1);
  const size_t lo = static_cast<size_t>(std::floor(pos)), hi = std::min(v.size() - 1, lo + 1);
  return v[lo] + (pos - static_cast<double>(lo)) * (v[hi] - v[lo]);
}

// The median with a 95% percentile-bootstrap interval (2000 resamples, fixed seed).
std::string median_ci(const std::vector<double>& v, const char* fmt) {
  std::mt19937_64 rng(12345);
  std::vector<double> meds;
  std::uniform_int_distribution<size_t> pick(0, v.empty() ? 0 : v.size() - 1);
  for (int b = 0; b < 2000 && !v.empty(); ++b) {
    std::vector<double> s(v.size());
    for (double& x : s) x = v[pick(rng)];
    meds.push_back(quantile(s, 0.5));
  }
  char buf[128], a[32], lo[32], hi[32];
  std::snprintf(a, sizeof a, fmt, quantile(v, 0.5));
  std::snprintf(lo, sizeof lo, fmt, quantile(meds, 0.025));
  std::snprintf(hi, sizeof hi, fmt, quantile(meds, 0.975));
  std::snprintf(buf, sizeof buf, "%s [%s, %s]", a, lo, hi);
  return buf;
}

template <class F>
std::vector<double> column(const std::vector<Run>& runs, F f) {
  std::vector<double> out;
  for (const Run& r : runs) out.push_back(f(r));
  return out;
}

void print_row(const char* name, const std::vector<Run>& runs) {
  int conv = 0;
  for (const Run& r : runs) conv += r.converged;
  const auto kf = column(runs, [](const Run& r) { return static_cast<double>(r.keyframes); });
  const auto gt = column(runs, [](const Run& r) { return r.eps_gt; });
  const auto p90 = column(runs, [](const Run& r) { return r.p90; });
  const auto frames = column(runs, [](const Run& r) { return static_cast<double>(r.frames); });
  std::printf("| %s | %s | %.0f | %.0f | %s | %.3f | %s | %d/%zu |\n", name,
              median_ci(kf, "%.1f").c_str(), quantile(kf, 0.9), quantile(frames, 0.5),
              median_ci(gt, "%.3f").c_str(), quantile(gt, 0.9), median_ci(p90, "%.3f").c_str(),
              conv, runs.size());
}

bool parse(int argc, char** argv, Options* o) {
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    auto val = [&]() -> std::string {
      if (i + 1 >= argc) throw Error(ErrorCode::kInvalidArgument, a + " needs a value");
      return argv[++i];
    };
    if (a == "--fleet")
      o->fleet = std::stoi(val());
    else if (a == "--next")
      o->next = std::stoi(val());
    else if (a == "--defects")
      o->defects = std::stoi(val());
    else if (a == "--normal")
      o->normal = std::stoi(val());
    else if (a == "--threads")
      o->threads = std::max(1, std::stoi(val()));
    else if (a == "--operator")
      o->op = val();
    else if (a == "--pp-spread")
      o->pp_spread_px = std::stod(val());
    else if (a == "--focal-spread")
      o->focal_spread = std::stod(val());
    else if (a == "--k-spread")
      o->k_spread = std::stod(val());
    else if (a == "--alpha")
      o->alpha = std::stod(val());
    else if (a == "--csv")
      o->csv = val();
    else if (a == "--deconvolve")
      o->deconvolve = std::stod(val());
    else {
      std::fprintf(stderr, "unknown argument %s (see the comment at the top of bench_fleet.cpp)\n",
                   a.c_str());
      return false;
    }
  }
  return true;
}

}  // namespace

int main(int argc, char** argv) {
  Options o;
  try {
    if (!parse(argc, argv, &o)) return 2;
    operator_preset(o.op);
  } catch (const std::exception& e) {
    std::fprintf(stderr, "bench_fleet: %s\n", e.what());
    return 2;
  }
  const LensModel lens = c525_reference_model().lens_model();
  const std::vector<std::string>& names = intrinsic_names(lens);
  std::printf(
      "bench_fleet: operator %s, spread: focal %.2f%%, principal point %.2f px, k %.1f%%; alpha "
      "%g\n",
      o.op.c_str(), 100 * o.focal_spread, o.pp_spread_px, 100 * o.k_spread, o.alpha);

  // 1. The fleet.
  std::vector<Run> fleet_runs(o.fleet);
  parallel(o.fleet, o.threads, [&](int i) {
    const uint64_t seed = 2001 + i;
    fleet_runs[i] = calibrate_unit(o, sample_unit(o, seed), seed, std::nullopt, std::nullopt);
  });
  std::vector<FleetUnit> units;
  std::vector<double> sigmas, p90s;
  for (size_t i = 0; i < fleet_runs.size(); ++i) {
    const Run& r = fleet_runs[i];
    if (!r.converged) continue;
    units.push_back({std::to_string(i), std::to_string(2001 + i), r.values});
    sigmas.push_back(r.sigma);
    p90s.push_back(r.p90);
  }
  std::printf("fleet: %zu of %d units passed (converged)\n", units.size(), o.fleet);
  IntrinsicsPrior prior;
  FleetStatistics stats;
  try {
    prior = fleet_prior(lens, units, quantile(sigmas, 0.5));
    prior.image_size = c525_reference_model().size();
    stats = fleet_statistics(names, units);
  } catch (const std::exception& e) {
    std::fprintf(stderr, "bench_fleet: %s\n", e.what());
    return 1;
  }
  if (o.deconvolve >= 0) {
    // S^-1/2 (S - C) S^-1/2 = I - S^-1/2 C S^-1/2, its eigenvalues floored.
    const Eigen::Index m = prior.covariance.rows();
    Eigen::MatrixXd c = Eigen::MatrixXd::Zero(m, m);
    int n = 0;
    for (const Run& r : fleet_runs) {
      if (!r.converged) continue;
      const Eigen::MatrixXd cs = r.result->covariance_scaled();
      for (Eigen::Index a = 0; a < m; ++a)
        for (Eigen::Index b = 0; b < m; ++b) {
          const auto ia = std::find(names.begin(), names.end(), prior.names[a]) - names.begin();
          const auto ib = std::find(names.begin(), names.end(), prior.names[b]) - names.begin();
          c(a, b) += cs(ia, ib);
        }
      ++n;
    }
    c /= n;
    Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd> es(prior.covariance);
    const Eigen::MatrixXd half = es.eigenvectors() * es.eigenvalues().cwiseSqrt().asDiagonal() *
                                 es.eigenvectors().transpose();
    const Eigen::MatrixXd ihalf = half.inverse();
    Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd> w(Eigen::MatrixXd::Identity(m, m) -
                                                     ihalf * c * ihalf);
    const Eigen::VectorXd ev = w.eigenvalues().cwiseMax(o.deconvolve);
    prior.covariance =
        half * w.eigenvectors() * ev.asDiagonal() * w.eigenvectors().transpose() * half;
    std::printf("deconvolved prior (floor %.2f): eigenvalues kept", o.deconvolve);
    for (Eigen::Index a = 0; a < m; ++a) std::printf(" %.2f", w.eigenvalues()[a]);
    std::printf("\n");
  }
  const double fleet_p90 = quantile(p90s, 0.5);
  std::printf(
      "fleet prior: noise %.3f px, default stop (median expected error p90) %.3f px; spread "
      "(measured):",
      prior.noise_px, fleet_p90);
  for (size_t a = 0; a < stats.names.size(); ++a)
    std::printf(" %s %.4g", stats.names[a].c_str(),
                std::sqrt(stats.covariance[a * stats.names.size() + a]));
  std::printf("\n");
  {
    CalibrationOptions co;
    co.prior = prior;
    const CalibrationResult pr = prior_result(prior.image_size, co);
    const ExpectedError pe = expected_error(pr);
    std::printf("the prior alone: expected error %.3f px (p90 %.3f px), limited by %s (%.0f%%)\n\n",
                pe.rms_px, pe.p90_px,
                pe.limiting_param >= 0 ? names[pe.limiting_param].c_str() : "-",
                100 * pe.limiting_share);
  }
  if (std::getenv("BENCH_FLEET_TRACE")) {
    g_trace = true;
    calibrate_unit(o, sample_unit(o, 3001), 3001, prior, fleet_p90);
    g_trace = false;
    calibrate_unit(o, sample_unit(o, 3001), 3001, std::nullopt, std::nullopt);
    return 0;
  }

  // 2. The next units, three ways.
  std::vector<Run> none(o.next), at_unit(o.next), dflt(o.next);
  parallel(o.next, o.threads, [&](int i) {
    const uint64_t seed = 3001 + i;
    const CameraModel truth = sample_unit(o, seed);
    none[i] = calibrate_unit(o, truth, seed, std::nullopt, std::nullopt);
    const std::optional<double> goal = std::isfinite(none[i].p90)
                                           ? std::optional<double>(none[i].p90)
                                           : std::optional<double>(fleet_p90);
    at_unit[i] = calibrate_unit(o, truth, seed, prior, goal);
    dflt[i] = calibrate_unit(o, truth, seed, prior, fleet_p90);
  });
  std::printf(
      "| next %d units | keyframes, median [95%% CI] | p90 | frames | eps_gt px, median [95%% CI] "
      "| eps_gt p90 | "
      "expected p90 px | converged |\n|---|---|---|---|---|---|---|---|\n",
      o.next);
  print_row("no prior (default engine)", none);
  print_row("fleet prior, stop at the unit's own expected error", at_unit);
  print_row("fleet prior, stop at the fleet's median (session default)", dflt);
  for (const auto* p : {&at_unit, &dflt}) {
    std::vector<double> ratio;
    int no_worse = 0, n = 0;
    for (int i = 0; i < o.next; ++i) {
      if (!std::isfinite(none[i].eps_gt) || !std::isfinite((*p)[i].eps_gt)) continue;
      ratio.push_back((*p)[i].eps_gt / none[i].eps_gt);
      no_worse += (*p)[i].eps_gt <= none[i].eps_gt;
      ++n;
    }
    std::printf("%s: eps_gt / no prior, paired: median %s, p90 %.2f; no worse on %d of %d\n",
                p == &at_unit ? "prior@unit" : "prior", median_ci(ratio, "%.2f").c_str(),
                quantile(ratio, 0.9), no_worse, n);
  }

  // 3. Outliers.
  struct Tested {
    std::string kind;
    Run plain, with_prior;
    FleetPosition pos_plain, pos_prior;
    bool prior_data_only = false;  // the prior run's keyframes were tested without the prior
  };
  std::vector<Tested> tested(2 * o.defects + o.normal);
  parallel(static_cast<int>(tested.size()), o.threads, [&](int i) {
    Tested& t = tested[i];
    uint64_t seed;
    CameraModel truth;
    if (i < 2 * o.defects) {
      seed = 4001 + i;
      truth = sample_unit(o, seed);
      if (i < o.defects) {
        t.kind = "cx +3%";
        truth.params()[2] *= 1.03;
      } else {
        t.kind = "k1 sign";
        truth.params()[4] = -truth.params()[4];
      }
    } else {
      seed = 5001 + (i - 2 * o.defects);
      truth = sample_unit(o, seed);
      t.kind = "normal";
    }
    t.plain = calibrate_unit(o, truth, seed, std::nullopt, std::nullopt);
    t.with_prior = calibrate_unit(o, truth, seed, prior, fleet_p90);
    bool data_only = false;
    if (t.plain.calibrated) t.pos_plain = fleet_position(stats, names, t.plain.values, o.alpha);
    if (t.with_prior.calibrated) {
      t.pos_prior = fleet_position_of(stats, *t.with_prior.result, t.with_prior.observations,
                                      t.with_prior.options, o.alpha, &data_only);
      t.prior_data_only = data_only;
    }
    t.plain.result.reset();
    t.with_prior.result.reset();
    t.plain.observations.clear();
    t.with_prior.observations.clear();
  });
  // How far past its bound the unit is, by the test nearer to flagging it (records/fleet.hpp:
  // the joint distance, or the parameter most off): above 1 is flagged.
  const auto margin = [](const FleetPosition& p) {
    const double z = p.deviations.empty() ? 0.0 : std::abs(p.deviations[0].second);
    return std::max(p.distance / p.threshold, z / p.parameter_threshold);
  };
  std::printf(
      "\n| units | flagged without the prior | flagged with the prior | the test nearer its "
      "bound: figure / bound, median [min, max] |\n|---|---|---|---|\n");
  for (const char* kind : {"cx +3%", "k1 sign", "normal"}) {
    int n = 0, f0 = 0, f1 = 0, data_only = 0;
    std::vector<double> rel;
    for (const Tested& t : tested) {
      if (t.kind != kind) continue;
      ++n;
      f0 += t.plain.calibrated && t.pos_plain.outlier;
      f1 += t.with_prior.calibrated && t.pos_prior.outlier;
      data_only += t.prior_data_only;
      if (t.plain.calibrated) rel.push_back(margin(t.pos_plain));
      if (t.with_prior.calibrated) rel.push_back(margin(t.pos_prior));
    }
    std::printf("| %s (%d) | %d | %d (%d tested without the prior) | %.2f [%.2f, %.2f] |\n", kind,
                n, f0, f1, data_only, quantile(rel, 0.5), quantile(rel, 0.0), quantile(rel, 1.0));
  }
  if (!o.csv.empty()) {
    std::ofstream csv(o.csv);
    csv << "phase,seed,config,converged,keyframes,frames,eps_gt,expected_p90,distance,threshold,"
           "z_max,parameter_threshold,outlier\n";
    auto line = [&](const char* phase, int seed, const char* config, const Run& r,
                    const FleetPosition* pos) {
      csv << phase << ',' << seed << ',' << config << ',' << r.converged << ',' << r.keyframes
          << ',' << r.frames << ',' << r.eps_gt << ',' << r.p90 << ','
          << (pos ? pos->distance : NAN) << ',' << (pos ? pos->threshold : NAN) << ','
          << (pos && !pos->deviations.empty() ? std::abs(pos->deviations[0].second) : NAN) << ','
          << (pos ? pos->parameter_threshold : NAN) << ',' << (pos ? pos->outlier : false) << '\n';
    };
    for (int i = 0; i < o.fleet; ++i) line("fleet", 2001 + i, "none", fleet_runs[i], nullptr);
    for (int i = 0; i < o.next; ++i) {
      line("next", 3001 + i, "none", none[i], nullptr);
      line("next", 3001 + i, "prior@unit", at_unit[i], nullptr);
      line("next", 3001 + i, "prior", dflt[i], nullptr);
    }
    for (size_t i = 0; i < tested.size(); ++i) {
      const Tested& t = tested[i];
      const int seed = static_cast<int>(i) < 2 * o.defects
                           ? 4001 + static_cast<int>(i)
                           : 5001 + static_cast<int>(i) - 2 * o.defects;
      line(t.kind.c_str(), seed, "none", t.plain, t.plain.calibrated ? &t.pos_plain : nullptr);
      line(t.kind.c_str(), seed, "prior", t.with_prior,
           t.with_prior.calibrated ? &t.pos_prior : nullptr);
    }
  }
  return 0;
}
