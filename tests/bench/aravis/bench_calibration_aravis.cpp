// Calibration on many cameras: how many GigE Vision cameras one machine streams at 15 fps each
// while a calibration session runs on every one.
//
// For N = 1, 2, 3, ... : N simulated cameras (Aravis' GigE Vision simulator, in this process, one
// thread each) on 127.0.0.1 ... 127.0.0.N, each sending the board of its own operator (an
// engine-guided simulated person or robot and a renderer, tests/aravis/guided_loop.hpp; 1280x720
// Mono8, noise 2, blur 0.8, a camera sampled around the C525 per seed) at the simulator's frame
// rate (--fps); N sessions, each on its own thread, open their camera through
// make_aravis_backend() by address and calibrate until convergence. By default the operators
// run free: one step per frame the camera sends, with the latest guidance, rendered ahead on a
// thread per camera (GuidedScene::prepare_next), so the camera's clock paces everything, a
// session that falls behind misses frames, and a renderer that falls behind makes its camera
// send the previous image again ("late"). --lockstep 1 couples operator and engine as the
// tests do, which puts the renderer's latency into every step. It stops after the
// first N at which a camera fails (no convergence, a result outside 5 sigma, a frame not
// bit-identical to what was sent) or falls below the frame rate (see usage()).
//
// Each simulator needs its own address, so the program re-executes itself under `unshare -n`
// (a private network namespace; root only), brings that namespace's loopback up and adds the
// addresses there; the machine's own interfaces are never touched.
//
// CPU: getrusage(RUSAGE_SELF) over the round, split into the session threads' CPU time (engine,
// session, frame checks; CLOCK_THREAD_CPUTIME_ID at their end), the simulators' (their threads,
// read in the fill callbacks: copying and sending, and on loopback the kernel's receive work,
// which runs in the sender's context; plus the render threads) and the rest (Aravis' stream
// threads, the backend's pump, supervisor and heartbeat). OpenCV's own worker threads are off by
// default (--opencv-threads 0), so that each session and each simulator is one thread and this
// split holds.
//
//   bench_calibration_aravis [--fps 15] [--max-cameras 8] [--only N] [--operator person|robot]
//                            [--seed 1] [--limit-s 180] [--supersample 2] [--opencv-threads 0]
//                            [--lockstep 0] [--udp-socket 0]
#include <arv.h>
#include <sys/resource.h>
#include <time.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <opencv2/core/utility.hpp>
#include <string>
#include <thread>
#include <vector>

#include "guided_aravis.hpp"
#include "netns.hpp"
#include "posecal/aravis_backend.hpp"
#include "common/error.hpp"
#include "calib/metrics.hpp"
#include "session/session.hpp"

using namespace posecal;
using namespace posecal::testing;
using Clock = std::chrono::steady_clock;

namespace {

struct Args {
  double fps = 15;
  int max_cameras = 8;
  int only = 0;  // > 0: just this N
  OperatorKind kind = OperatorKind::kPerson;
  uint64_t seed = 1;  // camera i uses seed + i
  double limit_s = 180;
  int supersample = 2;  // the renderer's (the simulators' CPU cost; 1 is ~2.4x cheaper)
  // OpenCV's own worker threads: 0 runs its functions on the calling thread, so that every
  // session and simulator is one thread and the CPU accounting per thread holds.
  int opencv_threads = 0;
  // false: free-running operators (one step per frame the camera sends; the engine must keep up
  // with the camera). true: lockstep as in the tests (a step per frame the engine processed, so
  // the renderer's latency is part of every step).
  bool lockstep = false;
  bool udp_socket = false;  // Aravis' UDP socket instead of its packet socket (packet_socket=0)
};

// A camera keeps up if its stream delivers at least kStreamFraction of the frame rate and its
// session processes new frames at no less than kEngineFraction of the frame rate over the whole
// session and at the full rate in the median second (see usage()).
constexpr double kStreamFraction = 0.98;
constexpr double kEngineFraction = 0.95;

void usage() {
  std::fprintf(
      stderr,
      "usage: bench_calibration_aravis [--fps F] [--max-cameras N] [--only N] "
      "[--operator person|robot] [--seed S] [--limit-s S] [--supersample 1|2]\n"
      "       [--opencv-threads 0] [--lockstep 0|1] [--udp-socket 0|1]\n"
      "Root only (private network namespace). A camera fails if its session does not converge,\n"
      "puts an intrinsic outside 5 sigma of the truth or processes a frame that is not\n"
      "bit-identical to the one sent. It falls below the frame rate if its stream delivers less\n"
      "than %.0f%% of --fps complete frames per second, or its session processes new frames at\n"
      "less than %.0f%% of --fps over the session or at less than --fps in the median second.\n"
      "A new frame is lost either in the session (missed: it arrived, the session never took\n"
      "it) or in the simulator (late: its renderer was not ready, the camera sent the previous\n"
      "image again, which happens when the machine is short of CPU).\n",
      100 * kStreamFraction, 100 * kEngineFraction);
}

bool parse(int argc, char** argv, Args* a) {
  for (int i = 1; i < argc; ++i) {
    const std::string k = argv[i];
    if (i + 1 >= argc) return false;
    const char* v = argv[++i];
    if (k == "--fps") {
      a->fps = std::atof(v);
    } else if (k == "--max-cameras") {
      a->max_cameras = std::atoi(v);
    } else if (k == "--only") {
      a->only = std::atoi(v);
    } else if (k == "--operator") {
      if (std::string(v) == "robot") {
        a->kind = OperatorKind::kRobot;
      } else if (std::string(v) != "person") {
        return false;
      }
    } else if (k == "--seed") {
      a->seed = std::strtoull(v, nullptr, 10);
    } else if (k == "--limit-s") {
      a->limit_s = std::atof(v);
    } else if (k == "--supersample") {
      a->supersample = std::atoi(v);
    } else if (k == "--udp-socket") {
      a->udp_socket = std::string(v) == "1";
    } else if (k == "--lockstep") {
      a->lockstep = std::string(v) == "1";
    } else if (k == "--opencv-threads") {
      a->opencv_threads = std::atoi(v);

    } else {
      return false;
    }
  }
  return a->fps > 0 && a->supersample >= 1 && a->supersample <= 4 && a->max_cameras >= 1 &&
         a->max_cameras <= 250 && a->only >= 0 && a->only <= 250 && a->limit_s > 0;
}

double cpu_seconds() {
  rusage u{};
  getrusage(RUSAGE_SELF, &u);
  return u.ru_utime.tv_sec + u.ru_stime.tv_sec + 1e-6 * (u.ru_utime.tv_usec + u.ru_stime.tv_usec);
}

double thread_cpu_seconds() {
  timespec ts{};
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
  return ts.tv_sec + 1e-9 * ts.tv_nsec;
}

std::string load_average() {
  std::ifstream in("/proc/loadavg");
  std::string one, five, fifteen;
  in >> one >> five >> fifteen;
  return one + " " + five + " " + fifteen;
}

double median(std::vector<double> v) {
  if (v.empty()) return 0;
  std::sort(v.begin(), v.end());
  return v.size() % 2 ? v[v.size() / 2] : 0.5 * (v[v.size() / 2 - 1] + v[v.size() / 2]);
}

// The simulator thread's CPU time between its first and its latest fill.
struct SimulatorCpu {
  std::atomic<double> first{-1};
  std::atomic<double> latest{0};
  double seconds() const { return first.load() < 0 ? 0 : latest.load() - first.load(); }
};

struct CameraRun {
  uint64_t seed = 0;
  EngineState state = EngineState::kWaitingForBoard;
  bool honest = false;
  int keyframes = 0;
  uint64_t frames = 0;    // processed by the engine
  uint64_t received = 0;  // complete frames from the stream (processed, repeats, queue drops)
  uint64_t incomplete = 0;
  uint64_t missed = 0;  // frames the camera sent that the engine never processed
  uint64_t late = 0;    // frames sent again because the next one was not rendered in time
                        // (lockstep: because the engine had not processed the last one)
  uint64_t exact = 0;
  double session_s = 0;  // first frame to the end
  double eps_gt = -1;
  double thread_cpu_s = 0;      // the session thread's CPU time (engine, session, frame checks)
  std::vector<double> frame_s;  // when each frame was processed, from the first
  std::string problem;

  // Frames processed in each whole second after the first frame; their median.
  double median_second_fps() const {
    std::vector<double> counts(static_cast<size_t>(session_s), 0.0);
    for (double t : frame_s) {
      if (t < counts.size()) counts[static_cast<size_t>(t)] += 1;
    }
    return median(counts);
  }

  double engine_fps() const { return session_s > 0 ? (frames - 1) / session_s : 0; }
  double stream_fps() const { return session_s > 0 ? received / session_s : 0; }
  bool ok() const {
    return state == EngineState::kConverged && honest && exact == frames && problem.empty();
  }
};

// One camera's session, run on its own thread until convergence, failure or the time limit. The
// session (and with it the stream) ends when the calibration does.
void run_session(std::unique_ptr<GuidedCamera> guided, const std::shared_ptr<GuidedScene>& scene,
                 double limit_s, CameraRun* out) {
  try {
    GuidedCamera* cam = guided.get();
    CalibrationSession s(std::move(guided), engine_options_for(scene->options()));
    const auto t_start = Clock::now();
    Clock::time_point t_first{};
    bool first = false;
    while (!s.finished() && Clock::now() - t_start < std::chrono::duration<double>(limit_s)) {
      const StepStatus st = s.step(2000);
      if (st == StepStatus::kFrame) {
        if (!first) {
          first = true;
          t_first = Clock::now();
        }
        out->frame_s.push_back(std::chrono::duration<double>(Clock::now() - t_first).count());
      }
      if (st == StepStatus::kDisconnected || st == StepStatus::kEndOfStream) {
        out->problem = std::string("stream ended: ") + step_status_name(st);
        break;
      }
    }
    const auto t_end = Clock::now();
    const CameraStats cs = cam->stats();
    const GuidedCameraStats g = cam->guided_stats();
    out->frames = s.frames_processed();
    out->received = g.delivered + g.repeats_skipped + cs.frames_dropped;
    out->incomplete = cs.frames_incomplete;
    out->missed = g.step_gaps;
    out->late = scene->stats().repeats;
    out->exact = g.exact;
    out->session_s = first ? std::chrono::duration<double>(t_end - t_first).count() : 0;
    if (!cam->first_problem().empty()) out->problem = cam->first_problem();
    if (s.has_engine()) {
      const CalibrationEngine& e = s.engine();
      out->state = e.state();
      out->keyframes = e.keyframes();
      if (const CalibrationResult* r = e.result()) {
        const CameraModel& truth = scene->truth();
        out->eps_gt = ground_truth_error(truth, r->model);
        out->honest = true;
        for (int i = 0; i < truth.num_params(); ++i) {
          out->honest &=
              std::abs(r->model.params()[i] - truth.params()[i]) < 5 * r->std_scaled[i] + 1e-12;
        }
      }
    }
  } catch (const std::exception& e) {
    out->problem = e.what();
  }
  out->thread_cpu_s = thread_cpu_seconds();  // the thread started with this session
}

struct Round {
  int cameras = 0;
  std::vector<CameraRun> runs;
  double cpu_s = 0, simulator_cpu_s = 0, session_cpu_s = 0, wall_s = 0;
};

Round run_round(const Args& args, int n) {
  Round round;
  round.cameras = n;
  std::vector<std::shared_ptr<GuidedScene>> scenes;
  std::vector<std::unique_ptr<SimulatorCpu>> sim_cpu;
  std::vector<std::unique_ptr<FakeGvCamera>> fakes;
  for (int i = 0; i < n; ++i) {
    GuidedSceneOptions options = c525_scene(args.seed + i, args.kind);
    options.render.supersample = args.supersample;
    options.lockstep = args.lockstep;
    scenes.push_back(std::make_shared<GuidedScene>(options, mono8_encoder()));
    sim_cpu.push_back(std::make_unique<SimulatorCpu>());
    auto source = guided_source(scenes.back());
    SimulatorCpu* cpu = sim_cpu.back().get();
    auto timed = [source, cpu](uint64_t id, PixelFormat f, const cv::Rect& roi) {
      double expected = -1;
      cpu->first.compare_exchange_strong(expected, thread_cpu_seconds());
      auto payload = source(id, f, roi);
      cpu->latest = thread_cpu_seconds();
      return payload;
    };
    const std::string address = "127.0.0." + std::to_string(i + 1);
    fakes.push_back(
        std::make_unique<FakeGvCamera>("PCAL-B" + std::to_string(i + 1), address, timed));
    if (!fakes.back()->start()) throw Error(ErrorCode::kDevice, "no simulator on " + address);
  }
  // Free-running operators render ahead on a thread per camera, so that each simulator sends
  // on its clock's tick (GuidedScene::prepare_next).
  std::vector<std::thread> renderers;
  std::vector<double> render_cpu(n, 0.0);
  if (!args.lockstep) {
    for (int i = 0; i < n; ++i) {
      renderers.emplace_back([scene = scenes[i], cpu = &render_cpu[i]] {
        while (scene->prepare_next()) {
        }
        *cpu = thread_cpu_seconds();
      });
    }
  }
  CameraManager manager;
  manager.add_backend(make_aravis_backend());
  std::vector<std::unique_ptr<GuidedCamera>> cameras;
  for (int i = 0; i < n; ++i) {
    std::unique_ptr<Camera> cam = manager.open("aravis://" + fakes[i]->address() +
                                               (args.udp_socket ? "?packet_socket=0" : ""));
    cam->configure(guided_config(*scenes[i], args.fps));
    cameras.push_back(std::make_unique<GuidedCamera>(std::move(cam), scenes[i],
                                                     mono8_decoder(scenes[i]->truth().size())));
  }

  round.runs.resize(n);
  const double cpu0 = cpu_seconds();
  const auto t0 = Clock::now();
  std::vector<std::thread> threads;
  for (int i = 0; i < n; ++i) {
    round.runs[i].seed = args.seed + i;
    threads.emplace_back(run_session, std::move(cameras[i]), scenes[i], args.limit_s,
                         &round.runs[i]);
  }
  for (auto& t : threads) t.join();
  round.wall_s = std::chrono::duration<double>(Clock::now() - t0).count();
  round.cpu_s = cpu_seconds() - cpu0;
  for (auto& scene : scenes) scene->stop_preparing();
  for (auto& t : renderers) t.join();
  for (const auto& c : sim_cpu) round.simulator_cpu_s += c->seconds();
  for (double c : render_cpu) round.simulator_cpu_s += c;
  for (const auto& r : round.runs) round.session_cpu_s += r.thread_cpu_s;
  for (auto& f : fakes) f->stop();
  return round;
}

bool keeps_up(const CameraRun& r, double fps) {
  return r.ok() && r.stream_fps() >= kStreamFraction * fps &&
         r.engine_fps() >= kEngineFraction * fps && r.median_second_fps() >= std::round(fps);
}

// Inside the private network namespace.
int run_rounds(const Args& args) {
  const int first = args.only > 0 ? args.only : 1;
  const int last = args.only > 0 ? args.only : args.max_cameras;
  std::printf(
      "# %s operator (%s), 1280x720 Mono8 at %.0f fps per camera, Aravis %s, render "
      "supersampling %d, OpenCV threads %d, seeds %llu.., %u hardware threads, load average %s\n",
      args.kind == OperatorKind::kRobot ? "robot" : "person",
      args.lockstep ? "lockstep" : "free-running", args.fps,
      args.udp_socket ? "UDP socket" : "packet socket", args.supersample, args.opencv_threads,
      static_cast<unsigned long long>(args.seed), std::thread::hardware_concurrency(),
      load_average().c_str());
  int verdict = 0;
  for (int n = first; n <= last; ++n) {
    Round r;
    try {
      r = run_round(args, n);
    } catch (const std::exception& e) {
      std::fprintf(stderr, "N=%d: %s\n", n, e.what());
      return 1;
    }
    std::printf("%3s %4s %10s %3s %6s %6s %5s %9s %10s %8s %10s %10s %6s %8s %s\n", "N", "seed",
                "state", "kf", "frames", "missed", "late", "session_s", "engine_fps", "median_s",
                "stream_fps", "incomplete", "exact", "eps_gt", "problem");
    std::vector<double> engine_fps, median_fps, stream_fps;
    uint64_t frames = 0, missed = 0, late = 0;
    bool all_keep_up = true;
    for (const CameraRun& c : r.runs) {
      std::printf(
          "%3d %4llu %10s %3d %6llu %6llu %5llu %9.1f %10.2f %8.0f %10.2f %10llu %6llu %8.3f %s\n",
          n, static_cast<unsigned long long>(c.seed), engine_state_name(c.state), c.keyframes,
          static_cast<unsigned long long>(c.frames), static_cast<unsigned long long>(c.missed),
          static_cast<unsigned long long>(c.late), c.session_s, c.engine_fps(),
          c.median_second_fps(), c.stream_fps(), static_cast<unsigned long long>(c.incomplete),
          static_cast<unsigned long long>(c.exact), c.eps_gt,
          c.ok() ? ""
                 : (c.problem.empty() ? (c.honest ? "not converged" : "outside 5 sigma")
                                      : c.problem.c_str()));
      engine_fps.push_back(c.engine_fps());
      median_fps.push_back(c.median_second_fps());
      stream_fps.push_back(c.stream_fps());
      frames += c.frames;
      missed += c.missed;
      late += c.late;
      all_keep_up &= keeps_up(c, args.fps);
    }
    const double other_cpu = r.cpu_s - r.simulator_cpu_s - r.session_cpu_s;
    auto per_frame_ms = [frames](double s) { return frames ? 1e3 * s / frames : 0.0; };
    std::printf(
        "N=%d: engine %.2f fps (median over cameras; min %.2f), median second %.0f fps (min %.0f), "
        "stream %.2f fps (min %.2f); CPU per processed frame: %.1f ms sessions (engine, checks) + "
        "%.1f ms transport (Aravis, backend threads) = %.1f ms, simulators %.1f ms; process "
        "%.0f%% of one core over %.1f s; missed %llu of %llu new frames; simulators late on "
        "%llu; load average at the end %s; %s\n\n",
        n, median(engine_fps), *std::min_element(engine_fps.begin(), engine_fps.end()),
        median(median_fps), *std::min_element(median_fps.begin(), median_fps.end()),
        median(stream_fps), *std::min_element(stream_fps.begin(), stream_fps.end()),
        per_frame_ms(r.session_cpu_s), per_frame_ms(other_cpu),
        per_frame_ms(r.session_cpu_s + other_cpu), per_frame_ms(r.simulator_cpu_s),
        100 * r.cpu_s / r.wall_s, r.wall_s, static_cast<unsigned long long>(missed),
        static_cast<unsigned long long>(frames + missed), static_cast<unsigned long long>(late),
        load_average().c_str(), all_keep_up ? "every camera keeps up" : "NOT KEPT UP");
    std::fflush(stdout);
    if (!all_keep_up) {
      verdict = n;
      break;
    }
  }
  if (verdict > 1) {
    std::printf("result: %d camera(s) keep up, %d do not\n", verdict - 1, verdict);
  } else if (verdict == 1) {
    std::printf("result: not even one camera keeps up\n");
  } else {
    std::printf("result: every N up to %d keeps up\n", last);
  }
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  Args args;
  if (!parse(argc, argv, &args)) {
    usage();
    return 2;
  }
  const int status = posecal::testing::enter_private_network(
      argc, argv, args.only > 0 ? args.only : args.max_cameras);
  if (status >= 0) return status;
  cv::setNumThreads(args.opencv_threads);
  return run_rounds(args);
}
