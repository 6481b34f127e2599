// Test support: a GigE Vision camera simulated in-process by Aravis (ArvGvFakeCamera) that
// answers GVCP and streams GVSP on a loopback address, filling every frame with a rendered view
// of the calibration board (posecal::SyntheticCamera, C525 model, 1280x720 scene).
//
// Every frame is a pure function of its GVSP frame id, pixel format and region of interest, so a
// test can recompute exactly what the camera sent (expected_engine) and compare it with what the
// backend delivered, bit for bit. Frame k shows view k % n_views; its first row starts with a
// stamp (tag, frame id) so two frames never look alike.
//
// Alternatively the frames come from a PayloadSource (closed-loop tests: guided_loop.hpp), which
// the simulator's thread asks for every frame it sends.
#pragma once

#include <arv.h>

#include <atomic>
#include <functional>
#include <memory>
#include <string>
#include <vector>

#include "device/camera.hpp"
#include "sim/synthetic.hpp"
#include "lens/reference_models.hpp"

namespace posecal::testing {

struct FakeScene {
  CameraModel model = c525_reference_model();
  Board board;
  std::vector<cv::Mat> views;  // CV_8UC1, model size
  uint32_t tag = 1;
};

// Renders `n_views` random board views (fixed seed). Shared by restarts of one simulator.
std::shared_ptr<const FakeScene> make_scene(uint64_t seed, int n_views, uint32_t tag);

class FakeGvCamera {
 public:
  // The raw payload of frame `frame_id` in the simulator's current format and region of
  // interest. Called on the simulator's thread. nullptr (or a payload of the wrong size, which
  // is counted in source_rejects()) leaves the frame as the simulator made it.
  using PayloadSource = std::function<std::shared_ptr<const std::vector<uint8_t>>(
      uint64_t frame_id, PixelFormat format, const cv::Rect& roi)>;

  FakeGvCamera(std::string serial, std::string address, std::shared_ptr<const FakeScene> scene);
  FakeGvCamera(std::string serial, std::string address, PayloadSource source);
  ~FakeGvCamera();
  FakeGvCamera(const FakeGvCamera&) = delete;
  FakeGvCamera& operator=(const FakeGvCamera&) = delete;

  // Starts the simulator; false if it cannot listen (address absent, GVCP port 3956 taken).
  bool start();
  // Stops it as if the camera was unplugged: its sockets close, nothing answers any more.
  void stop();
  bool running() const { return gv_ != nullptr; }
  // Fraction (0..1) of GVSP packets the simulator drops on purpose.
  void set_lost_packet_ratio(double ratio);

  const std::string& serial() const { return serial_; }
  const std::string& address() const { return address_; }
  std::string device_id() const { return "Aravis-Fake-" + serial_; }
  // The fixed scene (not for a camera made from a PayloadSource).
  const FakeScene& scene() const { return *scene_; }
  uint64_t frames_filled() const { return filled_->load(); }
  uint64_t last_frame_id() const { return last_id_->load(); }
  uint64_t source_rejects() const { return rejects_->load(); }

  // The 8-bit grey image behind frame `frame_id` over `roi` (sensor coordinates).
  cv::Mat expected_grey(uint64_t frame_id, const cv::Rect& roi) const;
  // The raw GVSP payload of that frame in `format`, and what convert_to_engine makes of it.
  std::vector<uint8_t> expected_raw(uint64_t frame_id, PixelFormat format,
                                    const cv::Rect& roi) const;
  cv::Mat expected_engine(uint64_t frame_id, PixelFormat format, const cv::Rect& roi) const;

 private:
  static void fill(ArvBuffer* buffer, void* self, guint32 exposure_us, guint32 gain,
                   ArvPixelFormat format);

  std::string serial_, address_;
  std::shared_ptr<const FakeScene> scene_;
  PayloadSource source_;
  ArvGvFakeCamera* gv_ = nullptr;
  double lost_ratio_ = 0.0;
  std::shared_ptr<std::atomic<uint64_t>> filled_ = std::make_shared<std::atomic<uint64_t>>(0);
  std::shared_ptr<std::atomic<uint64_t>> last_id_ = std::make_shared<std::atomic<uint64_t>>(0);
  std::shared_ptr<std::atomic<uint64_t>> rejects_ = std::make_shared<std::atomic<uint64_t>>(0);
};

// Raw payload of a grey image in a camera pixel format (Mono16: grey * 256 + 0x5a; RGB8: red and
// green grey, blue inverted; Bayer: the grey image as the mosaic).
std::vector<uint8_t> raw_from_grey(const cv::Mat& grey, PixelFormat format);

}  // namespace posecal::testing
