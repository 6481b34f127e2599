// Test support: an Aravis GigE Vision simulator whose frames come from a GuidedScene (the
// closed loop of guided_loop.hpp through GVCP/GVSP), shared by the closed-loop tests and the
// many-camera benchmark (tests/bench/aravis/bench_calibration_aravis.cpp).
#pragma once

#include <memory>
#include <string>
#include <vector>

#include "fake_gv_camera.hpp"
#include "guided_loop.hpp"
#include "select/engine.hpp"
#include "lens/reference_models.hpp"

namespace posecal::testing {

// The scene of core's closed-loop tests (tests/unit/test_closed_loop.cpp): a camera sampled
// around the C525 (1280x720, 10% standard deviation per parameter), noise 2, blur 0.8.
inline GuidedSceneOptions c525_scene(uint64_t seed, OperatorKind kind) {
  GuidedSceneOptions o;
  o.truth = sample_camera(c525_reference_model(), 0.1, 100 + seed);
  o.render.noise_sigma = 2.0;
  o.render.blur_sigma_px = 0.8;
  o.render.seed = seed;
  o.seed = seed;
  o.op.kind = kind;
  return o;
}

// The engine options of core's sim sessions for this scene.
inline EngineOptions engine_options_for(const GuidedSceneOptions& o) {
  EngineOptions eo;
  eo.board = o.board;
  eo.robot = o.op.kind == OperatorKind::kRobot;
  eo.target_timeout_frames = (o.op.move_frames + o.op.hold_frames) * o.op.max_tries + 1;
  return eo;
}

// Mono8: the payload is the image's bytes; the backend wraps them without conversion.
inline GuidedScene::Encoder mono8_encoder() {
  return [](const cv::Mat& grey) {
    const cv::Mat g = grey.isContinuous() ? grey : grey.clone();
    return std::vector<uint8_t>(g.datastart, g.dataend);
  };
}

inline GuidedCamera::Decoder mono8_decoder(cv::Size size) {
  return [size](const std::vector<uint8_t>& payload) {
    return convert_to_engine(PixelFormat::kMono8, payload.data(), payload.size(), size.width,
                             size.height, static_cast<size_t>(size.width));
  };
}

// The simulator's fill callback: Mono8 frames of the truth's size at offset 0 come from the
// scene; anything else is refused (counted in FakeGvCamera::source_rejects()).
inline FakeGvCamera::PayloadSource guided_source(std::shared_ptr<GuidedScene> scene) {
  return [scene](uint64_t frame_id, PixelFormat format, const cv::Rect& roi) -> Payload {
    if (format != PixelFormat::kMono8 || roi != cv::Rect(cv::Point(0, 0), scene->truth().size())) {
      return nullptr;
    }
    return scene->frame(frame_id);
  };
}

// The camera settings of a guided stream.
inline CameraConfig guided_config(const GuidedScene& scene, double fps) {
  CameraConfig c;
  c.pixel_format = PixelFormat::kMono8;
  c.roi = cv::Rect(cv::Point(0, 0), scene.truth().size());
  c.frame_rate_hz = fps;
  return c;
}

}  // namespace posecal::testing
