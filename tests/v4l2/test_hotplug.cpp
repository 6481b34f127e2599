// USB hot-plug: libusb-style events (injected) become camera added/removed notifications.
#include "rig.hpp"

namespace posecal::test {
namespace {

struct Notifications {
  std::mutex mutex;
  std::condition_variable changed;
  std::vector<std::pair<DeviceInfo, bool>> list;

  CameraBackend::HotplugCallback callback() {
    return [this](const DeviceInfo& info, bool added) {
      std::lock_guard<std::mutex> lock(mutex);
      list.emplace_back(info, added);
      changed.notify_all();
    };
  }
  // Waits (bounded) until `n` notifications have arrived.
  bool wait_for(size_t n, int timeout_ms = 3000) {
    std::unique_lock<std::mutex> lock(mutex);
    return changed.wait_for(lock, std::chrono::milliseconds(timeout_ms),
                            [&] { return list.size() >= n; });
  }
  size_t size() {
    std::lock_guard<std::mutex> lock(mutex);
    return list.size();
  }
};

using Kind = UsbHotplugEvent::Kind;
using V4l2Hotplug = EmulatedV4l2;

TEST_F(V4l2Hotplug, UsbEventsBecomeCameraNotifications) {
  Notifications n;
  rig.backend->set_hotplug_callback(n.callback());
  EXPECT_TRUE(rig.usb->running());
  EXPECT_EQ(rig.backend->hotplug_status(), "");

  // The C525 (bus 1, port 2) leaves: it was present when hot-plug started, so it is named.
  rig.emu->unplug("1-2");
  rig.usb->fire(Kind::kLeft, 1, {2}, 0x046d, 0x0826);
  ASSERT_TRUE(n.wait_for(1));
  EXPECT_FALSE(n.list[0].second);
  EXPECT_EQ(n.list[0].first.id, kC525Id);
  EXPECT_EQ(n.list[0].first.uri, "v4l2://" + kC525Id);

  // It comes back: one notification for the capture node (not for the metadata node).
  rig.add_c525();
  rig.usb->fire(Kind::kArrived, 1, {2}, 0x046d, 0x0826);
  ASSERT_TRUE(n.wait_for(2));
  EXPECT_TRUE(n.list[1].second);
  EXPECT_EQ(n.list[1].first.id, kC525Id);
  EXPECT_EQ(n.list[1].first.serial, "0320EC60");
  EXPECT_EQ(n.list[1].first.transport, "USB UVC");

  // A keyboard comes and goes: not a camera, no notification.
  rig.usb->fire(Kind::kArrived, 1, {1}, 0x046d, 0xc31c);
  rig.usb->fire(Kind::kLeft, 1, {1}, 0x046d, 0xc31c);
  // The LifeCam behind the hub (port path 3.1) leaves.
  rig.emu->unplug("1-3.1");
  rig.usb->fire(Kind::kLeft, 1, {3, 1}, 0x045e, 0x0810);
  ASSERT_TRUE(n.wait_for(3));
  std::this_thread::sleep_for(std::chrono::milliseconds(100));
  ASSERT_EQ(n.size(), 3u);  // nothing for the keyboard
  EXPECT_EQ(n.list[2].first.id, kLifeCamId);
  EXPECT_FALSE(n.list[2].second);
  // Leaving twice is reported once.
  rig.usb->fire(Kind::kLeft, 1, {3, 1});
  std::this_thread::sleep_for(std::chrono::milliseconds(100));
  EXPECT_EQ(n.size(), 3u);

  rig.backend->set_hotplug_callback(nullptr);
  EXPECT_FALSE(rig.usb->running());
}

// libusb reports the USB device before uvcvideo has created /dev/videoN: the backend waits
// (up to hotplug_settle_ms) for the node.
TEST_F(V4l2Hotplug, ArrivalWaitsForTheVideoNode) {
  Notifications n;
  rig.emu->unplug("1-2");
  rig.backend->set_hotplug_callback(n.callback());
  rig.usb->fire(Kind::kArrived, 1, {2});
  std::this_thread::sleep_for(std::chrono::milliseconds(200));
  EXPECT_EQ(n.size(), 0u);
  rig.add_c525();  // the driver finished binding
  ASSERT_TRUE(n.wait_for(1));
  EXPECT_TRUE(n.list[0].second);
  EXPECT_EQ(n.list[0].first.id, kC525Id);
}

TEST_F(V4l2Hotplug, ArrivalWithoutNodeGivesUpAfterSettleTime) {
  Notifications n;
  rig.emu->unplug("1-2");
  rig.backend->set_hotplug_callback(n.callback());
  const auto t0 = std::chrono::steady_clock::now();
  rig.usb->fire(Kind::kArrived, 1, {2});
  // A later event is handled after the settle time ran out.
  rig.emu->unplug("1-3.1");
  rig.usb->fire(Kind::kLeft, 1, {3, 1});
  ASSERT_TRUE(n.wait_for(1, 5000));
  EXPECT_GE(elapsed_ms(t0), 1400);
  EXPECT_EQ(n.list[0].first.id, kLifeCamId);
  EXPECT_FALSE(n.list[0].second);
}

TEST_F(V4l2Hotplug, StoppingDuringSettleIsPrompt) {
  Notifications n;
  rig.emu->unplug("1-2");
  rig.backend->set_hotplug_callback(n.callback());
  rig.usb->fire(Kind::kArrived, 1, {2});
  std::this_thread::sleep_for(std::chrono::milliseconds(100));
  const auto t0 = std::chrono::steady_clock::now();
  rig.backend->set_hotplug_callback(nullptr);
  EXPECT_LT(elapsed_ms(t0), 500);
  EXPECT_EQ(n.size(), 0u);
}

TEST_F(V4l2Hotplug, UnavailableHotplugDegradesGracefully) {
  rig.usb->available = false;
  Notifications n;
  testing::internal::CaptureStderr();
  EXPECT_NO_THROW(rig.backend->set_hotplug_callback(n.callback()));
  const std::string err = testing::internal::GetCapturedStderr();
  const std::string status = rig.backend->hotplug_status();
  EXPECT_NE(status.find("unavailable"), std::string::npos) << status;
  EXPECT_NE(status.find("fake: no hot-plug here"), std::string::npos) << status;
  EXPECT_NE(err.find(status), std::string::npos) << err;
  EXPECT_EQ(rig.backend->enumerate().size(), 3u);  // the rest works
  rig.backend->set_hotplug_callback(nullptr);
}

TEST_F(V4l2Hotplug, ThroughCameraManager) {
  Notifications n;
  {
    CameraManager manager;
    manager.add_backend(rig.backend);
    manager.set_hotplug_callback(n.callback());
    EXPECT_TRUE(rig.usb->running());
    rig.emu->unplug("1-2");
    rig.usb->fire(Kind::kLeft, 1, {2});
    ASSERT_TRUE(n.wait_for(1));
  }
  // The manager's destructor detached the callback and so stopped the source.
  EXPECT_FALSE(rig.usb->running());
}

// The real libusb source on this machine: either it starts and stops promptly, or it says why
// it cannot. No USB device is needed.
TEST(V4l2LibusbSource, StartsAndStopsOrExplains) {
  auto source = make_libusb_event_source();
  std::string why;
  const bool ok = source->start([](const UsbHotplugEvent&) {}, &why);
  if (ok) {
    std::this_thread::sleep_for(std::chrono::milliseconds(150));
    const auto t0 = std::chrono::steady_clock::now();
    source->stop();
    EXPECT_LT(elapsed_ms(t0), 1000);
    std::printf("libusb hot-plug is available here\n");
  } else {
    EXPECT_FALSE(why.empty());
    std::printf("libusb hot-plug unavailable here: %s\n", why.c_str());
  }
  source->stop();  // idempotent
}

}  // namespace
}  // namespace posecal::test
