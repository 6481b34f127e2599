// How good can k keyframes be? Predicted-information exploration (no rendering, no operator):
// the expected eps_gt (sqrt(trace(G Sigma)), Sigma from exact per-frame information at the true
// intrinsics, 1 px noise) after k keyframes chosen by
//   - rules:   the engine's rules (MaxIOD parameter, best of 6 rule candidates by projection score),
//   - greedy:  the best of a pool of random views (by default the engine's view sampling: tilt up
//              to 40 deg, 40-80% of the width) by the same score: what greedy pose selection
//              reaches when it is not restricted to the paper's families,
//   - random:  k random views as the benchmark's baseline (tilt up to 45 deg),
// each as a ratio to random-10 of the same camera (mean over draws). Both selected sequences
// start with the engine's two initial poses. docs/benchmarks.md, "How good can 9 keyframes be".
//
// and the engine's loop in prediction (MaxIOD, rule candidates plus the first N pool views, the
// prospective and measured ratio tests of core) for both ratio-test measures, with views free to
// win or required to serve the targeted parameter (the engine's rule).
//
//   build/bin/explore_information [--cameras N] [--pool P] [--draws D] [--max-tilt DEG]
//       [--width MIN MAX] [--sampler random|random-engine-margin|sampler] [--screening] [--verbose]
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <map>
#include <string>
#include <vector>

#include <Eigen/Dense>

#include "calib/calibration.hpp"
#include "select/engine.hpp"
#include "select/pose_rules.hpp"
#include "sim/sim_camera.hpp"
#include "select/view_candidates.hpp"
#include "board/views.hpp"
#include "lens/reference_models.hpp"
#include "calib/information.hpp"

using namespace posecal;

namespace {

constexpr int kMaxK = 20;
// Quadratures compared by --screening (nodes along the board's x and y axes).
constexpr int kRules = 4;
constexpr int kRuleNodes[kRules][2] = {{2, 2}, {3, 2}, {2, 3}, {3, 3}};
constexpr int kShortlists[4] = {4, 8, 16, 32};

double median(std::vector<double> v) {
  if (v.empty()) return std::nan("");
  std::sort(v.begin(), v.end());
  const size_t n = v.size();
  return n % 2 ? v[n / 2] : 0.5 * (v[n / 2 - 1] + v[n / 2]);
}

Eigen::MatrixXd inverse(const Eigen::MatrixXd& info) {
  Eigen::MatrixXd reg = info;
  reg.diagonal() += 1e-12 * info.diagonal().cwiseAbs().maxCoeff() * Eigen::VectorXd::Ones(info.rows());
  return reg.ldlt().solve(Eigen::MatrixXd::Identity(info.rows(), info.cols()));
}

double eps(const Eigen::MatrixXd& G, const Eigen::MatrixXd& info) { return std::sqrt((G * inverse(info)).trace()); }

// The pool entry whose information, added to `info`, leaves the lowest expected eps_gt.
size_t best_addition(const Eigen::MatrixXd& G, const Eigen::MatrixXd& info, const std::vector<Eigen::MatrixXd>& pool_info) {
  size_t pick = 0;
  double pick_score = 1e300;
  for (size_t c = 0; c < pool_info.size(); ++c) {
    const double s = eps(G, info + pool_info[c]);
    if (s < pick_score) pick_score = s, pick = c;
  }
  return pick;
}

struct Pick {
  double tilt_deg = 0, width_frac = 0, cx_frac = 0, cy_frac = 0;
};

Pick describe(const CameraModel& m, const Board& board, const Pose& p) {
  Pick k;
  const Eigen::Matrix3d R = p.R();
  k.tilt_deg = std::acos(std::min(1.0, std::abs(R(2, 2)))) * 180.0 / M_PI;
  double x0 = 1e9, x1 = -1e9, y0 = 1e9, y1 = -1e9;
  for (const cv::Point3d& c : board.corners()) {
    Eigen::Vector2d uv;
    if (!m.project(p.apply(Eigen::Vector3d(c.x, c.y, c.z)), &uv)) continue;
    x0 = std::min(x0, uv.x()), x1 = std::max(x1, uv.x()), y0 = std::min(y0, uv.y()), y1 = std::max(y1, uv.y());
  }
  k.width_frac = (x1 - x0) / m.size().width;
  k.cx_frac = (0.5 * (x0 + x1)) / m.size().width - 0.5;
  k.cy_frac = (0.5 * (y0 + y1)) / m.size().height - 0.5;
  return k;
}

struct Outcome {
  int keyframes = 0;
  double eps = 0;
};

// The engine's loop in prediction: MaxIOD parameter, candidates = its 6 rule candidates plus the
// first `n_pool` unused pool views, the best by projection score; prospective test on the chosen
// candidate, then the measured ratio test (core's ratio_test).
Outcome simulate(const CameraModel& truth, const Board& board, const Eigen::MatrixXd& G, const Eigen::MatrixXd& info0,
                 const std::vector<Pose>& pool, const std::vector<Eigen::MatrixXd>& pool_info, int n_pool,
                 EngineOptions::ConvergenceMeasure measure, double threshold, bool serve_target) {
  const std::vector<bool> fixed(9, false);
  PoseGenerator gen(board, truth.size());
  std::vector<bool> converged(9, false), used(pool.size(), false);
  int group_kf[2] = {0, 0};
  Eigen::MatrixXd info = info0;
  int k = 2;
  auto red = [&](double v0, double v1) {
    return measure == EngineOptions::ConvergenceMeasure::kStd ? 1 - std::sqrt(v1 / v0) : 1 - v1 / v0;
  };
  while (k < kMaxK) {
    const Eigen::MatrixXd cov = inverse(info);
    int best = -1;
    double best_iod = -1;
    for (int p = 0; p < 9; ++p) {
      if (converged[p]) continue;
      const double iod = cov(p, p) / std::max(1e-12, std::abs(truth.params()[p]));
      if (iod > best_iod) best_iod = iod, best = p;
    }
    if (best < 0) break;
    const std::vector<TargetPose> cands = gen.candidates(best, truth, 6);
    double pick_score = 1e300, pick_var = 0;
    int pick = -1;  // >= 0: rule candidate; < 0: pool view -(i+1)
    Eigen::MatrixXd pick_info;
    auto consider = [&](const Eigen::MatrixXd& fi, int id) {
      const Eigen::MatrixXd c = inverse(info + fi);
      const double s = (G * c).trace();
      if (s < pick_score) pick_score = s, pick = id, pick_var = c(best, best), pick_info = fi;
    };
    for (size_t c = 0; c < cands.size(); ++c)
      consider(frame_information(truth, cands[c].T_cam_board, board.corners(), fixed), static_cast<int>(c));
    const double rule_var = pick_var;
    int seen = 0;
    for (size_t i = 0; i < pool.size() && seen < n_pool; ++i) {
      if (used[i]) continue;
      ++seen;
      if (serve_target) {
        const Eigen::MatrixXd c = inverse(info + pool_info[i]);
        if (c(best, best) > rule_var) continue;  // must help the targeted parameter as much as the rule pick
      }
      consider(pool_info[i], -static_cast<int>(i) - 1);
    }
    if (red(cov(best, best), pick_var) < threshold) {
      converged[best] = true;
      continue;
    }
    if (pick >= 0) gen.commit(cands[static_cast<size_t>(pick)]);
    else used[static_cast<size_t>(-pick - 1)] = true;
    info += pick_info;
    ++k;
    ++group_kf[static_cast<int>(param_group(best))];
    const Eigen::MatrixXd now = inverse(info);
    std::vector<double> v0(9), v1(9);
    for (int p = 0; p < 9; ++p) v0[p] = cov(p, p), v1[p] = now(p, p);
    for (int p : ratio_test(v0, v1, best, converged, group_kf, threshold, measure)) converged[p] = true;
  }
  return {k, eps(G, info)};
}

}  // namespace

int main(int argc, char** argv) {
  int cameras = 24, pool_size = 600, draws = 10;
  double max_tilt = 40;  // the engine's view sampling (EngineOptions::view_candidates)
  bool verbose = false, screening = false;
  // random: random_board_views with its default 4 px margin; random-engine-margin: the same with
  // the engine's 2% margin; sampler: the engine's ViewSampler.
  std::string sampler_kind = "random";
  double min_width = 0.4, max_width = 0.8;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    auto next = [&] {
      if (i + 1 >= argc) {
        std::fprintf(stderr, "%s needs a value\n", a.c_str());
        std::exit(2);
      }
      return std::string(argv[++i]);
    };
    if (a == "--cameras") cameras = std::stoi(next());
    else if (a == "--pool") pool_size = std::stoi(next());
    else if (a == "--draws") draws = std::stoi(next());
    else if (a == "--max-tilt") max_tilt = std::stod(next());
    else if (a == "--verbose") verbose = true;
    else if (a == "--screening") screening = true;
    else if (a == "--sampler") sampler_kind = next();
    else if (a == "--width") min_width = std::stod(next()), max_width = std::stod(next());
    else {
      std::fprintf(stderr, "unknown option %s\n", a.c_str());
      return 2;
    }
  }
  const Board board(BoardSpec{});
  const std::vector<bool> fixed(9, false);
  std::vector<std::vector<double>> r_rules(kMaxK + 1), r_greedy(kMaxK + 1), r_random(kMaxK + 1);
  std::vector<Pick> greedy_picks;
  std::map<int, std::vector<double>> sim_kf, sim_ratio;
  int screen_cases = 0, screen_hit[kRules][4] = {};
  std::vector<double> screen_loss[kRules][4];
  for (int cam = 1; cam <= cameras; ++cam) {
    const CameraModel truth = sample_camera(c525_reference_model(), 0.1, cam);
    const Eigen::MatrixXd G = projection_gram(truth, fixed, 40, 23);
    auto info_of = [&](const Pose& p) { return frame_information(truth, p, board.corners(), fixed); };

    // Random-k baselines (mean over draws).
    ViewSampling vs45;
    std::vector<double> random_k(kMaxK + 1, 0.0);
    for (int d = 0; d < draws; ++d) {
      const std::vector<Pose> views = random_board_views(static_cast<uint64_t>(cam) * 7919 + d, kMaxK, truth, board, vs45);
      Eigen::MatrixXd info = Eigen::MatrixXd::Zero(9, 9);
      for (int k = 1; k <= kMaxK; ++k) {
        info += info_of(views[k - 1]);
        if (k >= 3) random_k[k] += eps(G, info) / draws;
      }
    }
    const double base = random_k[10];

    // The engine's rules, without convergence tests: after the initial poses, the MaxIOD parameter
    // and the best of its 6 candidates.
    PoseGenerator gen(board, truth.size());
    Eigen::MatrixXd info = info_of(gen.initial_pose(0, truth).T_cam_board) + info_of(gen.initial_pose(1, truth).T_cam_board);
    const Eigen::MatrixXd info_init = info;
    std::vector<double> rules_k(kMaxK + 1, 0.0);
    rules_k[2] = eps(G, info);
    for (int k = 3; k <= kMaxK; ++k) {
      const Eigen::MatrixXd cov = inverse(info);
      int best = 0;
      double best_iod = -1;
      for (int p = 0; p < 9; ++p) {
        const double iod = cov(p, p) / std::max(1e-12, std::abs(truth.params()[p]));
        if (iod > best_iod) best_iod = iod, best = p;
      }
      const std::vector<TargetPose> cands = gen.candidates(best, truth, 6);
      size_t pick = 0;
      double pick_score = 1e300;
      for (size_t c = 0; c < cands.size(); ++c) {
        const double s = eps(G, info + info_of(cands[c].T_cam_board));
        if (s < pick_score) pick_score = s, pick = c;
      }
      gen.commit(cands[pick]);
      info += info_of(cands[pick].T_cam_board);
      rules_k[k] = eps(G, info);
    }

    // Greedy over a pool of random views.
    ViewSampling vsp;
    vsp.max_tilt_deg = max_tilt;
    vsp.min_width_fraction = min_width;
    vsp.max_width_fraction = max_width;
    std::vector<Pose> pool;
    if (sampler_kind == "random" || sampler_kind == "random-engine-margin") {
      if (sampler_kind != "random") vsp.margin_px = 0.02 * std::max(truth.width(), truth.height());
      pool = random_board_views(static_cast<uint64_t>(cam) * 104729, pool_size, truth, board, vsp);
    } else if (sampler_kind == "sampler") {
      // The engine's ViewSampler under the truth, with the engine's margin; views that fail the
      // dense check are dropped.
      ViewSampling vse = vsp;
      vse.margin_px = 0.02 * std::max(truth.width(), truth.height());
      const ViewSampler sampler(truth, board, vse);
      std::mt19937_64 rng(static_cast<uint64_t>(cam) * 104729);
      while (static_cast<int>(pool.size()) < pool_size) {
        const std::optional<Pose> p = sampler.draw(rng);
        if (!p) break;
        if (board_fully_visible(truth, board, *p, vse.margin_px)) pool.push_back(*p);
      }
    } else {
      std::fprintf(stderr, "unknown sampler %s (random, random-engine-margin, sampler)\n", sampler_kind.c_str());
      return 2;
    }
    std::vector<Eigen::MatrixXd> pool_info;
    for (const Pose& p : pool) pool_info.push_back(info_of(p));
    const std::vector<Pose> pool_all = pool;
    const std::vector<Eigen::MatrixXd> pool_info_all = pool_info;
    info = info_init;
    std::vector<double> greedy_k(kMaxK + 1, 0.0);
    greedy_k[2] = eps(G, info);
    for (int k = 3; k <= kMaxK; ++k) {
      const size_t pick = best_addition(G, info, pool_info);
      info += pool_info[pick];
      greedy_k[k] = eps(G, info);
      if (k <= 9) greedy_picks.push_back(describe(truth, board, pool[pick]));
      if (verbose && cam <= 3) {
        const Pick d = describe(truth, board, pool[pick]);
        const Eigen::Vector3d n = pool[pick].R().col(2);
        const Eigen::MatrixXd cov = inverse(info);
        std::fprintf(stderr, "  cam %d k %2d: tilt %4.0f deg (normal %+.2f %+.2f), width %.2f, centre %+.2f %+.2f; eps %.3f;"
                     " sigma fx %.2f fy %.2f cx %.2f cy %.2f k1 %.4f\n", cam, k, d.tilt_deg, n.x(), n.y(), d.width_frac,
                     d.cx_frac, d.cy_frac, greedy_k[k], std::sqrt(cov(0, 0)), std::sqrt(cov(1, 1)), std::sqrt(cov(2, 2)),
                     std::sqrt(cov(3, 3)), std::sqrt(cov(4, 4)));
      }
      pool.erase(pool.begin() + static_cast<long>(pick));
      pool_info.erase(pool_info.begin() + static_cast<long>(pick));
    }
    if (screening) {
      // Along the greedy sequence: draw 300 views with the engine's ViewSampler, score them exactly
      // and on corner_quadrature()'s points, and see whether the exact best is shortlisted.
      std::vector<cv::Point3d> qp[kRules];
      std::vector<double> qw[kRules];
      for (int q = 0; q < kRules; ++q) corner_quadrature(board.corners(), kRuleNodes[q][0], kRuleNodes[q][1], &qp[q], &qw[q]);
      ViewSampling vse = vsp;
      vse.margin_px = 0.02 * std::max(truth.width(), truth.height());
      const ViewSampler sampler(truth, board, vse);
      Eigen::MatrixXd st = info_init;
      std::vector<Pose> seq_pool = pool_all;
      std::vector<Eigen::MatrixXd> seq_info = pool_info_all;
      for (int k = 3; k <= 9; ++k) {
        std::mt19937_64 rng(static_cast<uint64_t>(cam) * 31 + k);
        std::vector<double> exact, approx[kRules];
        for (int v = 0; v < 300; ++v) {
          const std::optional<Pose> p = sampler.draw(rng);
          if (!p || !board_fully_visible(truth, board, *p, vse.margin_px)) continue;
          exact.push_back(eps(G, st + info_of(*p)));
          for (int q = 0; q < kRules; ++q) approx[q].push_back(eps(G, st + frame_information(truth, *p, qp[q], qw[q], fixed)));
        }
        const size_t best = std::min_element(exact.begin(), exact.end()) - exact.begin();
        for (int q = 0; q < kRules; ++q) {
          std::vector<size_t> order(exact.size());
          for (size_t i = 0; i < order.size(); ++i) order[i] = i;
          std::sort(order.begin(), order.end(), [&](size_t a, size_t b) { return approx[q][a] < approx[q][b]; });
          for (int ki = 0; ki < 4; ++ki) {
            const size_t K = std::min(order.size(), static_cast<size_t>(kShortlists[ki]));
            double got = 1e300;
            bool hit = false;
            for (size_t i = 0; i < K; ++i) got = std::min(got, exact[order[i]]), hit |= order[i] == best;
            screen_hit[q][ki] += hit;
            screen_loss[q][ki].push_back(got / exact[best] - 1);
          }
        }
        ++screen_cases;
        // Continue along the greedy sequence.
        const size_t pick = best_addition(G, st, seq_info);
        st += seq_info[pick];
        seq_pool.erase(seq_pool.begin() + static_cast<long>(pick));
        seq_info.erase(seq_info.begin() + static_cast<long>(pick));
      }
    }
    for (int np : {0, 100, 300, 600}) {
      if (screening) break;
      for (auto m : {EngineOptions::ConvergenceMeasure::kVariance, EngineOptions::ConvergenceMeasure::kStd})
      for (bool serve : {false, true}) {
        if (np == 0 && serve) continue;
        const Outcome o = simulate(truth, board, G, info_init, pool_all, pool_info_all, np, m, 0.1, serve);
        const int key = np * 4 + (m == EngineOptions::ConvergenceMeasure::kStd) * 2 + serve;
        sim_kf[key].push_back(o.keyframes);
        sim_ratio[key].push_back(o.eps / base);
      }
    }
    for (int k = 3; k <= kMaxK; ++k) {
      r_rules[k].push_back(rules_k[k] / base);
      r_greedy[k].push_back(greedy_k[k] / base);
      r_random[k].push_back(random_k[k] / base);
    }
    std::fprintf(stderr, "camera %d: random-10 %.3f px/px-noise, rules@9 %.2f greedy@9 %.2f\n", cam, base,
                 rules_k[9] / base, greedy_k[9] / base);
  }
  if (screening) {
    std::printf("screening 300 ViewSampler views on quadrature points, %d choices: exact best in the screened top K,\n"
                "and eps of the best of the top K over the exact best - 1 (median, max)\n", screen_cases);
    for (int q = 0; q < kRules; ++q)
      for (int ki = 0; ki < 4; ++ki)
        std::printf("  %dx%d points, K %2d: %5.1f%%  loss median %.2e max %.2e\n", kRuleNodes[q][0], kRuleNodes[q][1], kShortlists[ki],
                    100.0 * screen_hit[q][ki] / std::max(1, screen_cases), median(screen_loss[q][ki]),
                    *std::max_element(screen_loss[q][ki].begin(), screen_loss[q][ki].end()));
  }
  std::printf("predicted eps_gt / random-10, median over %d cameras (pool %d views, tilt <= %.0f deg)\n", cameras,
              pool_size, max_tilt);
  std::printf("%4s %8s %8s %8s\n", "k", "rules", "greedy", "random");
  for (int k = 3; k <= kMaxK; ++k)
    std::printf("%4d %8.3f %8.3f %8.3f\n", k, median(r_rules[k]), median(r_greedy[k]), median(r_random[k]));
  std::printf("closed loop in prediction (rules + first N pool views), median keyframes / ratio:\n");
  for (const auto& [key, kf] : sim_kf)
    std::printf("  pool %3d %-8s %-12s: %4.1f keyframes (min %2.0f), ratio %.3f (max %.2f)\n", key / 4,
                (key / 2) % 2 ? "std" : "variance", key % 2 ? "serve-target" : "free", median(kf),
                *std::min_element(kf.begin(), kf.end()), median(sim_ratio[key]),
                *std::max_element(sim_ratio[key].begin(), sim_ratio[key].end()));
  std::vector<double> tilt, width, cxf, cyf;
  for (const Pick& p : greedy_picks) {
    tilt.push_back(p.tilt_deg), width.push_back(p.width_frac), cxf.push_back(std::abs(p.cx_frac)),
        cyf.push_back(std::abs(p.cy_frac));
  }
  std::printf("greedy picks 3..9: median tilt %.0f deg, width %.2f of the image, |centre offset| x %.2f y %.2f\n",
              median(tilt), median(width), median(cxf), median(cyf));
  return 0;
}
