// posecal's own share of a station's CPU (issue 18, item 3; docs/performance.md, "Many cameras
// on one station"), through the C ABI only.
//
//   build/bin/posecal_bench_station [--sequences K] [--seed S] [--fps F] [--max-cameras N]
//
// 1. Recording (not timed): K simulated calibrations (sim://?seed=S.., 1280x720, simulated
//    person) are stepped to the end and every frame they processed is kept, in order. Fed in
//    the same order to an "external" session with the same configuration, a sequence leads the
//    engine through the same states to the same result (the engine sees only the frames), so
//    the frames are rendered once, outside every timed loop: a real camera renders nothing on
//    the host.
// 2. CPU per frame: each sequence fed to one external session on one thread,
//    posecal_session_feed timed with the thread's CPU clock (CLOCK_THREAD_CPUTIME_ID; OpenCV's
//    and Ceres' worker threads, if any, are not in it: the process CPU over the whole sequence is
//    reported beside it). Median, 90th percentile and maximum over all frames.
// 3. Cameras at F fps: N external sessions on N threads, session i fed sequence i mod K, frame k
//    due at t0 + k / F (a late session feeds at once and works through its backlog). A session
//    keeps up if its mean rate is at least 99% of F and it converges, as in posecal_bench_abi;
//    N grows until one does not.
#include <time.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <string>
#include <thread>
#include <vector>

#include "posecal.h"

namespace {

using Clock = std::chrono::steady_clock;
using Frame = std::vector<unsigned char>;

double clock_s(clockid_t id) {
  timespec ts{};
  clock_gettime(id, &ts);
  return static_cast<double>(ts.tv_sec) + 1e-9 * static_cast<double>(ts.tv_nsec);
}

double since_s(Clock::time_point t0) {
  return std::chrono::duration<double>(Clock::now() - t0).count();
}

void die(const char* what) {
  std::fprintf(stderr, "%s: %s\n", what, posecal_last_error());
  std::exit(2);
}

bool converged(posecal_session* s) {
  std::vector<char> buf(1 << 16);
  size_t size = buf.size();
  if (posecal_session_status(s, buf.data(), &size) != POSECAL_OK) die("status");
  return std::strstr(buf.data(), "\"state\":\"converged\"") != nullptr;
}

double quantile(std::vector<double> v, double q) {
  if (v.empty()) return 0;
  std::sort(v.begin(), v.end());
  const double at = q * static_cast<double>(v.size() - 1);
  const auto lo = static_cast<size_t>(at);
  const size_t hi = std::min(lo + 1, v.size() - 1);
  return v[lo] + (at - static_cast<double>(lo)) * (v[hi] - v[lo]);
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

posecal_session* open_external(posecal_context* ctx) {
  posecal_session* s = nullptr;
  if (posecal_session_open(ctx, "external", nullptr, &s) != POSECAL_OK) die("open external");
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
  int frames = 0;
  double rate_fps = 0;
  bool converged = false;
};

void paced(posecal_session* s, const Sequence* q, double fps, Clock::time_point t0, Paced* out) {
  const double period = 1.0 / fps;
  std::this_thread::sleep_until(t0);
  double last_start = 0;
  size_t k = 0;
  for (; k < q->frames.size(); ++k) {
    const double due = static_cast<double>(k) * period;
    double now = since_s(t0);
    if (now < due) {
      std::this_thread::sleep_for(std::chrono::duration<double>(due - now));
      now = since_s(t0);
    }
    if (!feed(s, *q, k)) break;
    last_start = now;
  }
  out->frames = static_cast<int>(k);
  out->rate_fps = static_cast<double>(k) / (last_start + period);
  out->converged = converged(s);
}

}  // namespace

int main(int argc, char** argv) {
  int sequences = 3, seed = 100, max_cameras = 16;
  double fps = 15;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    auto next = [&]() -> const char* {
      if (i + 1 >= argc) {
        std::fprintf(stderr, "%s needs a value\n", a.c_str());
        std::exit(1);
      }
      return argv[++i];
    };
    if (a == "--sequences")
      sequences = std::max(1, std::atoi(next()));
    else if (a == "--seed")
      seed = std::atoi(next());
    else if (a == "--fps")
      fps = std::max(1.0, std::atof(next()));
    else if (a == "--max-cameras")
      max_cameras = std::max(1, std::atoi(next()));
    else {
      std::fprintf(stderr, "usage: %s [--sequences K] [--seed S] [--fps F] [--max-cameras N]\n",
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

  // 2. CPU per frame, one session at a time.
  std::vector<double> per_frame;
  for (const Sequence& q : qs) {
    posecal_session* s = open_external(ctx);
    const double p0 = clock_s(CLOCK_PROCESS_CPUTIME_ID);
    std::vector<double> mine;
    for (size_t k = 0; k < q.frames.size(); ++k) {
      const double c0 = clock_s(CLOCK_THREAD_CPUTIME_ID);
      const bool more = feed(s, q, k);
      mine.push_back(1e3 * (clock_s(CLOCK_THREAD_CPUTIME_ID) - c0));
      if (!more) break;
    }
    const double process_ms = 1e3 * (clock_s(CLOCK_PROCESS_CPUTIME_ID) - p0);
    const bool ok = converged(s);
    posecal_session_close(s);
    std::printf(
        "seed %d fed: %zu frames, %s; thread CPU per frame median %.2f ms, p90 %.2f ms, "
        "max %.1f ms; process CPU %.1f ms per frame\n",
        q.seed, mine.size(), ok ? "converged" : "NOT converged", quantile(mine, 0.5),
        quantile(mine, 0.9), quantile(mine, 1.0), process_ms / static_cast<double>(mine.size()));
    per_frame.insert(per_frame.end(), mine.begin(), mine.end());
  }
  std::printf("all sequences: thread CPU per frame median %.2f ms, p90 %.2f ms over %zu frames\n",
              quantile(per_frame, 0.5), quantile(per_frame, 0.9), per_frame.size());

  // 3. Cameras at fps.
  int capacity = 0;
  for (int n = 1; n <= max_cameras; ++n) {
    std::vector<posecal_session*> ss(static_cast<size_t>(n));
    for (auto& s : ss) s = open_external(ctx);
    std::vector<Paced> out(static_cast<size_t>(n));
    std::vector<std::thread> threads;
    const auto t0 = Clock::now() + std::chrono::milliseconds(20);
    const double c0 = clock_s(CLOCK_PROCESS_CPUTIME_ID);
    for (int i = 0; i < n; ++i) {
      threads.emplace_back(paced, ss[static_cast<size_t>(i)],
                           &qs[static_cast<size_t>(i % sequences)], fps, t0,
                           &out[static_cast<size_t>(i)]);
    }
    for (auto& t : threads) t.join();
    const double cores = (clock_s(CLOCK_PROCESS_CPUTIME_ID) - c0) / std::max(1e-9, since_s(t0));
    for (auto* s : ss) posecal_session_close(s);
    bool all = true;
    std::printf("%2d cameras at %.0f fps (cpu %.2f cores):", n, fps, cores);
    for (const Paced& p : out) {
      const bool ok = p.converged && p.rate_fps >= 0.99 * fps;
      all = all && ok;
      std::printf(" [%.2f fps%s]", p.rate_fps, p.converged ? "" : ", not converged");
    }
    std::printf(" %s\n", all ? "all keep up" : "NOT all keep up");
    if (!all) break;
    capacity = n;
  }
  std::printf("cameras at %.0f fps that keep up on %u hardware threads: %d\n", fps,
              std::thread::hardware_concurrency(), capacity);
  posecal_context_destroy(ctx);
  return 0;
}
