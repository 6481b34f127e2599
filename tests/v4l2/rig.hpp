// Test rig: the fixture sysfs/dev tree of two UVC cameras plus a platform camera, the UVC
// emulator serving their nodes, a fake USB hot-plug source and a V4l2Backend wired to all three.
#pragma once

#include <gtest/gtest.h>

#include <chrono>
#include <condition_variable>
#include <functional>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "common/error.hpp"
#include "posecal/v4l2_backend.hpp"
#include "uvc_emulator.hpp"

namespace posecal::test {

inline const std::string kC525Id = "usb-046d_HD_Webcam_C525_0320EC60-video-index0";
inline const std::string kC525MetaId = "usb-046d_HD_Webcam_C525_0320EC60-video-index1";
inline const std::string kLifeCamId =
    "usb-Microsoft_Microsoft\xC2\xAE_LifeCam_HD-3000-video-index0";
inline const std::string kMonoId = "platform-mono-sensor.0-video-index0";

inline std::string fixture_root() {
  return std::string(POSECAL_SOURCE_DIR) + "/tests/data/v4l2/two_uvc_cameras";
}

// Hot-plug events fired by the test. `available = false` plays a system without hot-plug.
class FakeUsbEvents final : public UsbEventSource {
 public:
  bool available = true;
  bool start(Handler handler, std::string* why_not) override {
    std::lock_guard<std::mutex> lock(mutex_);
    if (!available) {
      *why_not = "fake: no hot-plug here";
      return false;
    }
    handler_ = std::move(handler);
    ++starts_;
    return true;
  }
  void stop() override {
    std::lock_guard<std::mutex> lock(mutex_);
    handler_ = nullptr;
  }
  bool running() const {
    std::lock_guard<std::mutex> lock(mutex_);
    return handler_ != nullptr;
  }
  int starts() const {
    std::lock_guard<std::mutex> lock(mutex_);
    return starts_;
  }
  void fire(UsbHotplugEvent::Kind kind, int bus, std::vector<int> ports, uint16_t vid = 0,
            uint16_t pid = 0) {
    Handler h;
    {
      std::lock_guard<std::mutex> lock(mutex_);
      h = handler_;
    }
    ASSERT_TRUE(h) << "hot-plug source not started";
    UsbHotplugEvent e;
    e.kind = kind;
    e.bus = bus;
    e.ports = std::move(ports);
    e.vendor_id = vid;
    e.product_id = pid;
    h(e);
  }

 private:
  mutable std::mutex mutex_;
  Handler handler_;
  int starts_ = 0;
};

struct Rig {
  std::string root = fixture_root();
  std::string sys = root + "/sys";
  std::string dev = root + "/dev";
  std::shared_ptr<emu::UvcEmulator> emu = std::make_shared<emu::UvcEmulator>();
  std::shared_ptr<FakeUsbEvents> usb = std::make_shared<FakeUsbEvents>();
  std::shared_ptr<V4l2Backend> backend;

  std::string video(int n) const { return dev + "/video" + std::to_string(n); }

  Rig() {
    add_c525();
    add_lifecam();
    emu->add_node(video(4), emu::grey_read_node(), "mono-sensor.0");
    backend = std::make_shared<V4l2Backend>(options());
  }
  void add_c525() {
    emu->add_node(video(0), emu::c525_video_node(), "1-2");
    emu->add_node(video(1), emu::c525_metadata_node(), "1-2");
  }
  void add_lifecam() {
    emu->add_node(video(2), emu::lifecam_video_node(), "1-3.1");
    emu->add_node(video(3), emu::lifecam_metadata_node(), "1-3.1");
  }
  V4l2BackendOptions options() const {
    V4l2BackendOptions o;
    o.io = emu;
    o.sysfs_root = sys;
    o.dev_root = dev;
    o.usb_events = usb;
    o.hotplug_settle_ms = 1500;
    return o;
  }
  std::unique_ptr<V4l2Camera> open(const std::string& uri) {
    std::unique_ptr<Camera> c = backend->open(Uri::parse(uri));
    auto* v = dynamic_cast<V4l2Camera*>(c.get());
    if (!v) throw Error(ErrorCode::kInternal, "not a V4l2Camera");
    c.release();
    return std::unique_ptr<V4l2Camera>(v);
  }
};

// Every test ends with no descriptor open and no buffer mapped in the emulator.
class EmulatedV4l2 : public ::testing::Test {
 protected:
  void TearDown() override {
    EXPECT_EQ(rig.emu->open_fds(), 0) << "leaked file descriptors";
    EXPECT_EQ(rig.emu->live_mappings(), 0) << "leaked buffer mappings";
    EXPECT_EQ(rig.emu->bad_munmaps(), 0) << "munmap() of something that was not mapped";
  }
  Rig rig;
};

// Expects `f` to throw posecal::Error with `code`; returns the message.
template <typename F>
std::string expect_error(ErrorCode code, F&& f) {
  try {
    f();
  } catch (const Error& e) {
    EXPECT_EQ(e.code(), code) << e.what();
    return e.what();
  }
  ADD_FAILURE() << "expected posecal::Error(" << error_code_name(code) << ")";
  return {};
}

inline double elapsed_ms(std::chrono::steady_clock::time_point since) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - since)
      .count();
}

}  // namespace posecal::test
