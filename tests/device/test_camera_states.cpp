// The camera state machine of device/camera.hpp, checked once for every backend: each public call
// in each state (Opened, Configured, Streaming, Disconnected) is either allowed (it may still
// fail for its own reasons, e.g. an unknown feature, but never with kState) or refused with
// Error(kState), as the table in camera.hpp says; next_frame() while disconnected returns
// kDisconnected and stop() is a no-op. Backends: sim, images, external, V4L2 (UVC emulator),
// Aravis (GigE Vision simulator on loopback), and a minimal test camera for the transitions no
// built-in source can make (a disconnect of a simple camera).
#include <gtest/gtest.h>

#include <chrono>
#include <filesystem>
#include <functional>
#include <memory>
#include <opencv2/imgcodecs.hpp>
#include <string>
#include <thread>
#include <vector>

#include "common/error.hpp"
#include "device/sources.hpp"
#include "fake_gv_camera.hpp"
#include "lens/reference_models.hpp"
#include "posecal/aravis_backend.hpp"
#include "rig.hpp"
#include "sim/sim_camera.hpp"

namespace posecal {
namespace {

using Clock = std::chrono::steady_clock;

enum class Call { kCurrentConfig, kValidate, kConfigure, kFeatures, kGetFeature, kSetFeature, kLock, kStart, kStop, kNextFrame };
// The calls that keep the state first: they share one camera, which is closed before each of the
// others gets a fresh one (a GigE Vision camera has one controller at a time).
const std::vector<Call> kAllCalls = {Call::kCurrentConfig, Call::kValidate, Call::kFeatures, Call::kGetFeature,
                                     Call::kSetFeature,    Call::kLock,     Call::kNextFrame, Call::kConfigure,
                                     Call::kStart,         Call::kStop};
const char* call_name(Call c) {
  switch (c) {
    case Call::kCurrentConfig: return "current_config";
    case Call::kValidate: return "validate";
    case Call::kConfigure: return "configure";
    case Call::kFeatures: return "features";
    case Call::kGetFeature: return "get_feature";
    case Call::kSetFeature: return "set_feature";
    case Call::kLock: return "lock_for_calibration";
    case Call::kStart: return "start";
    case Call::kStop: return "stop";
    case Call::kNextFrame: return "next_frame";
  }
  return "?";
}
// Calls that leave the state as it is (one camera serves all of them in a state).
bool keeps_state(Call c) { return c != Call::kConfigure && c != Call::kStart && c != Call::kStop; }

// camera.hpp's table.
bool allowed(CameraState s, Call c) {
  switch (s) {
    case CameraState::kOpened:
    case CameraState::kConfigured: return c != Call::kNextFrame;
    case CameraState::kStreaming: return c != Call::kConfigure && c != Call::kStart;
    case CameraState::kDisconnected: return c == Call::kStop || c == Call::kNextFrame;
  }
  return false;
}

// Runs the call; the error code it threw, or nullopt.
std::optional<ErrorCode> run(Camera& cam, Call c, FrameStatus* status) {
  try {
    switch (c) {
      case Call::kCurrentConfig: cam.current_config(); break;
      case Call::kValidate: cam.validate(CameraConfig{}); break;
      case Call::kConfigure: cam.configure(CameraConfig{}); break;
      case Call::kFeatures: cam.features(); break;
      case Call::kGetFeature: cam.get_feature("NoSuchFeature"); break;
      case Call::kSetFeature: cam.set_feature("NoSuchFeature", "1"); break;
      case Call::kLock: cam.lock_for_calibration(); break;
      case Call::kStart: cam.start(); break;
      case Call::kStop: cam.stop(); break;
      case Call::kNextFrame: {
        Frame f;
        *status = cam.next_frame(100, &f);
        break;
      }
    }
  } catch (const Error& e) {
    return e.code();
  }
  return std::nullopt;
}

// A camera of a backend with whatever keeps it alive (an emulator, a simulator).
struct Opened {
  std::shared_ptr<void> keep;
  std::unique_ptr<Camera> camera;
};

struct Backend {
  std::string name;
  std::function<Opened()> open;
  // Makes the camera disconnected (nullptr: the backend's cameras never disconnect).
  std::function<void(Opened&)> disconnect;
};

// Brings a fresh camera into `s`; false (and a test failure) if it cannot.
bool bring_to(const Backend& b, Opened& o, CameraState s) {
  Camera& cam = *o.camera;
  if (s == CameraState::kConfigured) cam.configure(CameraConfig{});
  if (s == CameraState::kStreaming) cam.start();
  if (s == CameraState::kDisconnected) b.disconnect(o);
  EXPECT_EQ(cam.state(), s) << b.name;
  return cam.state() == s;
}

void check_backend(const Backend& b) {
  for (CameraState s : {CameraState::kOpened, CameraState::kConfigured, CameraState::kStreaming,
                        CameraState::kDisconnected}) {
    if (s == CameraState::kDisconnected && !b.disconnect) continue;
    Opened shared = b.open();
    if (!bring_to(b, shared, s)) continue;
    for (Call c : kAllCalls) {
      Opened fresh;
      Opened* o = &shared;
      if (!keeps_state(c)) {
        shared = Opened{};
        fresh = b.open();
        if (!bring_to(b, fresh, s)) continue;
        o = &fresh;
      }
      FrameStatus status = FrameStatus::kOk;
      const std::optional<ErrorCode> err = run(*o->camera, c, &status);
      const std::string where = b.name + ": " + call_name(c) + "() while " + camera_state_name(s);
      if (allowed(s, c)) {
        EXPECT_TRUE(!err || *err != ErrorCode::kState) << where << " was refused as not allowed";
      } else {
        ASSERT_TRUE(err.has_value()) << where << " was not refused";
        EXPECT_EQ(*err, ErrorCode::kState) << where << " failed with " << error_code_name(*err);
      }
      if (s == CameraState::kDisconnected && c == Call::kNextFrame) {
        EXPECT_EQ(status, FrameStatus::kDisconnected) << where;
      }
      if (keeps_state(c)) {
        EXPECT_EQ(o->camera->state(), s) << where << " changed the state";
      }
    }
  }
}

// ---- the backends ---------------------------------------------------------------------------

Backend sim_backend() {
  return {"sim",
          [] {
            SimCameraOptions so;
            so.truth = c525_reference_model();
            return Opened{nullptr, make_sim_camera(so)};
          },
          nullptr};
}

Backend images_backend(const std::string& dir) {
  return {"images", [dir] { return Opened{nullptr, make_images_backend()->open(Uri::parse("images://" + dir))}; },
          nullptr};
}

Backend external_backend() {
  return {"external", [] { return Opened{nullptr, make_external_backend()->open(Uri::parse("external"))}; }, nullptr};
}

Backend v4l2_backend() {
  auto open = [] {
    auto rig = std::make_shared<test::Rig>();
    std::unique_ptr<Camera> cam = rig->open("v4l2://" + test::kC525Id);
    return Opened{rig, std::move(cam)};
  };
  auto disconnect = [](Opened& o) {
    static_cast<test::Rig*>(o.keep.get())->emu->unplug("1-2");
    // The backend learns of it at its next system call.
    Frame f;
    if (o.camera->state() == CameraState::kStreaming) o.camera->next_frame(100, &f);
    try {
      o.camera->current_config();
    } catch (const Error&) {
    }
  };
  return {"v4l2", open, disconnect};
}

// A camera that only the test disconnects: the base class's handling of a disconnect for sources
// that never disconnect by themselves.
class UnpluggableCamera final : public SimpleCamera {
 public:
  UnpluggableCamera() : SimpleCamera([] {
    DeviceInfo d;
    d.uri = "test://unpluggable";
    return d;
  }()) {}
  void unplug() { mark_disconnected(); }

 protected:
  FrameStatus do_next_frame(int, Frame*) override { return FrameStatus::kTimeout; }
};

Backend unpluggable_backend() {
  return {"unpluggable", [] { return Opened{nullptr, std::make_unique<UnpluggableCamera>()}; },
          [](Opened& o) { static_cast<UnpluggableCamera*>(o.camera.get())->unplug(); }};
}

// ---- tests -----------------------------------------------------------------------------------

TEST(CameraStates, BuiltInSources) {
  const std::string dir = (std::filesystem::temp_directory_path() / "posecal_camera_states").string();
  std::filesystem::create_directories(dir);
  ASSERT_TRUE(cv::imwrite(dir + "/a.png", cv::Mat(48, 64, CV_8UC1, cv::Scalar(128))));
  check_backend(sim_backend());
  check_backend(images_backend(dir));
  check_backend(external_backend());
  check_backend(unpluggable_backend());
  std::filesystem::remove_all(dir);
}

TEST(CameraStates, V4l2) { check_backend(v4l2_backend()); }

TEST(CameraStates, Aravis) {
  // One simulator at a time on 127.0.0.1 (ctest RESOURCE_LOCK); restarted after each disconnect.
  auto scene = testing::make_scene(5, 1, 1);
  auto fake = std::make_shared<std::unique_ptr<testing::FakeGvCamera>>();
  auto start_fake = [fake, scene] {
    *fake = std::make_unique<testing::FakeGvCamera>("PCAL-STATES", "127.0.0.1", scene);
    return (*fake)->start();
  };
  ASSERT_TRUE(start_fake()) << "the Aravis simulator could not listen on 127.0.0.1:3956";
  AravisBackendOptions opt;
  opt.frame_timeout_ms = 200;
  opt.idle_probe_interval_ms = 200;
  opt.probe_timeout_ms = 50;
  opt.probe_retries = 2;
  opt.auto_reconnect = false;
  auto backend = make_aravis_backend(opt);
  auto open = [backend, fake, start_fake] {
    if (!*fake || !(*fake)->running()) {
      EXPECT_TRUE(start_fake());
    }
    return Opened{nullptr, backend->open(Uri::parse("aravis://127.0.0.1"))};
  };
  auto disconnect = [fake](Opened& o) {
    (*fake)->stop();
    const auto t0 = Clock::now();
    while (o.camera->state() != CameraState::kDisconnected && Clock::now() - t0 < std::chrono::seconds(5)) {
      Frame f;
      if (o.camera->state() == CameraState::kStreaming) {
        o.camera->next_frame(50, &f);
      } else {
        std::this_thread::sleep_for(std::chrono::milliseconds(20));
      }
    }
  };
  check_backend({"aravis", open, disconnect});
}

}  // namespace
}  // namespace posecal
