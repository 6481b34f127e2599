// Checks that several GigE Vision cameras streaming on one interface never deliver each other's
// packets: N simulated cameras (Aravis' simulator, in this process) on 127.0.0.1 ... 127.0.0.N
// of a private network namespace (root only), each showing its own scene (every frame a pure
// function of its frame id, fake_gv_camera.hpp). Each round opens all of them through
// make_aravis_backend(), starts their streams one after the other (as independent sessions do)
// and checks the first frames of every camera bit for bit against what its own simulator sent;
// a frame that differs is examined: which byte range differs and whose frame those bytes are.
//
// Found with the many-camera benchmark: with Aravis' packet socket (the default for root), a
// camera whose stream starts while others are streaming occasionally assembles its first frames
// partly from the other cameras' packets that carry the same block id (the simulators all
// count from the same id). With the UDP socket (--udp-socket 1, packet_socket=0) it never did.
// docs/aravis.md, "Calibration on many cameras", has the figures.
//
//   aravis_stream_crosstalk [--cameras 3] [--rounds 60] [--frames 12] [--fps 30]
//                           [--busy-threads 2] [--udp-socket 0]
//
// Exit status: 0 if every frame was exact, 1 otherwise (77: not root).
#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <string>
#include <thread>
#include <vector>

#include "fake_gv_camera.hpp"
#include "netns.hpp"
#include "posecal/aravis_backend.hpp"

using namespace posecal;
using posecal::testing::FakeGvCamera;
using posecal::testing::make_scene;

namespace {

struct Args {
  int cameras = 3;
  int rounds = 60;
  int frames = 12;
  double fps = 30;
  bool udp_socket = false;
  int busy_threads = 2;  // threads spinning meanwhile: the race needs the stream thread preempted
};

bool parse(int argc, char** argv, Args* a) {
  for (int i = 1; i < argc; ++i) {
    const std::string k = argv[i];
    if (i + 1 >= argc) return false;
    const char* v = argv[++i];
    if (k == "--cameras") {
      a->cameras = std::atoi(v);
    } else if (k == "--rounds") {
      a->rounds = std::atoi(v);
    } else if (k == "--frames") {
      a->frames = std::atoi(v);
    } else if (k == "--fps") {
      a->fps = std::atof(v);
    } else if (k == "--busy-threads") {
      a->busy_threads = std::atoi(v);
    } else if (k == "--udp-socket") {
      a->udp_socket = std::string(v) == "1";
    } else {
      return false;
    }
  }
  return a->cameras >= 2 && a->cameras <= 250 && a->rounds >= 1 && a->frames >= 1 && a->fps > 0 &&
         a->busy_threads >= 0 && a->busy_threads <= 64;
}

const cv::Rect kRoi(0, 0, 1280, 720);

// Where a bad frame differs from the expected one, and which camera's frame of the same id
// supplied those bytes (-1: none).
void examine(const cv::Mat& got, const cv::Mat& expected, uint64_t frame_id,
             const std::vector<std::unique_ptr<FakeGvCamera>>& fakes, int self) {
  long first = -1, last = -1;
  for (long b = 0; b < static_cast<long>(got.total()); ++b) {
    if (got.data[b] != expected.data[b]) {
      if (first < 0) first = b;
      last = b;
    }
  }
  int source = -1;
  for (int j = 0; j < static_cast<int>(fakes.size()) && first >= 0; ++j) {
    if (j == self) continue;
    const cv::Mat other = fakes[j]->expected_engine(frame_id, PixelFormat::kMono8, kRoi);
    if (std::equal(got.data + first, got.data + last + 1, other.data + first)) source = j;
  }
  std::printf("  camera %d frame %llu: bytes %ld..%ld differ (%ld bytes)%s\n", self + 1,
              static_cast<unsigned long long>(frame_id), first, last, last - first + 1,
              source >= 0 ? (" and are camera " + std::to_string(source + 1) + "'s frame " +
                             std::to_string(frame_id))
                                .c_str()
                          : "; they are no other camera's frame of that id");
}

}  // namespace

int main(int argc, char** argv) {
  Args args;
  if (!parse(argc, argv, &args)) {
    std::fprintf(stderr,
                 "usage: aravis_stream_crosstalk [--cameras N] [--rounds R] [--frames F] "
                 "[--fps F] [--busy-threads 2] [--udp-socket 0|1]\n");
    return 2;
  }
  const int status = posecal::testing::enter_private_network(argc, argv, args.cameras);
  if (status >= 0) return status;

  std::printf(
      "# %d cameras, %d rounds, first %d frames each at %.0f fps, Aravis %s, %d busy "
      "threads\n",
      args.cameras, args.rounds, args.frames, args.fps,
      args.udp_socket ? "UDP socket" : "packet socket", args.busy_threads);
  std::atomic<bool> quit{false};
  std::vector<std::thread> busy;
  for (int i = 0; i < args.busy_threads; ++i) {
    busy.emplace_back([&quit] {
      volatile uint64_t x = 0;
      while (!quit.load(std::memory_order_relaxed)) x = x + 1;
    });
  }
  std::vector<std::shared_ptr<const testing::FakeScene>> scenes;
  for (int i = 0; i < args.cameras; ++i) {
    scenes.push_back(make_scene(40 + i, 3, static_cast<uint32_t>(i + 1)));
  }
  uint64_t checked = 0, bad = 0, bad_rounds = 0;
  for (int round = 0; round < args.rounds; ++round) {
    std::vector<std::unique_ptr<FakeGvCamera>> fakes;
    for (int i = 0; i < args.cameras; ++i) {
      fakes.push_back(std::make_unique<FakeGvCamera>(
          "PCAL-X" + std::to_string(i + 1), "127.0.0." + std::to_string(i + 1), scenes[i]));
      if (!fakes.back()->start()) {
        std::fprintf(stderr, "no simulator on %s\n", fakes.back()->address().c_str());
        return 1;
      }
    }
    CameraManager manager;
    manager.add_backend(make_aravis_backend());
    std::vector<std::unique_ptr<Camera>> cams;
    for (const auto& fake : fakes) {
      cams.push_back(manager.open("aravis://" + fake->address() +
                                  (args.udp_socket ? "?packet_socket=0" : "")));
      CameraConfig c;
      c.pixel_format = PixelFormat::kMono8;
      c.roi = kRoi;
      c.frame_rate_hz = args.fps;
      cams.back()->configure(c);
    }
    // One after the other, each reading its own frames at once, as independent sessions do.
    std::vector<std::vector<Frame>> got(cams.size());
    std::vector<std::thread> readers;
    for (size_t i = 0; i < cams.size(); ++i) {
      cams[i]->start();
      readers.emplace_back([&, i] {
        for (int k = 0; k < args.frames; ++k) {
          Frame f;
          if (cams[i]->next_frame(2000, &f) != FrameStatus::kOk) continue;
          f.image = f.image.clone();  // keep it past the lent-buffer limit
          f.hold.reset();
          got[i].push_back(std::move(f));
        }
      });
    }
    for (auto& t : readers) t.join();
    bool round_bad = false;
    for (size_t i = 0; i < cams.size(); ++i) {
      for (const Frame& f : got[i]) {
        ++checked;
        const cv::Mat e = fakes[i]->expected_engine(f.frame_id, PixelFormat::kMono8, kRoi);
        if (f.image.size() == e.size() && cv::norm(f.image, e, cv::NORM_INF) == 0) continue;
        ++bad;
        round_bad = true;
        std::printf("round %d:\n", round + 1);
        examine(f.image, e, f.frame_id, fakes, static_cast<int>(i));
      }
    }
    bad_rounds += round_bad;
    cams.clear();
    fakes.clear();
  }
  quit = true;
  for (auto& t : busy) t.join();
  std::printf("%llu frames checked, %llu not exact, in %llu of %d rounds\n",
              static_cast<unsigned long long>(checked), static_cast<unsigned long long>(bad),
              static_cast<unsigned long long>(bad_rounds), args.rounds);
  return bad == 0 ? 0 : 1;
}
