// Throughput of the Aravis path: GigE Vision simulator -> GVSP over loopback -> Aravis stream
// thread -> posecal pump -> next_frame() -> engine cv::Mat. Frames per second delivered and CPU
// time per delivered frame of this process (the receiving side: Aravis' stream and heartbeat
// threads, the backend's pump and supervisor, the consumer loop).
//
// The simulator runs as a separate process (arv-fake-gv-camera-0.8) so that its CPU time (making
// and sending the packets) is not counted; --in-process puts it in this process instead.
//
//   bench_aravis [--seconds 3] [--runs 5] [--width 1280] [--height 720] [--format Mono8]
//                [--fps 1000] [--packet-size 0] [--socket-buffer 0] [--copy] [--udp-socket]
//                [--in-process]
//
// Prints one line per run and the medians. docs/aravis.md records the figures.
#include <arv.h>
#include <signal.h>
#include <spawn.h>
#include <sys/resource.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <string>
#include <thread>
#include <vector>

#include "posecal/aravis_backend.hpp"
#include "common/error.hpp"

extern char** environ;

using namespace posecal;
using Clock = std::chrono::steady_clock;

namespace {

struct Args {
  double seconds = 3;
  int runs = 5;
  int width = 1280, height = 720;
  std::string format = "Mono8";
  double fps = 1000;  // the simulator's maximum: it sends as fast as it can
  int packet_size = 0;
  int socket_buffer = 0;  // bytes, 0: the backend default (four frames)
  bool copy = false;
  bool in_process = false;
  bool udp_socket = false;  // disable Aravis' packet socket
};

double cpu_seconds() {
  rusage u{};
  getrusage(RUSAGE_SELF, &u);
  return u.ru_utime.tv_sec + u.ru_stime.tv_sec + 1e-6 * (u.ru_utime.tv_usec + u.ru_stime.tv_usec);
}

// utime + stime of another process, seconds (0 if unreadable).
double process_cpu_seconds(pid_t pid) {
  char path[64];
  std::snprintf(path, sizeof path, "/proc/%d/stat", static_cast<int>(pid));
  FILE* f = std::fopen(path, "r");
  if (f == nullptr) return 0;
  char buf[4096];
  const size_t n = std::fread(buf, 1, sizeof buf - 1, f);
  std::fclose(f);
  buf[n] = '\0';
  const char* p = std::strrchr(buf, ')');  // the command name may contain spaces
  if (p == nullptr) return 0;
  unsigned long utime = 0, stime = 0;
  // Fields after ") ": state(3) ... utime(14) stime(15).
  if (std::sscanf(p + 2, "%*c %*d %*d %*d %*d %*d %*u %*u %*u %*u %*u %lu %lu", &utime, &stime) !=
      2)
    return 0;
  return static_cast<double>(utime + stime) / static_cast<double>(sysconf(_SC_CLK_TCK));
}

double median(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  return v.empty()
             ? 0
             : (v.size() % 2 ? v[v.size() / 2] : 0.5 * (v[v.size() / 2 - 1] + v[v.size() / 2]));
}

bool parse(int argc, char** argv, Args* a) {
  for (int i = 1; i < argc; ++i) {
    const std::string k = argv[i];
    auto next = [&]() -> const char* { return i + 1 < argc ? argv[++i] : nullptr; };
    const char* v = nullptr;
    if (k == "--copy") {
      a->copy = true;
    } else if (k == "--in-process") {
      a->in_process = true;
    } else if (k == "--udp-socket") {
      a->udp_socket = true;
    } else if ((v = next()) == nullptr) {
      return false;
    } else if (k == "--seconds") {
      a->seconds = std::atof(v);
    } else if (k == "--runs") {
      a->runs = std::atoi(v);
    } else if (k == "--width") {
      a->width = std::atoi(v);
    } else if (k == "--height") {
      a->height = std::atoi(v);
    } else if (k == "--format") {
      a->format = v;
    } else if (k == "--fps") {
      a->fps = std::atof(v);
    } else if (k == "--packet-size") {
      a->packet_size = std::atoi(v);
    } else if (k == "--socket-buffer") {
      a->socket_buffer = std::atoi(v);
    } else {
      return false;
    }
  }
  return a->seconds > 0 && a->runs > 0 &&
         pixel_format_from_name(a->format) != PixelFormat::kUnknown;
}

}  // namespace

int main(int argc, char** argv) {
  Args args;
  if (!parse(argc, argv, &args)) {
    std::fprintf(
        stderr,
        "usage: bench_aravis [--seconds S] [--runs N] [--width W] [--height H] "
        "[--format Mono8|Mono16|RGB8|BayerRG8] [--fps F] [--packet-size B] [--socket-buffer B] "
        "[--copy] "
        "[--udp-socket] [--in-process]\n");
    return 2;
  }

  // The simulator.
  pid_t sim_pid = 0;
  ArvGvFakeCamera* in_process = nullptr;
  if (args.in_process) {
    in_process = arv_gv_fake_camera_new("127.0.0.1", "PCALBENCH");
    if (!arv_gv_fake_camera_is_running(in_process)) {
      std::fprintf(stderr, "the simulator cannot listen on 127.0.0.1:3956\n");
      return 1;
    }
  } else {
    const char* sim_argv[] = {
        "arv-fake-gv-camera-0.8", "-i", "127.0.0.1", "-s", "PCALBENCH", nullptr};
    if (posix_spawnp(&sim_pid, sim_argv[0], nullptr, nullptr, const_cast<char**>(sim_argv),
                     environ) != 0) {
      std::fprintf(stderr,
                   "cannot start arv-fake-gv-camera-0.8 (aravis-tools); try --in-process\n");
      return 1;
    }
  }

  CameraManager manager;
  AravisBackendOptions options;
  options.zero_copy = !args.copy;
  options.packet_size = args.packet_size;
  options.packet_socket = !args.udp_socket;
  options.socket_buffer_size = args.socket_buffer;
  manager.add_backend(make_aravis_backend(options));

  std::printf(
      "# %dx%d %s, requested %.0f fps, packet size %s, socket buffer %s, %s, %s, simulator %s\n",
      args.width, args.height, args.format.c_str(), args.fps,
      args.packet_size ? std::to_string(args.packet_size).c_str() : "camera default",
      args.socket_buffer ? std::to_string(args.socket_buffer).c_str() : "4 frames",
      args.copy ? "copying Mono8" : "zero-copy Mono8",
      args.udp_socket ? "UDP socket" : "packet socket if permitted",
      args.in_process ? "in this process (its CPU is counted)" : "in its own process");
  std::vector<double> fps_runs, cpu_runs, cpu_pct_runs;
  int status = 0;
  try {
    std::unique_ptr<Camera> cam;
    const auto t_open = Clock::now();
    while (!cam) {  // the simulator process needs a moment to listen
      try {
        cam = manager.open("aravis://127.0.0.1");
      } catch (const Error& e) {
        if (e.code() != ErrorCode::kNotFound || Clock::now() - t_open > std::chrono::seconds(10))
          throw;
        std::this_thread::sleep_for(std::chrono::milliseconds(100));
      }
    }
    CameraConfig c;
    c.pixel_format = pixel_format_from_name(args.format);
    c.roi = cv::Rect(0, 0, args.width, args.height);
    c.frame_rate_hz = args.fps;
    cam->configure(c);
    const CameraConfig actual = cam->current_config();
    std::printf("# camera: %dx%d, frame rate %.1f Hz\n", actual.roi->width, actual.roi->height,
                actual.frame_rate_hz.value_or(0));
    std::printf("%4s %10s %12s %14s %10s %12s %12s\n", "run", "frames", "fps", "cpu_us/frame",
                "cpu_%", "incomplete", "sender_cpu_%");
    for (int run = 0; run < args.runs; ++run) {
      cam->start();
      Frame f;
      const auto warm = Clock::now();
      while (Clock::now() - warm < std::chrono::milliseconds(500)) cam->next_frame(1000, &f);
      const CameraStats s0 = cam->stats();
      const double cpu0 = cpu_seconds();
      const double sim0 = sim_pid ? process_cpu_seconds(sim_pid) : 0;
      const auto t0 = Clock::now();
      uint64_t frames = 0, checksum = 0;
      while (std::chrono::duration<double>(Clock::now() - t0).count() < args.seconds) {
        if (cam->next_frame(1000, &f) != FrameStatus::kOk) continue;
        checksum += f.image.data[f.image.total() * f.image.elemSize() / 2];  // read the frame
        ++frames;
      }
      const double wall = std::chrono::duration<double>(Clock::now() - t0).count();
      const double cpu = cpu_seconds() - cpu0;
      const double sim = sim_pid ? process_cpu_seconds(sim_pid) - sim0 : 0;
      const CameraStats s1 = cam->stats();
      cam->stop();
      const double fps = frames / wall;
      const double us = frames ? 1e6 * cpu / frames : 0;
      fps_runs.push_back(fps);
      cpu_runs.push_back(us);
      cpu_pct_runs.push_back(100 * cpu / wall);
      std::printf("%4d %10llu %12.1f %14.1f %10.1f %12llu %12.1f\n", run + 1,
                  static_cast<unsigned long long>(frames), fps, us, 100 * cpu / wall,
                  static_cast<unsigned long long>(s1.frames_incomplete - s0.frames_incomplete),
                  100 * sim / wall);
      if (checksum == 42) std::printf(" ");  // keeps the reads
    }
    std::printf("median: %.1f fps, %.1f us CPU per frame (%.1f %% of one core)\n", median(fps_runs),
                median(cpu_runs), median(cpu_pct_runs));
  } catch (const std::exception& e) {
    std::fprintf(stderr, "bench_aravis: %s\n", e.what());
    status = 1;
  }
  if (sim_pid != 0) {
    kill(sim_pid, SIGTERM);
    int st = 0;
    waitpid(sim_pid, &st, 0);
  }
  if (in_process != nullptr) g_object_unref(in_process);
  return status;
}
