// Soak test of libposecal through its C ABI only (docs/performance.md, "Soak"): many simulated
// calibrations back to back in one process, watching resident memory, open descriptors and
// threads for growth.
//
//   build/bin/posecal_soak [--calibrations N] [--threads T] [--sample-every K]
//                          [--max-growth-bytes B] [--result-every R] [--trim 0|1]
//                          [--gate rss|heap] [--leak-bytes L]
//
// Each calibration is real but cheap: sim://?model=VGA&operator=hold-only&seed=S, a 640x480
// webcam with pincushion distortion (the benchmark's "vga" family, written to a temporary model
// file) and the simulated person who holds each pose for 3 frames; open, step until finished
// (converged or not), status, save the calibration to a file, and every R-th calibration the
// result JSON (which renders the 50-frame test set); close. T threads run sessions concurrently
// for the whole run, taking the next calibration from one counter.
//
// One warm-up calibration runs first (OpenCV's thread pool and other lazily created process
// state); the start counts are taken after it. Every K finished calibrations the resident set
// (/proc/self/statm), the open descriptors (/proc/self/fd) and the threads (/proc/self/task) are
// sampled; with --trim 1 the allocator first returns its free memory to the system
// (malloc_trim), so that a sample measures live memory rather than what glibc keeps cached (the
// 60-calibration run in ctest: without it, two samples differed by 4 MB either way from run to
// run). At the end: the table, the RSS growth per calibration (Theil-Sen slope over the
// samples of the second half of the run, without those taken once fewer sessions than threads
// remain), and the descriptors and threads after the workers
// have ended. Each sample also reads the heap in use (glibc's mallinfo2: the bytes of allocated
// chunks in every arena plus the mmapped ones), which a leak raises as it raises the RSS but
// which does not move with what the allocator keeps cached; --gate heap tests its slope instead
// of the RSS's (ctest's short run: over 60 calibrations the RSS after malloc_trim moved between
// 64 and 83 MB and back, CI 2026-12-07, and both RSS estimates read 250-630 KB per calibration
// of a run whose RSS ended 1 MB above its start).
// --leak-bytes L leaks L bytes per calibration on purpose (allocated, written, never freed): the
// check that the gate sees a leak (ctest plugin_soak_sees_a_leak).
// Exit status 1 if the slope exceeds B bytes per calibration (default 1024), if the
// descriptors or threads are not back at their start counts, or if a calibration failed (an ABI
// call returned an error); 2 on a usage error.
#include <dirent.h>
#include <malloc.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <mutex>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "bench_common.hpp"
#include "posecal.h"

namespace {

using Clock = std::chrono::steady_clock;

struct Sample {
  int calibrations = 0;
  double seconds = 0;
  long rss_bytes = 0;
  long heap_bytes = 0;
  int fds = 0;
  int threads = 0;
  int converged = 0;
};

long rss_bytes() {
  long pages_total = 0, pages_resident = 0;
  FILE* f = std::fopen("/proc/self/statm", "r");
  if (f == nullptr) return -1;
  if (std::fscanf(f, "%ld %ld", &pages_total, &pages_resident) != 2) pages_resident = -1;
  std::fclose(f);
  return pages_resident < 0 ? -1 : pages_resident * sysconf(_SC_PAGESIZE);
}

// The heap in use: allocated chunks in every arena plus the chunks mmapped on their own.
long heap_bytes() {
  const struct mallinfo2 m = mallinfo2();
  return static_cast<long>(m.uordblks + m.hblkhd);
}

// Entries of a /proc directory, without "." and "..". The descriptor of the directory listing
// itself is open while counting: it is subtracted for /proc/self/fd.
int count_entries(const char* dir) {
  DIR* d = opendir(dir);
  if (d == nullptr) return -1;
  int n = 0;
  while (dirent* e = readdir(d)) {
    if (std::strcmp(e->d_name, ".") != 0 && std::strcmp(e->d_name, "..") != 0) ++n;
  }
  closedir(d);
  return n;
}

int open_fds() { return count_entries("/proc/self/fd") - 1; }
int threads() { return count_entries("/proc/self/task"); }

// The benchmark's "vga" camera (tests/bench/bench_pose_selection.cpp): 640x480, f ~ 610,
// pincushion distortion.
const char* const kVgaModel =
    "%YAML:1.0\n"
    "---\n"
    "image_width: 640\n"
    "image_height: 480\n"
    "camera_matrix: !!opencv-matrix\n"
    "   rows: 3\n"
    "   cols: 3\n"
    "   dt: d\n"
    "   data: [ 610., 0., 322., 0., 612., 238.5, 0., 0., 1. ]\n"
    "distortion_coefficients: !!opencv-matrix\n"
    "   rows: 1\n"
    "   cols: 5\n"
    "   dt: d\n"
    "   data: [ 0.12, -0.25, 0.001, -0.0015, 0.1 ]\n";

struct Run {
  posecal_context* ctx = nullptr;
  std::string dir;         // temporary files
  std::string model_path;  // the VGA model
  int result_every = 25;
  std::atomic<bool> failed{false};
};

bool fail(Run* run, const std::string& what) {
  std::fprintf(stderr, "calibration failed: %s: %s\n", what.c_str(), posecal_last_error());
  run->failed = true;
  return false;
}

// One calibration; true if it converged. A failed ABI call marks the run as failed.
bool calibrate(Run* run, int index, int worker) {
  const std::string uri = "sim://?model=" + run->model_path +
                          "&operator=hold-only&seed=" + std::to_string(1 + index % 1000);
  posecal_session* s = nullptr;
  if (posecal_session_open(run->ctx, uri.c_str(), nullptr, &s) != POSECAL_OK) {
    return fail(run, "open " + uri);
  }
  posecal_status st;
  while ((st = posecal_session_step(s, 1000)) == POSECAL_OK) {
  }
  bool ok = st == POSECAL_E_STATE;  // finished
  if (!ok) fail(run, "step " + uri);
  std::vector<char> buf(1 << 20);
  size_t size = buf.size();
  bool converged = false;
  if (ok && posecal_session_status(s, buf.data(), &size) == POSECAL_OK) {
    converged = std::strstr(buf.data(), "\"state\":\"converged\"") != nullptr;
  } else if (ok) {
    ok = fail(run, "status " + uri);
  }
  if (ok) {
    // A session that ended before its second keyframe has no calibration (POSECAL_E_STATE).
    const std::string out = run->dir + "/worker" + std::to_string(worker) + ".yml";
    const posecal_status ss = posecal_session_save(s, out.c_str());
    if (ss != POSECAL_OK && ss != POSECAL_E_STATE) ok = fail(run, "save " + uri);
    size = buf.size();
    if (ok && ss == POSECAL_OK && run->result_every > 0 && index % run->result_every == 0 &&
        posecal_session_result(s, buf.data(), &size) != POSECAL_OK) {
      fail(run, "result " + uri);
    }
  }
  posecal_session_close(s);
  return converged;
}

// The Theil-Sen slope of y over x: the median of the slopes between every two samples. One
// sample in four may be off by megabytes (what glibc keeps after malloc_trim varies) without
// moving it; a least-squares slope over 6 samples moved by 169 KB per calibration for one
// sample 3.4 MB high (CI, 2026-12-06).
double slope(const std::vector<double>& x, const std::vector<double>& y) {
  std::vector<double> slopes;
  for (size_t i = 0; i < x.size(); ++i) {
    for (size_t j = i + 1; j < x.size(); ++j) {
      if (x[j] != x[i]) slopes.push_back((y[j] - y[i]) / (x[j] - x[i]));
    }
  }
  return posecal_bench::quantile(std::move(slopes), 0.5);
}

// How fast the floor of y rises over x: the lowest sample of the later half of the samples less
// the lowest of the earlier half, over the distance between the halves' mean x.
double floor_growth(const std::vector<double>& x, const std::vector<double>& y) {
  const size_t half = x.size() / 2;
  double low1 = y[0], low2 = y[half], x1 = 0, x2 = 0;
  for (size_t i = 0; i < x.size(); ++i) {
    if (i < half) {
      low1 = std::min(low1, y[i]);
      x1 += x[i] / static_cast<double>(half);
    } else {
      low2 = std::min(low2, y[i]);
      x2 += x[i] / static_cast<double>(x.size() - half);
    }
  }
  return x2 > x1 ? (low2 - low1) / (x2 - x1) : 0.0;
}

int usage(const char* argv0) {
  std::fprintf(stderr,
               "usage: %s [--calibrations N] [--threads T] [--sample-every K] "
               "[--max-growth-bytes B] [--result-every R] [--trim 0|1] [--gate rss|heap] "
               "[--leak-bytes L]\n",
               argv0);
  return 2;
}

}  // namespace

int main(int argc, char** argv) {
  int calibrations = 1000, nthreads = 1, sample_every = 50;
  double max_growth = 1024;
  bool trim = false, gate_heap = false;
  long leak_bytes = 0;
  Run run;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    if (i + 1 >= argc) return usage(argv[0]);
    const char* v = argv[++i];
    if (a == "--calibrations")
      calibrations = std::atoi(v);
    else if (a == "--threads")
      nthreads = std::atoi(v);
    else if (a == "--sample-every")
      sample_every = std::atoi(v);
    else if (a == "--max-growth-bytes")
      max_growth = std::atof(v);
    else if (a == "--trim")
      trim = std::atoi(v) != 0;
    else if (a == "--result-every")
      run.result_every = std::atoi(v);
    else if (a == "--leak-bytes")
      leak_bytes = std::atol(v);
    else if (a == "--gate" && (std::strcmp(v, "rss") == 0 || std::strcmp(v, "heap") == 0))
      gate_heap = std::strcmp(v, "heap") == 0;
    else
      return usage(argv[0]);
  }
  if (calibrations < 2 || nthreads < 1 || nthreads > 64 || sample_every < 1 || leak_bytes < 0)
    return usage(argv[0]);

  char tmpl[] = "/tmp/posecal_soak_XXXXXX";
  if (mkdtemp(tmpl) == nullptr) {
    std::perror("mkdtemp");
    return 2;
  }
  run.dir = tmpl;
  run.model_path = run.dir + "/vga.yml";
  {
    FILE* f = std::fopen(run.model_path.c_str(), "w");
    if (f == nullptr || std::fputs(kVgaModel, f) < 0 || std::fclose(f) != 0) {
      std::perror("model file");
      return 2;
    }
  }
  if (posecal_context_create("{\"backends\": [\"sim\"]}", &run.ctx) != POSECAL_OK) {
    std::fprintf(stderr, "context: %s\n", posecal_last_error());
    return 2;
  }

  calibrate(&run, 0, 0);  // warm-up
  if (trim) malloc_trim(0);
  const Sample start{0, 0, rss_bytes(), heap_bytes(), open_fds(), threads(), 0};
  std::printf("soak: %d calibrations of sim://?model=vga&operator=hold-only on %d thread(s)\n",
              calibrations, nthreads);
  std::printf("%12s %9s %10s %10s %6s %8s %10s\n", "calibrations", "seconds", "RSS_KiB", "heap_KiB",
              "fds", "threads", "converged");
  std::printf("%12s %9.1f %10ld %10ld %6d %8d %10s\n", "start", 0.0, start.rss_bytes / 1024,
              start.heap_bytes / 1024, start.fds, start.threads, "-");

  std::vector<Sample> samples;
  std::mutex mu;
  std::atomic<int> next{1}, done{0}, converged{0};
  const auto t0 = Clock::now();
  auto worker = [&](int w) {
    while (!run.failed) {
      const int index = next++;
      if (index > calibrations) return;
      if (calibrate(&run, index, w)) ++converged;
      if (leak_bytes > 0) {
        // Deliberately never freed (--leak-bytes); written so that its pages are resident.
        void* leaked = std::malloc(static_cast<size_t>(leak_bytes));
        if (leaked != nullptr) std::memset(leaked, 1, static_cast<size_t>(leak_bytes));
      }
      const int finished = ++done;
      if (finished % sample_every == 0 || finished == calibrations) {
        if (trim) malloc_trim(0);
        Sample s{finished,        std::chrono::duration<double>(Clock::now() - t0).count(),
                 rss_bytes(),     heap_bytes(),
                 open_fds(),      threads(),
                 converged.load()};
        std::lock_guard<std::mutex> lock(mu);
        samples.push_back(s);
        std::printf("%12d %9.1f %10ld %10ld %6d %8d %10d\n", s.calibrations, s.seconds,
                    s.rss_bytes / 1024, s.heap_bytes / 1024, s.fds, s.threads, s.converged);
        std::fflush(stdout);
      }
    }
  };
  std::vector<std::thread> pool;
  for (int w = 0; w < nthreads; ++w) pool.emplace_back(worker, w);
  for (std::thread& t : pool) t.join();
  const double seconds = std::chrono::duration<double>(Clock::now() - t0).count();
  if (trim) malloc_trim(0);
  const Sample end{done.load(), seconds,   rss_bytes(),     heap_bytes(),
                   open_fds(),  threads(), converged.load()};

  std::sort(samples.begin(), samples.end(),
            [](const Sample& a, const Sample& b) { return a.calibrations < b.calibrations; });
  std::vector<double> x, y, heap;
  // The second half of the run, without the samples taken while the workers run out of work
  // (fewer sessions alive than threads: RSS falls, which would hide growth).
  const int last_full = nthreads > 1 ? calibrations - nthreads : calibrations;
  for (const Sample& s : samples) {
    if (2 * s.calibrations > calibrations && s.calibrations <= last_full) {
      x.push_back(s.calibrations);
      y.push_back(static_cast<double>(s.rss_bytes));
      heap.push_back(static_cast<double>(s.heap_bytes));
    }
  }
  const double trend = x.size() >= 2 ? slope(x, y) : 0;
  const double floor_rise = x.size() >= 4 ? floor_growth(x, y) : trend;
  // A leak raises every sample, the floor too; the heap's levels (RSS after malloc_trim moved
  // between 73.8, 77.7 and 80.1 MB and back in one run of 60 calibrations, CI 2026-12-07, so the
  // Theil-Sen slope over 15 samples read 75.8 KB per calibration) leave the floor where it was.
  const double rss_growth = std::min(trend, floor_rise);
  const double heap_growth = x.size() >= 2 ? slope(x, heap) : 0;
  const double growth = gate_heap ? heap_growth : rss_growth;
  std::printf("end: %d calibrations (%d converged) in %.1f s, %.2f s each per thread\n",
              end.calibrations, end.converged, seconds,
              end.calibrations > 0 ? seconds * nthreads / end.calibrations : 0.0);
  std::printf(
      "RSS %ld -> %ld KiB; growth over the second half: %.1f bytes per calibration "
      "(Theil-Sen %.1f, floor %.1f; %zu samples)%s\n",
      start.rss_bytes / 1024, end.rss_bytes / 1024, rss_growth, trend, floor_rise, x.size(),
      gate_heap ? "" : " <- gated");
  std::printf(
      "heap in use %ld -> %ld KiB; growth over the second half: %.1f bytes per calibration "
      "(Theil-Sen)%s\n",
      start.heap_bytes / 1024, end.heap_bytes / 1024, heap_growth, gate_heap ? " <- gated" : "");
  std::printf("limit %.0f bytes per calibration\n", max_growth);
  std::printf("after the workers ended: fds %d (start %d), threads %d (start %d)\n", end.fds,
              start.fds, end.threads, start.threads);

  posecal_context_destroy(run.ctx);
  std::remove(run.model_path.c_str());
  for (int w = 0; w < nthreads; ++w) {
    std::remove((run.dir + "/worker" + std::to_string(w) + ".yml").c_str());
  }
  ::rmdir(run.dir.c_str());

  bool ok = true;
  if (run.failed || end.calibrations != calibrations) {
    std::printf("FAIL: a calibration failed\n");
    ok = false;
  }
  if (x.size() < 2) {
    std::printf("FAIL: fewer than 2 samples in the second half (lower --sample-every)\n");
    ok = false;
  }
  if (growth > max_growth) {
    std::printf("FAIL: %s grows by %.1f bytes per calibration (limit %.0f)\n",
                gate_heap ? "the heap in use" : "RSS", growth, max_growth);
    ok = false;
  }
  if (end.fds != start.fds || end.threads != start.threads) {
    std::printf("FAIL: descriptors or threads not back at their start counts\n");
    ok = false;
  }
  if (ok) std::printf("PASS\n");
  return ok ? 0 : 1;
}
