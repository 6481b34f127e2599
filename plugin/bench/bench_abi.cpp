// Benchmark of libposecal through its C ABI only (docs/performance.md, "Plugin (C ABI)").
//
//   build/bin/posecal_bench_abi [--runs N] [--seed S] [--fps F] [--max-cameras N] [--json]
//
// 1. A full simulated calibration (sim://?seed=S, 1280x720, simulated person): open, step until
//    converged, close; wall time and CPU time (CLOCK_PROCESS_CPUTIME_ID; the runs are
//    sequential, so it is the run's CPU), median and range over N runs. The first result call
//    (which renders the 50-frame test set for eps_test) is timed separately.
// 2. Concurrent cameras: N sessions on N threads, each paced like a camera at F frames per
//    second (frame k is due at t0 + k / F; a session that is late steps at once and so works
//    through its backlog: no frame is dropped). A session keeps up if its mean rate over the
//    whole calibration is at least 99% of F and it converges. The worst lag (in frames) is
//    reported too: the recalibration after a keyframe stalls a session for a few frames, which
//    a camera's queue (4 frames by default) absorbs or drops. N grows from 1 until some session
//    does not keep up; the largest N where all do is reported. The simulated camera renders its
//    frames on the host (~10 ms of CPU per 1280x720 frame), which a real camera would not: the
//    figure is conservative.
#include <time.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <string>
#include <thread>
#include <vector>

#include "bench_common.hpp"
#include "posecal.h"

namespace {

using posecal_bench::Clock;
using posecal_bench::converged;
using posecal_bench::die;
using posecal_bench::since_s;

double cpu_s() { return posecal_bench::clock_s(CLOCK_PROCESS_CPUTIME_ID); }
double median(const std::vector<double>& v) { return posecal_bench::quantile(v, 0.5); }

struct Single {
  double wall_s, cpu_s, result_wall_s;
  int frames;
  bool converged;
};

Single one_calibration(posecal_context* ctx, const std::string& uri) {
  Single r{};
  const auto t0 = Clock::now();
  const double c0 = cpu_s();
  posecal_session* s = nullptr;
  if (posecal_session_open(ctx, uri.c_str(), nullptr, &s) != POSECAL_OK) die("open");
  posecal_status st;
  while ((st = posecal_session_step(s, 1000)) == POSECAL_OK) ++r.frames;
  if (st != POSECAL_E_STATE) die("step");
  r.converged = converged(s);
  r.wall_s = since_s(t0);
  r.cpu_s = cpu_s() - c0;
  const auto t1 = Clock::now();
  std::vector<char> buf(1 << 20);
  size_t size = buf.size();
  if (posecal_session_result(s, buf.data(), &size) != POSECAL_OK) die("result");
  r.result_wall_s = since_s(t1);
  posecal_session_close(s);
  return r;
}

struct Paced {
  int frames = 0;
  double rate_fps = 0;
  double max_lag_frames = 0;
  bool converged = false;
};

// One camera at `fps`: frame k is due at t0 + k / fps. The session is opened before t0 (opening
// a simulated camera builds its ray map, ~0.3 s, which is not part of the frame loop).
void paced_session(posecal_session* s, double fps, Clock::time_point t0, Paced* out) {
  const double period = 1.0 / fps;
  std::this_thread::sleep_until(t0);
  int k = 0;
  double last_start = 0;
  posecal_status st = POSECAL_OK;
  while (true) {
    const double due = k * period;
    double now = since_s(t0);
    if (now < due) {
      std::this_thread::sleep_for(std::chrono::duration<double>(due - now));
      now = since_s(t0);
    } else {
      out->max_lag_frames = std::max(out->max_lag_frames, (now - due) / period);
    }
    st = posecal_session_step(s, 1000);
    if (st != POSECAL_OK) break;
    last_start = now;
    ++k;
  }
  if (st != POSECAL_E_STATE) die("step");
  out->frames = k;
  // Frame k - 1 was due at (k - 1) / fps; on schedule the rate is exactly fps, and every frame
  // that started late lowers it.
  out->rate_fps = k / (last_start + period);
  out->converged = converged(s);
}

struct Trial {
  int cameras;
  bool all_kept_up;
  std::vector<Paced> sessions;
  double cpu_utilisation;  // process CPU / wall, in cores
};

Trial concurrent(posecal_context* ctx, int n, double fps, int seed) {
  Trial t{n, true, std::vector<Paced>(n), 0};
  std::vector<posecal_session*> sessions(n, nullptr);
  for (int i = 0; i < n; ++i) {
    const std::string uri = "sim://?seed=" + std::to_string(seed + i);
    if (posecal_session_open(ctx, uri.c_str(), nullptr, &sessions[i]) != POSECAL_OK) die("open");
  }
  std::vector<std::thread> threads;
  const auto t0 = Clock::now() + std::chrono::milliseconds(20);
  const double c0 = cpu_s();
  for (int i = 0; i < n; ++i) {
    threads.emplace_back(paced_session, sessions[i], fps, t0, &t.sessions[i]);
  }
  for (auto& th : threads) th.join();
  t.cpu_utilisation = (cpu_s() - c0) / std::max(since_s(t0), 1e-9);
  for (posecal_session* s : sessions) posecal_session_close(s);
  for (const Paced& p : t.sessions) {
    const bool ok = p.converged && p.rate_fps >= 0.99 * fps;
    t.all_kept_up = t.all_kept_up && ok;
  }
  return t;
}

}  // namespace

int main(int argc, char** argv) {
  int runs = 5, seed = 1, max_cameras = 12;
  double fps = 15;
  bool json = false;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    auto next = [&] { return posecal_bench::option_value(argc, argv, &i); };
    if (a == "--runs")
      runs = std::max(1, std::atoi(next()));
    else if (a == "--seed")
      seed = std::atoi(next());
    else if (a == "--fps")
      fps = std::atof(next());
    else if (a == "--max-cameras")
      max_cameras = std::max(1, std::atoi(next()));
    else if (a == "--json")
      json = true;
    else {
      std::fprintf(stderr, "usage: %s [--runs N] [--seed S] [--fps F] [--max-cameras N] [--json]\n",
                   argv[0]);
      return 1;
    }
  }
  posecal_context* ctx = nullptr;
  if (posecal_context_create("{\"backends\": [\"sim\"]}", &ctx) != POSECAL_OK) die("context");

  // 1. Single calibration, N runs.
  std::vector<double> walls, cpus, results;
  int frames = 0, converged_runs = 0;
  const std::string uri = "sim://?seed=" + std::to_string(seed);
  for (int r = 0; r < runs; ++r) {
    const Single s = one_calibration(ctx, uri);
    walls.push_back(s.wall_s);
    cpus.push_back(s.cpu_s);
    results.push_back(s.result_wall_s);
    frames = s.frames;
    converged_runs += s.converged;
    if (!json) {
      std::printf("run %d: %d frames, wall %.3f s, cpu %.3f s, first result call %.3f s%s\n", r + 1,
                  s.frames, s.wall_s, s.cpu_s, s.result_wall_s,
                  s.converged ? "" : " (NOT converged)");
    }
  }

  // 2. Concurrent paced cameras.
  std::vector<Trial> trials;
  int capacity = 0;
  for (int n = 1; n <= max_cameras; ++n) {
    const Trial t = concurrent(ctx, n, fps, 100);
    trials.push_back(t);
    if (!json) {
      std::printf("%2d cameras at %.0f fps: %s (cpu %.2f cores)", n, fps,
                  t.all_kept_up ? "all keep up" : "NOT all keep up", t.cpu_utilisation);
      for (const Paced& p : t.sessions) {
        std::printf(" [%.2f fps, lag<=%.1f, %d frames%s]", p.rate_fps, p.max_lag_frames, p.frames,
                    p.converged ? "" : ", not converged");
      }
      std::printf("\n");
    }
    if (!t.all_kept_up) break;
    capacity = n;
  }
  posecal_context_destroy(ctx);

  const unsigned hw = std::thread::hardware_concurrency();
  if (json) {
    std::printf("{\"runs\":%d,\"frames\":%d,\"converged_runs\":%d,", runs, frames, converged_runs);
    std::printf("\"wall_s_median\":%.4f,\"wall_s_min\":%.4f,\"wall_s_max\":%.4f,", median(walls),
                *std::min_element(walls.begin(), walls.end()),
                *std::max_element(walls.begin(), walls.end()));
    std::printf("\"cpu_s_median\":%.4f,\"result_call_s_median\":%.4f,", median(cpus),
                median(results));
    std::printf("\"fps\":%.1f,\"hardware_threads\":%u,\"max_cameras_keeping_up\":%d,\"trials\":[",
                fps, hw, capacity);
    for (size_t i = 0; i < trials.size(); ++i) {
      const Trial& t = trials[i];
      std::printf("%s{\"cameras\":%d,\"all_kept_up\":%s,\"cpu_cores\":%.3f,\"rates\":[",
                  i ? "," : "", t.cameras, t.all_kept_up ? "true" : "false", t.cpu_utilisation);
      for (size_t j = 0; j < t.sessions.size(); ++j) {
        std::printf("%s%.3f", j ? "," : "", t.sessions[j].rate_fps);
      }
      std::printf("],\"max_lag_frames\":[");
      for (size_t j = 0; j < t.sessions.size(); ++j) {
        std::printf("%s%.2f", j ? "," : "", t.sessions[j].max_lag_frames);
      }
      std::printf("]}");
    }
    std::printf("]}\n");
  } else {
    std::printf(
        "full calibration (%s, %d frames): wall median %.3f s [%.3f..%.3f], cpu median %.3f s "
        "over %d runs (%d converged); first result call %.3f s\n",
        uri.c_str(), frames, median(walls), *std::min_element(walls.begin(), walls.end()),
        *std::max_element(walls.begin(), walls.end()), median(cpus), runs, converged_runs,
        median(results));
    std::printf(
        "%u hardware threads: %d simulated 1280x720 cameras at %.0f fps calibrate "
        "concurrently with every session keeping up\n",
        hw, capacity, fps);
  }
  return 0;
}
