// posecal's own share of a station's CPU (issue 18, item 3; docs/performance.md, "Many cameras
// on one station"), through the C ABI only.
//
//   build/bin/posecal_bench_station [--sequences K] [--seed S] [--fps F] [--max-cameras N]
//                                   [--config JSON] [--window S] [--overload-queue D]
//
// 1. Recording (not timed): K simulated calibrations (sim://?seed=S.., 1280x720, simulated
//    person) are stepped to the end and every frame they processed is kept, in order. Fed in
//    the same order to an "external" session with the same configuration, a sequence leads the
//    engine through the same states to the same result (the engine sees only the frames), so
//    the frames are rendered once, outside every timed loop: a real camera renders nothing on
//    the host.
// 2. CPU per frame: each sequence fed to one external session on one thread, first with the
//    whole frame searched every time ("track_board": false), then as configured (--config, the
//    sessions' JSON config; default none, i.e. tracking on), side by side;
//    posecal_session_feed timed with the thread's CPU clock (CLOCK_THREAD_CPUTIME_ID; OpenCV's
//    and Ceres' worker threads, if any, are not in it: the process CPU over the whole sequence is
//    reported beside it). Median, 90th percentile and maximum over all frames.
// 3. Cameras at F fps: N external sessions on N threads, session i fed sequence i mod K, frame k
//    due at t0_i + k / F for S seconds (--window, default 12), session after session; the
//    cameras' starts t0_i are spread over 2 s, since independent cameras do not capture keyframes
//    in the same frame as copies of one recording started together would (a late session feeds
//    at once and works through its backlog). A camera keeps up if its mean rate is at least 99%
//    of F and every session it fed to the end converged; N grows until one does not.
// 4. Overloaded (unless --overload-queue 0): twice that many cameras, each frame arriving into a
//    queue of D frames (default 4, a camera's default) that drops the oldest, one session each
//    (starts spread over 1 s); reports the share of each camera's frames processed (even or not)
//    and how many still converge on a recording with frames missing.
#include <time.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <numeric>
#include <string>
#include <thread>
#include <vector>

#include "bench_common.hpp"
#include "posecal.h"

namespace {

using Clock = posecal_bench::Clock;
using Frame = std::vector<unsigned char>;
using posecal_bench::clock_s;
using posecal_bench::converged;
using posecal_bench::die;
using posecal_bench::quantile;
using posecal_bench::since_s;

// The status's "board_search" object, as JSON text.
std::string board_search(posecal_session* s) {
  const std::string st = posecal_bench::status_json(s);
  const size_t at = st.find("\"board_search\":");
  if (at == std::string::npos) return "?";
  const size_t end = st.find('}', at);
  return st.substr(at + 15, end == std::string::npos ? 0 : end + 1 - (at + 15));
}

constexpr int kWidth = 1280, kHeight = 720;

struct Sequence {
  int seed = 0;
  std::vector<Frame> frames;
  bool converged = false;
};

Sequence record(posecal_context* ctx, int seed) {
  Sequence q;
  q.seed = seed;
  const std::string uri = "sim://?seed=" + std::to_string(seed);
  posecal_session* s = nullptr;
  if (posecal_session_open(ctx, uri.c_str(), nullptr, &s) != POSECAL_OK) die("open");
  posecal_status st;
  while ((st = posecal_session_step(s, 1000)) == POSECAL_OK) {
    Frame f(static_cast<size_t>(kWidth) * kHeight);
    posecal_image img{sizeof(posecal_image), kWidth,  kHeight, kWidth,
                      POSECAL_PIXEL_MONO8,   f.data()};
    if (posecal_session_last_frame(s, &img) != POSECAL_OK) die("last_frame");
    q.frames.push_back(std::move(f));
  }
  if (st != POSECAL_E_STATE) die("step");
  q.converged = converged(s);
  posecal_session_close(s);
  return q;
}

posecal_session* open_external(posecal_context* ctx, const std::string& config) {
  posecal_session* s = nullptr;
  if (posecal_session_open(ctx, "external", config.empty() ? nullptr : config.c_str(), &s) !=
      POSECAL_OK)
    die("open external");
  return s;
}

// Feeds frame k of `q`; false once the session has finished (POSECAL_E_STATE).
bool feed(posecal_session* s, const Sequence& q, size_t k) {
  posecal_image img{sizeof(posecal_image),
                    kWidth,
                    kHeight,
                    kWidth,
                    POSECAL_PIXEL_MONO8,
                    const_cast<unsigned char*>(q.frames[k].data())};
  const posecal_status st = posecal_session_feed(s, &img);
  if (st == POSECAL_E_STATE) return false;
  if (st != POSECAL_OK) die("feed");
  return true;
}

struct Paced {
  long frames = 0;
  double rate_fps = 0;
  int sessions = 0, converged = 0;  // sessions fed to their end
};

// One camera for `window_s` seconds from t0: recording q fed at fps, frame g of the camera due at
// t0 + g / fps, session after session (a new one opened when the recording ends), so every
// camera is busy for the whole window whatever its recording's length.
void paced(posecal_context* ctx, const std::string& config, const Sequence* q, double fps,
           Clock::time_point t0, double window_s, Paced* out) {
  const double period = 1.0 / fps;
  std::this_thread::sleep_until(t0);
  double last_start = 0;
  long g = 0;
  for (bool more_time = true; more_time;) {
    posecal_session* s = open_external(ctx, config);
    size_t k = 0;
    for (; k < q->frames.size(); ++k, ++g) {
      const double due = static_cast<double>(g) * period;
      if (due >= window_s) {
        more_time = false;
        break;
      }
      double now = since_s(t0);
      if (now < due) {
        std::this_thread::sleep_for(std::chrono::duration<double>(due - now));
        now = since_s(t0);
      }
      last_start = now;
      if (!feed(s, *q, k)) {
        ++g;
        break;
      }
    }
    if (more_time) {
      ++out->sessions;
      out->converged += converged(s) ? 1 : 0;
    }
    posecal_session_close(s);
  }
  out->frames = g;
  out->rate_fps = static_cast<double>(g) / (last_start + period);
}

// An overloaded station (more cameras than keep up): frame k arrives at t0 + k / fps into a queue
// of `depth` frames that drops the oldest, as a camera's queue does (CameraConfig::queue_depth,
// default 4); the session takes the oldest queued frame when it is free. Every camera drops its
// own excess, so the cores are shared between the cameras and none is stalled.
struct Dropping {
  int processed = 0, dropped = 0;
  bool converged = false;
};

void dropping(posecal_session* s, const Sequence* q, double fps, int depth, Clock::time_point t0,
              Dropping* out) {
  const double period = 1.0 / fps;
  const auto frames = static_cast<long>(q->frames.size());
  std::this_thread::sleep_until(t0);
  long k = 0;
  while (k < frames) {
    const double now = since_s(t0);
    const long newest = std::min(frames - 1, static_cast<long>(now / period));
    if (newest < k) {
      std::this_thread::sleep_for(
          std::chrono::duration<double>(static_cast<double>(k) * period - now));
      continue;
    }
    if (newest - k >= depth) {  // the queue is full: the oldest frames are gone
      out->dropped += static_cast<int>(newest - k - depth + 1);
      k = newest - depth + 1;
    }
    ++out->processed;
    if (!feed(s, *q, static_cast<size_t>(k++))) break;
  }
  out->converged = converged(s);
}

}  // namespace

int main(int argc, char** argv) {
  int sequences = 3, seed = 100, max_cameras = 16;
  double fps = 15;
  std::string config_tracked;  // the sessions' config (JSON), default none: tracking on
  int overload_depth = 4;      // 0: no overload run
  double window_s = 12;        // each camera count runs this long
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    auto next = [&] { return posecal_bench::option_value(argc, argv, &i); };
    if (a == "--sequences")
      sequences = std::max(1, std::atoi(next()));
    else if (a == "--seed")
      seed = std::atoi(next());
    else if (a == "--fps")
      fps = std::max(1.0, std::atof(next()));
    else if (a == "--max-cameras")
      max_cameras = std::max(1, std::atoi(next()));
    else if (a == "--config")
      config_tracked = next();
    else if (a == "--window")
      window_s = std::max(3.0, std::atof(next()));
    else if (a == "--overload-queue")
      overload_depth = std::max(0, std::atoi(next()));
    else {
      std::fprintf(stderr,
                   "usage: %s [--sequences K] [--seed S] [--fps F] [--max-cameras N] [--config "
                   "JSON] [--window S] [--overload-queue D]\n",
                   argv[0]);
      return 1;
    }
  }
  posecal_context* ctx = nullptr;
  if (posecal_context_create("{\"backends\": [\"sim\", \"external\"]}", &ctx) != POSECAL_OK)
    die("context");

  std::vector<Sequence> qs;
  for (int i = 0; i < sequences; ++i) {
    qs.push_back(record(ctx, seed + i));
    std::printf("recorded sim://?seed=%d: %zu frames, %s\n", qs.back().seed,
                qs.back().frames.size(), qs.back().converged ? "converged" : "NOT converged");
  }

  // 2. CPU per frame, one session at a time: the whole frame searched every time, then tracked
  // (the default), side by side.
  const std::string whole_frame = R"({"track_board": false})";
  for (const std::string& config : {whole_frame, config_tracked}) {
    std::printf("%s:\n", config == whole_frame
                             ? "whole-frame search (track_board false)"
                             : ("external sessions " +
                                (config.empty() ? std::string("(the default: tracked)") : config))
                                   .c_str());
    std::vector<double> per_frame, per_frame_all;
    for (const Sequence& q : qs) {
      posecal_session* s = open_external(ctx, config);
      std::vector<double> mine, all_threads;
      for (size_t k = 0; k < q.frames.size(); ++k) {
        const double c0 = clock_s(CLOCK_THREAD_CPUTIME_ID), a0 = clock_s(CLOCK_PROCESS_CPUTIME_ID);
        const bool more = feed(s, q, k);
        mine.push_back(1e3 * (clock_s(CLOCK_THREAD_CPUTIME_ID) - c0));
        all_threads.push_back(1e3 * (clock_s(CLOCK_PROCESS_CPUTIME_ID) - a0));
        if (!more) break;
      }
      const bool ok = converged(s);
      const std::string search = board_search(s);
      posecal_session_close(s);
      std::printf(
          "seed %d fed: %zu frames, %s; thread CPU per frame median %.2f ms, p90 %.2f ms, "
          "max %.1f ms; process CPU per frame median %.2f ms, mean %.2f ms; board searches %s\n",
          q.seed, mine.size(), ok ? "converged" : "NOT converged", quantile(mine, 0.5),
          quantile(mine, 0.9), quantile(mine, 1.0), quantile(all_threads, 0.5),
          std::accumulate(all_threads.begin(), all_threads.end(), 0.0) /
              static_cast<double>(all_threads.size()),
          search.c_str());
      per_frame.insert(per_frame.end(), mine.begin(), mine.end());
      per_frame_all.insert(per_frame_all.end(), all_threads.begin(), all_threads.end());
    }
    std::printf(
        "all sequences: thread CPU per frame median %.2f ms, p90 %.2f ms; process CPU (OpenCV's "
        "and Ceres' worker threads included) median %.2f ms, p90 %.2f ms; over %zu frames\n",
        quantile(per_frame, 0.5), quantile(per_frame, 0.9), quantile(per_frame_all, 0.5),
        quantile(per_frame_all, 0.9), per_frame.size());
  }

  // 3. Cameras at fps, all busy for the same window.
  int capacity = 0;
  for (int n = 1; n <= max_cameras; ++n) {
    std::vector<Paced> out(static_cast<size_t>(n));
    std::vector<std::thread> threads;
    const auto t0 = Clock::now() + std::chrono::milliseconds(20);
    const double c0 = clock_s(CLOCK_PROCESS_CPUTIME_ID);
    for (int i = 0; i < n; ++i) {
      // Independent cameras do not capture in the same frame: the starts are spread over 2 s.
      const auto start = t0 + std::chrono::milliseconds(2000 * i / n);
      threads.emplace_back(paced, ctx, config_tracked, &qs[static_cast<size_t>(i % sequences)], fps,
                           start, window_s, &out[static_cast<size_t>(i)]);
    }
    for (auto& t : threads) t.join();
    const double cores = (clock_s(CLOCK_PROCESS_CPUTIME_ID) - c0) / std::max(1e-9, since_s(t0));
    bool all = true;
    int sessions = 0, ok = 0;
    std::printf("%2d cameras at %.0f fps (cpu %.2f cores):", n, fps, cores);
    for (const Paced& p : out) {
      all = all && p.converged == p.sessions && p.rate_fps >= 0.99 * fps;
      sessions += p.sessions;
      ok += p.converged;
      std::printf(" %.2f", p.rate_fps);
    }
    std::printf(" fps; %d of %d sessions converged; %s\n", ok, sessions,
                all ? "all keep up" : "NOT all keep up");
    if (!all) break;
    capacity = n;
  }
  std::printf("cameras at %.0f fps that keep up on %u hardware threads: %d\n", fps,
              std::thread::hardware_concurrency(), capacity);

  // 4. Overloaded: twice the cameras that keep up, each behind its own dropping queue.
  if (overload_depth > 0 && capacity > 0) {
    const int n = 2 * capacity;
    std::vector<posecal_session*> ss(static_cast<size_t>(n));
    for (auto& s : ss) s = open_external(ctx, config_tracked);
    std::vector<Dropping> out(static_cast<size_t>(n));
    std::vector<std::thread> threads;
    const auto t0 = Clock::now() + std::chrono::milliseconds(20);
    for (int i = 0; i < n; ++i) {
      threads.emplace_back(dropping, ss[static_cast<size_t>(i)],
                           &qs[static_cast<size_t>(i % sequences)], fps, overload_depth,
                           t0 + std::chrono::milliseconds(1000 * i / n),
                           &out[static_cast<size_t>(i)]);
    }
    for (auto& t : threads) t.join();
    for (auto* s : ss) posecal_session_close(s);
    std::vector<double> share;
    int ok = 0;
    for (int i = 0; i < n; ++i) {
      const Dropping& d = out[static_cast<size_t>(i)];
      share.push_back(static_cast<double>(d.processed) / std::max(1, d.processed + d.dropped));
      ok += d.converged ? 1 : 0;
    }
    std::printf(
        "overloaded: %d cameras at %.0f fps, queues of %d dropping the oldest: share of frames "
        "processed per camera min %.2f, median %.2f, max %.2f; %d of %d converged within their "
        "recording\n",
        n, fps, overload_depth, quantile(share, 0), quantile(share, 0.5), quantile(share, 1), ok,
        n);
  }
  posecal_context_destroy(ctx);
  return 0;
}
