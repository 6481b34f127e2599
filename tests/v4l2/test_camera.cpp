// The backend and its cameras against the emulated C525, LifeCam and read()-only mono camera.
#include <opencv2/imgproc.hpp>

#include "board/board.hpp"
#include "rig.hpp"

namespace posecal::test {
namespace {

const DeviceInfo* find_info(const std::vector<DeviceInfo>& list, const std::string& id) {
  for (const auto& d : list) {
    if (d.id == id) return &d;
  }
  return nullptr;
}

using V4l2Camera_ = EmulatedV4l2;

TEST_F(V4l2Camera_, EnumerateListsCaptureNodesOnly) {
  const auto list = rig.backend->enumerate();
  ASSERT_EQ(list.size(), 3u);  // video1 and video3 are metadata nodes
  const DeviceInfo* c525 = find_info(list, kC525Id);
  ASSERT_TRUE(c525);
  EXPECT_EQ(c525->uri, "v4l2://" + kC525Id);
  EXPECT_EQ(c525->backend, "v4l2");
  EXPECT_EQ(c525->vendor, "046d");
  EXPECT_EQ(c525->model, "HD Webcam C525");
  EXPECT_EQ(c525->serial, "0320EC60");
  EXPECT_EQ(c525->transport, "USB UVC");
  const DeviceInfo* lifecam = find_info(list, kLifeCamId);
  ASSERT_TRUE(lifecam);
  EXPECT_EQ(lifecam->vendor, "Microsoft");
  EXPECT_EQ(lifecam->model, "Microsoft\xC2\xAE LifeCam HD-3000");
  EXPECT_EQ(lifecam->serial, "");
  const DeviceInfo* mono = find_info(list, kMonoId);
  ASSERT_TRUE(mono);
  EXPECT_EQ(mono->transport, "V4L2 (mono_sensor)");
  EXPECT_EQ(mono->model, "Mono Sensor");
  // Every listed URI opens the camera it names.
  for (const auto& d : list) {
    auto cam = rig.open(d.uri);
    EXPECT_EQ(cam->info().id, d.id);
  }
}

TEST_F(V4l2Camera_, OpensByStableIdDevPathAndByIdLink) {
  auto by_id = rig.open("v4l2://" + kC525Id);
  EXPECT_EQ(by_id->device_path(), rig.video(0));
  EXPECT_EQ(by_id->state(), CameraState::kOpened);
  auto by_path = rig.open("v4l2:///dev/video0");
  EXPECT_EQ(by_path->info().id, kC525Id);
  EXPECT_EQ(by_path->device_path(), rig.video(0));
  auto by_link = rig.open("v4l2:///dev/v4l/by-id/" + kLifeCamId);
  EXPECT_EQ(by_link->device_path(), rig.video(2));
  EXPECT_EQ(by_link->info().id, kLifeCamId);
  // Through the CameraManager, as the plugin does.
  CameraManager manager;
  manager.add_backend(rig.backend);
  auto via_manager = manager.open("v4l2://" + kC525Id);
  EXPECT_EQ(via_manager->info().serial, "0320EC60");
  EXPECT_EQ(manager.list().size(), 3u);
}

TEST_F(V4l2Camera_, MissingCamerasAreNotFound) {
  const std::string msg =
      expect_error(ErrorCode::kNotFound, [&] { rig.open("v4l2://usb-nope-video-index0"); });
  EXPECT_NE(msg.find(kC525Id), std::string::npos) << "should list the ids present: " << msg;
  expect_error(ErrorCode::kNotFound, [&] { rig.open("v4l2:///dev/video9"); });
  expect_error(ErrorCode::kInvalidArgument, [&] { rig.open("v4l2://"); });
  expect_error(ErrorCode::kInvalidArgument, [&] { rig.open("v4l2:///dev/video0?fps=30"); });
}

TEST_F(V4l2Camera_, MetadataNodeIsRejectedByName) {
  std::string msg =
      expect_error(ErrorCode::kInvalidArgument, [&] { rig.open("v4l2:///dev/video1"); });
  EXPECT_NE(msg.find(rig.video(1)), std::string::npos) << msg;
  EXPECT_NE(msg.find("not a video capture device"), std::string::npos) << msg;
  EXPECT_NE(msg.find("metadata"), std::string::npos) << msg;
  msg = expect_error(ErrorCode::kInvalidArgument, [&] { rig.open("v4l2://" + kC525MetaId); });
  EXPECT_NE(msg.find(rig.video(1)), std::string::npos) << msg;
}

TEST_F(V4l2Camera_, FormatsAreEnumerated) {
  auto cam = rig.open("v4l2://" + kC525Id);
  const auto& formats = cam->formats();
  ASSERT_EQ(formats.size(), 2u);
  EXPECT_EQ(formats[0].fourcc_text, "YUYV");
  EXPECT_EQ(formats[0].pixel_format, PixelFormat::kYUYV);
  EXPECT_EQ(formats[1].fourcc_text, "MJPG");
  EXPECT_EQ(formats[1].description, "Motion-JPEG");
  EXPECT_TRUE(formats[1].compressed);
  const auto rate_at = [](const V4l2Format& f, int w, int h) {
    for (const auto& s : f.sizes) {
      if (s.width == w && s.height == h && !s.intervals.empty())
        return s.intervals.front().rate_hz();
    }
    return 0.0;
  };
  EXPECT_EQ(rate_at(formats[0], 1280, 720), 10.0);
  EXPECT_EQ(rate_at(formats[1], 1280, 720), 30.0);
  EXPECT_EQ(rate_at(formats[0], 640, 480), 30.0);
  EXPECT_EQ(formats[1].sizes.size(), 6u);
}

TEST_F(V4l2Camera_, ValidateAdjustsWithoutTouchingTheDevice) {
  auto cam = rig.open("v4l2://" + kC525Id);
  const uint64_t changes = rig.emu->state_changes(rig.video(0));
  const v4l2_pix_format before = rig.emu->format(rig.video(0));
  CameraConfig req;
  req.pixel_format = PixelFormat::kMJPEG;
  req.roi = cv::Rect(10, 20, 1000, 700);
  req.frame_rate_hz = 29;
  req.exposure_us = 12345;
  const CameraConfig v = cam->validate(req);
  EXPECT_EQ(*v.pixel_format, PixelFormat::kMJPEG);
  EXPECT_EQ(*v.roi, cv::Rect(0, 0, 960, 720));  // nearest size; UVC cannot crop
  EXPECT_EQ(*v.frame_rate_hz, 30.0);
  EXPECT_EQ(*v.exposure_us, 12300.0);  // 100 us units
  // YUYV at 720p: USB 2 bandwidth allows 10 fps at most.
  req.pixel_format = PixelFormat::kYUYV;
  req.roi = cv::Rect(0, 0, 1280, 720);
  req.exposure_us.reset();
  EXPECT_EQ(*cam->validate(req).frame_rate_hz, 10.0);
  EXPECT_EQ(rig.emu->state_changes(rig.video(0)), changes);
  EXPECT_EQ(rig.emu->format(rig.video(0)).pixelformat, before.pixelformat);
  EXPECT_EQ(rig.emu->format(rig.video(0)).width, before.width);

  CameraConfig bad;
  bad.pixel_format = PixelFormat::kMono8;
  std::string msg = expect_error(ErrorCode::kUnsupported, [&] { cam->validate(bad); });
  EXPECT_NE(msg.find("HD Webcam C525"), std::string::npos) << msg;
  EXPECT_NE(msg.find("Mono8"), std::string::npos) << msg;
  bad = {};
  bad.gain_db = 6;
  expect_error(ErrorCode::kUnsupported, [&] { cam->validate(bad); });
  bad = {};
  bad.roi = cv::Rect(0, 0, 0, 480);
  expect_error(ErrorCode::kInvalidArgument, [&] { cam->validate(bad); });
  bad = {};
  bad.frame_rate_hz = -1;
  expect_error(ErrorCode::kInvalidArgument, [&] { cam->validate(bad); });
}

TEST_F(V4l2Camera_, ConfigureAppliesAndReportsDriverAdjustments) {
  auto cam = rig.open("v4l2://" + kC525Id);
  CameraConfig req;
  req.pixel_format = PixelFormat::kMJPEG;
  req.roi = cv::Rect(0, 0, 1000, 700);
  req.frame_rate_hz = 14;
  req.exposure_us = 20000;
  req.queue_depth = 3;
  cam->configure(req);
  EXPECT_EQ(cam->state(), CameraState::kConfigured);
  const CameraConfig cur = cam->current_config();
  EXPECT_EQ(*cur.pixel_format, PixelFormat::kMJPEG);
  EXPECT_EQ(*cur.roi, cv::Rect(0, 0, 960, 720));
  EXPECT_EQ(*cur.frame_rate_hz, 15.0);
  EXPECT_EQ(*cur.exposure_us, 20000.0);
  EXPECT_EQ(cur.queue_depth, 3);
  EXPECT_EQ(rig.emu->format(rig.video(0)).width, 960u);
  EXPECT_EQ(rig.emu->frame_rate(rig.video(0)), 15.0);
  EXPECT_EQ(rig.emu->control(rig.video(0), V4L2_CID_EXPOSURE_AUTO), V4L2_EXPOSURE_MANUAL);
  EXPECT_EQ(rig.emu->control(rig.video(0), V4L2_CID_EXPOSURE_ABSOLUTE), 200);
  // A new size without a frame rate keeps the previous rate (uvcvideo would reset it to 30).
  CameraConfig size_only;
  size_only.roi = cv::Rect(0, 0, 640, 480);
  cam->configure(size_only);
  EXPECT_EQ(*cam->current_config().frame_rate_hz, 15.0);
  EXPECT_EQ(*cam->current_config().pixel_format, PixelFormat::kMJPEG);
}

TEST_F(V4l2Camera_, StateMachine) {
  auto cam = rig.open("v4l2://" + kC525Id);
  Frame f;
  expect_error(ErrorCode::kState, [&] { cam->next_frame(10, &f); });
  cam->stop();   // no-op when not streaming
  cam->start();  // from Opened: configures the current format
  EXPECT_EQ(cam->state(), CameraState::kStreaming);
  EXPECT_EQ(*cam->current_config().pixel_format, PixelFormat::kYUYV);
  expect_error(ErrorCode::kState, [&] { cam->start(); });
  expect_error(ErrorCode::kState, [&] { cam->configure({}); });
  EXPECT_NO_THROW(cam->validate({}));  // allowed while streaming, changes nothing
  cam->stop();
  EXPECT_EQ(cam->state(), CameraState::kConfigured);
  EXPECT_EQ(rig.emu->live_mappings(), 0);
  cam->configure({});
  cam->start();
  cam->stop();
}

// Streams and checks that the board is found in the decoded frames.
void stream_and_detect(Rig& rig, PixelFormat format, cv::Size size, double fps, int frames) {
  auto cam = rig.open("v4l2://" + kC525Id);
  CameraConfig req;
  req.pixel_format = format;
  req.roi = cv::Rect(0, 0, size.width, size.height);
  req.frame_rate_hz = fps;
  cam->configure(req);
  cam->start();
  EXPECT_TRUE(rig.emu->streaming(rig.video(0)));
  EXPECT_EQ(rig.emu->live_mappings(), 4);  // queue_depth buffers
  const Board target;
  uint64_t last_id = 0;
  int64_t last_ts = 0;
  for (int i = 0; i < frames; ++i) {
    Frame f;
    ASSERT_EQ(cam->next_frame(2000, &f), FrameStatus::kOk) << i;
    EXPECT_EQ(f.image.type(), CV_8UC3);
    EXPECT_EQ(f.image.size(), size);
    EXPECT_EQ(f.source_format, format);
    if (i > 0) {
      EXPECT_GT(f.frame_id, last_id);
      EXPECT_GT(f.timestamp_ns, last_ts);
    }
    last_id = f.frame_id;
    last_ts = f.timestamp_ns;
    if (i == 0) {
      const Detection d = target.detect(f.image);
      EXPECT_GE(d.size(), static_cast<size_t>(target.num_corners()) * 3 / 4);
      cv::Mat grey, diff;
      cv::cvtColor(f.image, grey, cv::COLOR_BGR2GRAY);
      cv::absdiff(grey, rig.emu->scene(rig.video(0)), diff);
      EXPECT_LT(cv::mean(diff)[0], 4.0) << "decoded frame differs from the rendered scene";
    }
  }
  EXPECT_EQ(cam->stats().frames_delivered, static_cast<uint64_t>(frames));
  EXPECT_EQ(cam->stats().frames_incomplete, 0u);
  cam->stop();
  EXPECT_FALSE(rig.emu->streaming(rig.video(0)));
  EXPECT_EQ(rig.emu->live_mappings(), 0);
}

TEST_F(V4l2Camera_, StreamsMjpeg720pAndBoardIsDetected) {
  stream_and_detect(rig, PixelFormat::kMJPEG, {1280, 720}, 30, 5);
}

TEST_F(V4l2Camera_, StreamsYuyvAndBoardIsDetected) {
  stream_and_detect(rig, PixelFormat::kYUYV, {640, 480}, 30, 3);
}

TEST_F(V4l2Camera_, StreamsYuyv720pAt10Fps) {
  auto cam = rig.open("v4l2://" + kC525Id);
  CameraConfig req;
  req.pixel_format = PixelFormat::kYUYV;
  req.roi = cv::Rect(0, 0, 1280, 720);
  cam->configure(req);
  EXPECT_EQ(*cam->current_config().frame_rate_hz, 10.0);
  cam->start();
  Frame a, b;
  ASSERT_EQ(cam->next_frame(1000, &a), FrameStatus::kOk);
  ASSERT_EQ(cam->next_frame(1000, &b), FrameStatus::kOk);
  EXPECT_NEAR((b.timestamp_ns - a.timestamp_ns) / 1e6, 100.0, 1.0);
  EXPECT_EQ(b.image.size(), cv::Size(1280, 720));
}

TEST_F(V4l2Camera_, CorruptMjpegFramesAreCountedAndSkipped) {
  auto cam = rig.open("v4l2://" + kC525Id);
  CameraConfig req;
  req.pixel_format = PixelFormat::kMJPEG;
  req.roi = cv::Rect(0, 0, 640, 480);
  cam->configure(req);
  // Corruption is armed before (re)starting, so that no clean frame is already waiting in a
  // buffer: the stream's first frames are the corrupt ones.
  rig.emu->corrupt_next_frames(rig.video(0), 2, emu::Corruption::kTruncated);
  cam->start();
  Frame f;
  ASSERT_EQ(cam->next_frame(2000, &f), FrameStatus::kOk);
  EXPECT_EQ(f.frame_id, 2u);
  EXPECT_EQ(cam->stats().frames_incomplete, 2u);
  EXPECT_EQ(cam->stats().frames_delivered, 1u);
  EXPECT_FALSE(Board().detect(f.image).empty());
  cam->stop();
  rig.emu->corrupt_next_frames(rig.video(0), 1, emu::Corruption::kErrorFlag);
  cam->start();
  ASSERT_EQ(cam->next_frame(2000, &f), FrameStatus::kOk);
  EXPECT_EQ(f.frame_id, 1u);
  EXPECT_EQ(cam->stats().frames_incomplete, 3u);
  // Nothing but corrupt frames: the timeout still holds.
  cam->stop();
  rig.emu->corrupt_next_frames(rig.video(0), 1000, emu::Corruption::kTruncated);
  cam->start();
  const auto t0 = std::chrono::steady_clock::now();
  EXPECT_EQ(cam->next_frame(150, &f), FrameStatus::kTimeout);
  EXPECT_LT(elapsed_ms(t0), 250);
  EXPECT_GE(cam->stats().frames_incomplete, 4u);
  EXPECT_EQ(cam->stats().frames_delivered, 2u);
}

TEST_F(V4l2Camera_, NextFrameNeverWaitsLongerThanItsTimeout) {
  auto cam = rig.open("v4l2://" + kC525Id);
  CameraConfig req;
  req.pixel_format = PixelFormat::kYUYV;
  req.roi = cv::Rect(0, 0, 320, 240);
  req.frame_rate_hz = 5;
  cam->configure(req);
  cam->start();
  Frame f;
  auto t0 = std::chrono::steady_clock::now();
  EXPECT_EQ(cam->next_frame(0, &f), FrameStatus::kTimeout);  // first frame is 200 ms away
  EXPECT_LT(elapsed_ms(t0), 50);
  ASSERT_EQ(cam->next_frame(1000, &f), FrameStatus::kOk);
  t0 = std::chrono::steady_clock::now();
  EXPECT_EQ(cam->next_frame(60, &f), FrameStatus::kTimeout);
  EXPECT_GE(elapsed_ms(t0), 59);
  EXPECT_LT(elapsed_ms(t0), 160);  // 60 ms plus scheduling slack on a loaded machine
}

TEST_F(V4l2Camera_, DroppedFramesAreCountedFromSequenceGaps) {
  auto cam = rig.open("v4l2://" + kC525Id);
  CameraConfig req;
  req.pixel_format = PixelFormat::kMJPEG;
  req.roi = cv::Rect(0, 0, 320, 240);
  req.queue_depth = 2;
  cam->configure(req);
  cam->start();
  Frame f;
  ASSERT_EQ(cam->next_frame(1000, &f), FrameStatus::kOk);
  std::this_thread::sleep_for(std::chrono::milliseconds(300));  // ~9 frames, 2 buffers
  for (int i = 0; i < 3; ++i) ASSERT_EQ(cam->next_frame(1000, &f), FrameStatus::kOk);
  EXPECT_GE(cam->stats().frames_dropped, 5u);
}

TEST_F(V4l2Camera_, ReadIoFallbackWithGreyAndStepwiseSizes) {
  auto cam = rig.open("v4l2://" + kMonoId);
  EXPECT_TRUE(cam->uses_read_io());
  ASSERT_EQ(cam->formats().size(), 1u);
  EXPECT_TRUE(cam->formats()[0].stepwise);
  EXPECT_EQ(cam->formats()[0].step_width, 16);
  // No TRY_FMT on this driver: the backend adjusts on its own, the same way S_FMT then does.
  CameraConfig req;
  req.pixel_format = PixelFormat::kMono8;
  req.roi = cv::Rect(0, 0, 650, 470);
  EXPECT_EQ(*cam->validate(req).roi, cv::Rect(0, 0, 656, 472));
  CameraConfig rate;
  rate.frame_rate_hz = 15;
  expect_error(ErrorCode::kUnsupported, [&] { cam->validate(rate); });
  cam->configure(req);
  EXPECT_EQ(rig.emu->format(rig.video(4)).width, 656u);
  cam->start();
  Frame f;
  ASSERT_EQ(cam->next_frame(1000, &f), FrameStatus::kOk);
  EXPECT_EQ(f.image.type(), CV_8UC1);
  EXPECT_EQ(f.image.size(), cv::Size(656, 472));
  EXPECT_EQ(cv::norm(f.image, rig.emu->scene(rig.video(4)), cv::NORM_INF), 0.0);  // lossless
  ASSERT_EQ(cam->next_frame(1000, &f), FrameStatus::kOk);
  EXPECT_EQ(f.frame_id, 1u);
  rig.emu->corrupt_next_frames(rig.video(4), 1, emu::Corruption::kTruncated);
  ASSERT_EQ(cam->next_frame(1000, &f), FrameStatus::kOk);
  EXPECT_EQ(cam->stats().frames_incomplete, 1u);
  cam->stop();
  // Stopping a read() capture reopens the node; the format can change again.
  EXPECT_EQ(rig.emu->open_fds(), 1);
  req.roi = cv::Rect(0, 0, 320, 240);
  cam->configure(req);
  cam->start();
  ASSERT_EQ(cam->next_frame(1000, &f), FrameStatus::kOk);
  EXPECT_EQ(f.image.size(), cv::Size(320, 240));
}

TEST_F(V4l2Camera_, SecondOpenerSeesTheDeviceBusy) {
  auto a = rig.open("v4l2://" + kC525Id);
  auto b = rig.open("v4l2:///dev/video0");
  b->configure({});
  a->start();
  CameraConfig req;
  req.roi = cv::Rect(0, 0, 320, 240);
  std::string msg = expect_error(ErrorCode::kDevice, [&] { b->configure(req); });  // S_FMT
  EXPECT_NE(msg.find("busy"), std::string::npos) << msg;
  msg = expect_error(ErrorCode::kDevice, [&] { b->start(); });  // REQBUFS
  EXPECT_NE(msg.find("busy"), std::string::npos) << msg;
  EXPECT_EQ(b->state(), CameraState::kConfigured);
  a->stop();
  b->start();
  Frame f;
  EXPECT_EQ(b->next_frame(1000, &f), FrameStatus::kOk);
}

const FeatureInfo* find_feature(const std::vector<FeatureInfo>& list, const std::string& name) {
  for (const auto& f : list) {
    if (f.name == name) return &f;
  }
  return nullptr;
}

TEST_F(V4l2Camera_, ControlsAreEnumeratedWithV4l2CtlNames) {
  auto cam = rig.open("v4l2://" + kC525Id);
  const auto features = cam->features();
  for (const char* name :
       {"brightness", "contrast", "saturation", "white_balance_automatic", "gain",
        "power_line_frequency", "white_balance_temperature", "sharpness", "backlight_compensation",
        "auto_exposure", "exposure_time_absolute", "exposure_dynamic_framerate", "pan_absolute",
        "tilt_absolute", "focus_absolute", "focus_automatic_continuous", "zoom_absolute"}) {
    EXPECT_TRUE(find_feature(features, name)) << name;
  }
  EXPECT_EQ(features.size(), 17u);  // the control classes are not features
  const FeatureInfo* focus = find_feature(features, "focus_absolute");
  ASSERT_TRUE(focus);
  EXPECT_EQ(focus->type, FeatureType::kInteger);
  EXPECT_EQ(focus->min, "0");
  EXPECT_EQ(focus->max, "255");
  EXPECT_EQ(focus->value, "35");  // where autofocus put the lens
  EXPECT_FALSE(focus->writable);  // inactive while autofocus runs
  const FeatureInfo* ae = find_feature(features, "auto_exposure");
  ASSERT_TRUE(ae);
  EXPECT_EQ(ae->type, FeatureType::kEnumeration);
  EXPECT_EQ(ae->value, "3");
  EXPECT_EQ(ae->options, (std::vector<std::string>{"1: Manual Mode", "3: Aperture Priority Mode"}));
  const FeatureInfo* exposure = find_feature(features, "exposure_time_absolute");
  ASSERT_TRUE(exposure);
  EXPECT_EQ(exposure->unit, "100 us");
  EXPECT_EQ(exposure->min, "3");
  EXPECT_EQ(exposure->max, "2047");
  const FeatureInfo* af = find_feature(features, "focus_automatic_continuous");
  ASSERT_TRUE(af);
  EXPECT_EQ(af->type, FeatureType::kBoolean);
  EXPECT_TRUE(af->writable);
}

TEST_F(V4l2Camera_, ControlsGetSetRangeAndUnknown) {
  auto cam = rig.open("v4l2://" + kC525Id);
  cam->set_feature("brightness", "200");
  EXPECT_EQ(cam->get_feature("brightness"), "200");
  EXPECT_EQ(rig.emu->control(rig.video(0), V4L2_CID_BRIGHTNESS), 200);
  std::string msg =
      expect_error(ErrorCode::kInvalidArgument, [&] { cam->set_feature("brightness", "256"); });
  EXPECT_NE(msg.find("HD Webcam C525"), std::string::npos) << msg;
  EXPECT_NE(msg.find(rig.video(0)), std::string::npos) << msg;
  EXPECT_NE(msg.find("brightness"), std::string::npos) << msg;
  EXPECT_NE(msg.find("[0, 255]"), std::string::npos) << msg;
  expect_error(ErrorCode::kInvalidArgument, [&] { cam->set_feature("brightness", "-1"); });
  expect_error(ErrorCode::kInvalidArgument, [&] { cam->set_feature("brightness", "bright"); });
  EXPECT_EQ(rig.emu->control(rig.video(0), V4L2_CID_BRIGHTNESS), 200);
  msg = expect_error(ErrorCode::kNotFound, [&] { cam->set_feature("iris_absolute", "1"); });
  EXPECT_NE(msg.find("iris_absolute"), std::string::npos) << msg;
  expect_error(ErrorCode::kNotFound, [&] { cam->get_feature("iris_absolute"); });
  // Menus take the index or the item's name; skipped and out-of-range items are refused.
  expect_error(ErrorCode::kInvalidArgument, [&] { cam->set_feature("auto_exposure", "2"); });
  expect_error(ErrorCode::kInvalidArgument, [&] { cam->set_feature("auto_exposure", "7"); });
  expect_error(ErrorCode::kInvalidArgument,
               [&] { cam->set_feature("auto_exposure", "Shutter Priority Mode"); });
  cam->set_feature("power_line_frequency", "50 Hz");
  EXPECT_EQ(cam->get_feature("power_line_frequency"), "1");
  // Manual controls are inactive while their automatic mode is on.
  msg = expect_error(ErrorCode::kInvalidArgument,
                     [&] { cam->set_feature("exposure_time_absolute", "100"); });
  EXPECT_NE(msg.find("inactive"), std::string::npos) << msg;
  cam->set_feature("auto_exposure", "Manual Mode");
  EXPECT_EQ(cam->get_feature("auto_exposure"), "1");
  cam->set_feature("exposure_time_absolute", "100");
  EXPECT_EQ(cam->get_feature("exposure_time_absolute"), "100");
  // The driver rounds to the control's step (focus: 5).
  cam->set_feature("focus_automatic_continuous", "false");
  cam->set_feature("focus_absolute", "52");
  EXPECT_EQ(cam->get_feature("focus_absolute"), "50");
  expect_error(ErrorCode::kInvalidArgument,
               [&] { cam->set_feature("focus_automatic_continuous", "maybe"); });
  // Controls work while streaming too.
  cam->start();
  cam->set_feature("gain", "10");
  EXPECT_EQ(cam->get_feature("gain"), "10");
}

TEST_F(V4l2Camera_, LegacyDriverControlsReadOnlyAndButtons) {
  auto cam = rig.open("v4l2://" + kMonoId);  // QUERYCTRL and G/S_CTRL only
  const auto features = cam->features();
  ASSERT_EQ(features.size(), 4u);
  const FeatureInfo* temp = find_feature(features, "sensor_temperature");
  ASSERT_TRUE(temp);
  EXPECT_FALSE(temp->writable);
  const FeatureInfo* wb = find_feature(features, "do_white_balance");
  ASSERT_TRUE(wb);
  EXPECT_EQ(wb->type, FeatureType::kCommand);
  EXPECT_FALSE(wb->readable);
  expect_error(ErrorCode::kInvalidArgument, [&] { cam->set_feature("sensor_temperature", "20"); });
  expect_error(ErrorCode::kInvalidArgument, [&] { cam->get_feature("do_white_balance"); });
  cam->set_feature("do_white_balance", "");
  cam->set_feature("brightness", "17");
  EXPECT_EQ(rig.emu->control(rig.video(4), V4L2_CID_BRIGHTNESS), 17);
  EXPECT_EQ(cam->get_feature("brightness"), "17");
  // Nothing to lock on this camera, and no failure either.
  EXPECT_EQ(cam->lock_for_calibration(), (std::map<std::string, std::string>{{"gain", "0"}}));
}

TEST_F(V4l2Camera_, CalibrationLockFixesFocusAndExposure) {
  auto cam = rig.open("v4l2://" + kC525Id);
  cam->start();
  const auto locked = cam->lock_for_calibration();
  const std::map<std::string, std::string> expected = {
      {"focus_automatic_continuous", "0"}, {"auto_exposure", "1"},
      {"exposure_dynamic_framerate", "0"}, {"focus_absolute", "35"},
      {"exposure_time_absolute", "166"},   {"gain", "64"}};
  EXPECT_EQ(locked, expected);
  const std::string v = rig.video(0);
  EXPECT_EQ(rig.emu->control(v, V4L2_CID_FOCUS_AUTO), 0);
  EXPECT_EQ(rig.emu->control(v, V4L2_CID_EXPOSURE_AUTO), V4L2_EXPOSURE_MANUAL);
  EXPECT_EQ(rig.emu->control(v, V4L2_CID_FOCUS_ABSOLUTE), 35);
  EXPECT_EQ(rig.emu->control(v, V4L2_CID_EXPOSURE_ABSOLUTE), 166);
  const auto features = cam->features();
  EXPECT_TRUE(find_feature(features, "focus_absolute")->writable);
  Frame f;
  EXPECT_EQ(cam->next_frame(1000, &f), FrameStatus::kOk);
  // Locking again records the same values.
  EXPECT_EQ(cam->lock_for_calibration(), expected);
}

TEST_F(V4l2Camera_, CalibrationLockOnFixedFocusCamera) {
  auto cam = rig.open("v4l2://" + kLifeCamId);
  const auto locked = cam->lock_for_calibration();
  EXPECT_EQ(locked.count("focus_absolute"), 0u);
  EXPECT_EQ(locked.at("auto_exposure"), "1");
  EXPECT_EQ(locked.at("exposure_time_absolute"), "312");
}

}  // namespace
}  // namespace posecal::test
