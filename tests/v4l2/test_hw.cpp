// Real hardware: the backend on the kernel seam (/dev/video*, /sys). Skips without a camera.
// POSECAL_V4L2_URI selects the camera (default: the first one listed); set
// POSECAL_V4L2_ALLOW_LOCK=1 to also run the calibration lock, which changes the camera's
// focus/exposure settings until they are changed back (v4l2-ctl, or replugging), and
// POSECAL_V4L2_INTERACTIVE=1 for the checks that ask a person to unplug and replug the camera
// (docs/v4l2.md, "Manual check with a real C525").
#include <gtest/gtest.h>

#include <chrono>
#include <condition_variable>
#include <cstdlib>
#include <mutex>
#include <thread>

#include "common/error.hpp"
#include "board/board.hpp"
#include "posecal/v4l2_backend.hpp"

namespace posecal {
namespace {

std::string pick_camera(V4l2Backend& backend) {
  if (const char* uri = std::getenv("POSECAL_V4L2_URI")) return uri;
  const auto list = backend.enumerate();
  for (const auto& d : list) {
    std::printf("found %s: %s %s (serial '%s', %s)\n", d.uri.c_str(), d.vendor.c_str(),
                d.model.c_str(), d.serial.c_str(), d.transport.c_str());
  }
  return list.empty() ? "" : list.front().uri;
}

TEST(V4l2Hardware, StreamsFromARealCamera) {
  V4l2Backend backend;
  const std::string uri = pick_camera(backend);
  if (uri.empty()) GTEST_SKIP() << "no V4L2 video-capture device on this machine";
  auto cam_base = backend.open(Uri::parse(uri));
  auto* cam = dynamic_cast<V4l2Camera*>(cam_base.get());
  ASSERT_TRUE(cam);
  for (const auto& f : cam->formats()) {
    std::printf("format %s (%s): %zu sizes\n", f.fourcc_text.c_str(), f.description.c_str(),
                f.sizes.size());
  }
  for (const auto& f : cam->features()) {
    std::printf("  %-32s %-11s = %s [%s, %s]\n", f.name.c_str(), feature_type_name(f.type), f.value.c_str(),
                f.min.c_str(), f.max.c_str());
  }
  CameraConfig req;
  req.pixel_format = PixelFormat::kMJPEG;
  req.roi = cv::Rect(0, 0, 1280, 720);
  req.frame_rate_hz = 30;
  CameraConfig v;
  try {
    v = cam->validate(req);
  } catch (const Error&) {
    v = cam->validate({});  // no MJPEG: the current format
  }
  cam->configure(v);
  const CameraConfig cur = cam->current_config();
  std::printf("streaming %s %dx%d @ %.2f Hz\n", pixel_format_name(*cur.pixel_format),
              cur.roi->width, cur.roi->height, cur.frame_rate_hz.value_or(0));
  cam->start();
  int ok = 0;
  Frame f;
  for (int i = 0; i < 30; ++i) {
    const FrameStatus s = cam->next_frame(3000, &f);
    ASSERT_NE(s, FrameStatus::kDisconnected);
    if (s == FrameStatus::kOk) {
      ++ok;
      EXPECT_EQ(f.image.cols, cur.roi->width);
      EXPECT_EQ(f.image.rows, cur.roi->height);
    }
  }
  cam->stop();
  const CameraStats st = cam->stats();
  std::printf("delivered %llu, dropped %llu, incomplete %llu\n",
              static_cast<unsigned long long>(st.frames_delivered),
              static_cast<unsigned long long>(st.frames_dropped),
              static_cast<unsigned long long>(st.frames_incomplete));
  EXPECT_GE(ok, 25);
  const Detection d = Board().detect(f.image);
  std::printf("board corners detected in the last frame: %zu (0 unless a board is in view)\n",
              d.size());
}

TEST(V4l2Hardware, CalibrationLock) {
  V4l2Backend backend;
  const std::string uri = pick_camera(backend);
  if (uri.empty()) GTEST_SKIP() << "no V4L2 video-capture device on this machine";
  if (!std::getenv("POSECAL_V4L2_ALLOW_LOCK")) {
    GTEST_SKIP() << "set POSECAL_V4L2_ALLOW_LOCK=1 to let the test change focus/exposure settings";
  }
  auto cam = backend.open(Uri::parse(uri));
  const auto locked = cam->lock_for_calibration();
  for (const auto& [name, value] : locked) {
    std::printf("locked %s = %s\n", name.c_str(), value.c_str());
    EXPECT_EQ(cam->get_feature(name), value);
  }
}

bool interactive() { return std::getenv("POSECAL_V4L2_INTERACTIVE") != nullptr; }

TEST(V4l2Hardware, UnplugWhileStreaming) {
  V4l2Backend backend;
  const std::string uri = pick_camera(backend);
  if (uri.empty()) GTEST_SKIP() << "no V4L2 video-capture device on this machine";
  if (!interactive()) GTEST_SKIP() << "set POSECAL_V4L2_INTERACTIVE=1 to unplug the camera by hand";
  auto cam = backend.open(Uri::parse(uri));
  std::mutex m;
  std::vector<CameraEvent> events;
  cam->set_event_callback([&](const CameraEvent& e) {
    std::lock_guard<std::mutex> lock(m);
    events.push_back(e);
  });
  cam->start();
  std::printf(">>> unplug %s within 30 s\n", uri.c_str());
  std::fflush(stdout);
  Frame f;
  FrameStatus s = FrameStatus::kOk;
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(30);
  while (std::chrono::steady_clock::now() < deadline) {
    s = cam->next_frame(500, &f);
    if (s == FrameStatus::kDisconnected) break;
  }
  ASSERT_EQ(s, FrameStatus::kDisconnected) << "the camera was not unplugged in time";
  EXPECT_EQ(cam->state(), CameraState::kDisconnected);
  std::lock_guard<std::mutex> lock(m);
  ASSERT_EQ(events.size(), 1u);
  std::printf("event: %s\n", events[0].message.c_str());
}

TEST(V4l2Hardware, HotplugReportsReplug) {
  V4l2Backend backend;
  if (!interactive()) GTEST_SKIP() << "set POSECAL_V4L2_INTERACTIVE=1 to replug a camera by hand";
  std::mutex m;
  std::condition_variable cv;
  std::vector<std::pair<DeviceInfo, bool>> seen;
  backend.set_hotplug_callback([&](const DeviceInfo& d, bool added) {
    std::lock_guard<std::mutex> lock(m);
    seen.emplace_back(d, added);
    cv.notify_all();
  });
  if (!backend.hotplug_status().empty()) GTEST_SKIP() << backend.hotplug_status();
  std::printf(">>> unplug a camera, then plug it back in, within 60 s\n");
  std::fflush(stdout);
  std::unique_lock<std::mutex> lock(m);
  const bool both = cv.wait_for(lock, std::chrono::seconds(60), [&] {
    bool removed = false;
    for (const auto& [d, added] : seen) {
      if (!added) removed = true;
      if (added && removed) return true;
    }
    return false;
  });
  for (const auto& [d, added] : seen) {
    std::printf("%s %s (%s)\n", added ? "added" : "removed", d.uri.c_str(), d.model.c_str());
  }
  EXPECT_TRUE(both) << "expected a removal followed by an arrival";
  lock.unlock();
  backend.set_hotplug_callback(nullptr);
}

}  // namespace
}  // namespace posecal
