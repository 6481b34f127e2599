// Closed-loop calibration through the V4L2 backend: the engine guides a simulated operator,
// whose board the emulated Logitech C525 sends (MJPEG or YUYV payloads produced by the UVC
// emulator's sensor); the session receives it through make_v4l2_backend() with the emulator as
// the V4l2Io and the fixture sysfs tree, opened by its stable id, with the calibration lock
// applied by the session. The lockstep coupling is tests/aravis/guided_loop.hpp's. The result
// must converge within 5 sigma of the truth, every frame the engine used must be exactly the
// decoded payload the emulator sent, and nothing may leak.
#include <gtest/gtest.h>

#include <chrono>
#include <cstdio>

#include "guided_loop.hpp"
#include "calib/metrics.hpp"
#include "session/session.hpp"
#include "rig.hpp"
#include "lens/reference_models.hpp"

using namespace posecal;
using posecal::testing::GuidedCamera;
using posecal::testing::GuidedScene;
using posecal::testing::GuidedSceneOptions;
using posecal::testing::Payload;
using Clock = std::chrono::steady_clock;

namespace {

constexpr double kSessionLimitS = 45;

struct Case {
  const char* name;
  OperatorKind kind;
  uint64_t seed;
  PixelFormat format;
  uint32_t fourcc;
  double fps;  // the C525 offers YUYV 1280x720 at 10 fps at most, MJPEG at 30
};

GuidedSceneOptions scene_options(const Case& c) {
  // As core's closed-loop tests: a camera sampled around the C525, noise 2, blur 0.8.
  GuidedSceneOptions o;
  o.truth = sample_camera(c525_reference_model(), 0.1, 100 + c.seed);
  o.render.noise_sigma = 2.0;
  o.render.blur_sigma_px = 0.8;
  o.render.seed = c.seed;
  o.seed = c.seed;
  o.op.kind = c.kind;
  return o;
}

void closed_loop(const Case& c) {
  test::Rig rig;
  const GuidedSceneOptions options = scene_options(c);
  const cv::Size size = options.truth.size();
  auto scene = std::make_shared<GuidedScene>(
      options, [&c](const cv::Mat& grey) { return emu::encode_payload(c.fourcc, grey); });
  // The emulated sensor asks the scene for every frame it delivers while streaming.
  const std::string node = rig.video(0);
  rig.emu->set_payload_source(
      node, [scene, &c, size](uint32_t sequence, const v4l2_pix_format& f) -> Payload {
        if (f.pixelformat != c.fourcc || f.width != static_cast<uint32_t>(size.width) ||
            f.height != static_cast<uint32_t>(size.height)) {
          return nullptr;
        }
        return scene->frame(sequence);
      });
  // What the backend must make of a payload: the engine image, as convert_to_engine decodes it.
  auto decode = [&c, size](const std::vector<uint8_t>& payload) {
    const size_t stride = c.format == PixelFormat::kYUYV ? 2u * size.width : 0u;
    return convert_to_engine(c.format, payload.data(), payload.size(), size.width, size.height,
                             stride)
        .clone();
  };

  {
    CameraManager manager;
    manager.add_backend(make_v4l2_backend(rig.options()));
    std::unique_ptr<Camera> v4l2 = manager.open("v4l2://" + test::kC525Id);
    CameraConfig config;
    config.pixel_format = c.format;
    config.roi = cv::Rect(cv::Point(0, 0), size);
    config.frame_rate_hz = c.fps;
    v4l2->configure(config);
    ASSERT_EQ(*v4l2->current_config().roi, *config.roi);
    ASSERT_DOUBLE_EQ(*v4l2->current_config().frame_rate_hz, c.fps);
    auto guided = std::make_unique<GuidedCamera>(std::move(v4l2), scene, decode);
    GuidedCamera* cam = guided.get();

    EngineOptions eo;
    eo.robot = c.kind == OperatorKind::kRobot;
    eo.target_timeout_frames =
        (options.op.move_frames + options.op.hold_frames) * options.op.max_tries + 1;
    CalibrationSession s(std::move(guided), eo);
    const auto t0 = Clock::now();
    while (!s.finished() &&
           std::chrono::duration<double>(Clock::now() - t0).count() < kSessionLimitS) {
      const StepStatus st = s.step(2000);
      ASSERT_NE(st, StepStatus::kDisconnected);
      ASSERT_NE(st, StepStatus::kEndOfStream);
    }
    const double wall_s = std::chrono::duration<double>(Clock::now() - t0).count();
    ASSERT_TRUE(s.has_engine());
    const CalibrationEngine& e = s.engine();
    const auto g = cam->guided_stats();
    const auto st = scene->stats();
    std::printf(
        "%s: %s, %d keyframes, %llu frames, eps_gt %.3f px, %.1f s; sensor delivered %llu "
        "frames (%llu repeats), %llu exact, %llu dropped by the driver\n",
        c.name, engine_state_name(e.state()), e.keyframes(),
        static_cast<unsigned long long>(s.frames_processed()),
        e.result() ? ground_truth_error(options.truth, e.result()->model) : -1.0, wall_s,
        static_cast<unsigned long long>(st.frames), static_cast<unsigned long long>(st.repeats),
        static_cast<unsigned long long>(g.exact),
        static_cast<unsigned long long>(cam->stats().frames_dropped));

    // The calibration lock reached the device: focus and exposure manual.
    const auto& locked = s.locked_settings();
    ASSERT_EQ(locked.count("focus_automatic_continuous"), 1u);
    EXPECT_EQ(locked.at("focus_automatic_continuous"), "0");
    ASSERT_EQ(locked.count("auto_exposure"), 1u);
    EXPECT_EQ(locked.at("auto_exposure"), "1");
    EXPECT_EQ(rig.emu->control(node, V4L2_CID_FOCUS_AUTO), 0);
    EXPECT_EQ(rig.emu->control(node, V4L2_CID_EXPOSURE_AUTO), V4L2_EXPOSURE_MANUAL);

    EXPECT_TRUE(e.converged()) << engine_state_name(e.state()) << " " << e.failure_reason();
    ASSERT_NE(e.result(), nullptr);
    const CalibrationResult& r = *e.result();
    for (int i = 0; i < options.truth.num_params(); ++i) {
      EXPECT_LT(std::abs(r.model.params()[i] - options.truth.params()[i]),
                5 * r.std_scaled[i] + 1e-12)
          << c.name << " " << options.truth.param_names()[i] << ": estimate " << r.model.params()[i]
          << ", truth " << options.truth.params()[i] << ", sigma " << r.std_scaled[i];
    }
    // Every frame the engine used is the decoded payload of one operator step, once.
    EXPECT_EQ(g.delivered, s.frames_processed());
    EXPECT_EQ(g.exact, g.delivered) << cam->first_problem();
    EXPECT_EQ(g.corrupt, 0u) << cam->first_problem();
    EXPECT_EQ(g.unknown, 0u) << cam->first_problem();
    EXPECT_EQ(g.step_gaps, 0u);
    EXPECT_GE(st.steps, g.delivered);
    EXPECT_LE(st.steps, g.delivered + 1);
    EXPECT_EQ(cam->stats().frames_incomplete, 0u);
    EXPECT_EQ(cam->stats().disconnects, 0u);
  }
  // Session and camera gone: nothing left open or mapped.
  EXPECT_EQ(rig.emu->open_fds(), 0);
  EXPECT_EQ(rig.emu->live_mappings(), 0);
  EXPECT_EQ(rig.emu->bad_munmaps(), 0);
}

}  // namespace

TEST(V4l2ClosedLoop, PersonConvergesOnMjpeg720p) {
  closed_loop({"C525 MJPEG 1280x720, person", OperatorKind::kPerson, 2, PixelFormat::kMJPEG,
               V4L2_PIX_FMT_MJPEG, 30});
}

TEST(V4l2ClosedLoop, RobotConvergesOnMjpeg720p) {
  closed_loop({"C525 MJPEG 1280x720, robot", OperatorKind::kRobot, 4, PixelFormat::kMJPEG,
               V4L2_PIX_FMT_MJPEG, 30});
}

TEST(V4l2ClosedLoop, RobotConvergesOnYuyv720pAt10Fps) {
  closed_loop({"C525 YUYV 1280x720 at 10 fps, robot", OperatorKind::kRobot, 1, PixelFormat::kYUYV,
               V4L2_PIX_FMT_YUYV, 10});
}
