// Synthetic camera: renders a calibration target at any 6-DoF pose through any camera model,
// including its true lens distortion. It is the test bed of everything else, so the rendering is
// exact by construction:
//   every output sample (pixel centres at integer coordinates, supersampled n x n) is mapped
//   through the inverse camera model to a ray, intersected with the board plane, and the board
//   texture (with a mip level chosen for the footprint) is sampled bilinearly; samples are
//   averaged to pixels, then optics blur, exposure/contrast and sensor noise are applied.
// Deterministic per seed: frame k of a camera with seed s is a pure function of (s, k, pose).
#pragma once

#include <cstdint>
#include <memory>
#include <opencv2/core.hpp>

#include "lens/camera_model.hpp"
#include "lens/geometry.hpp"
#include "board/board.hpp"

namespace posecal {

// Two rendering paths that differ in how they sample and filter, so that a detector (or an engine
// tuned on its results) that suits one of them is exposed by the other (docs/benchmarks.md).
enum class Renderer {
  // Ray casting: every one of n x n samples per pixel is unprojected through the true lens and
  // meets the board; the texture is mip-mapped and sampled bilinearly, samples are box-averaged;
  // Gaussian optics blur and additive Gaussian noise, in grey levels.
  kRayCast,
  // Warping: the board is first drawn through its homography into an ideal pinhole image at
  // twice the focal length (warpPerspective, bilinear; a tent filter there stands in for the
  // pixel's area), which is then resampled at the pixel centres through the true lens (bicubic,
  // no integration over the lens' local stretch of the pixel); the optics is a defocus disc of
  // the same second moment as blur_sigma_px, applied in linear radiance; noise is signal
  // dependent (shot and read noise, noise_sigma at mid grey), and a 1.6 tone curve maps radiance
  // to grey levels (paper_white, ink_black and background stay the grey levels they name).
  // supersample is not used.
  kWarp,
};

struct RenderOptions {
  Renderer renderer = Renderer::kRayCast;
  int supersample = 2;               // n x n samples per pixel (kRayCast)
  double blur_sigma_px = 0.0;        // Gaussian optics blur, output pixels
  double noise_sigma = 0.0;          // additive Gaussian sensor noise, grey levels
  double paper_white = 235.0;        // grey level of the board's white at exposure 1
  double ink_black = 25.0;           // grey level of the board's black at exposure 1
  double exposure = 1.0;             // multiplies the scene radiance (saturates at 255)
  double background = 110.0;         // mean background grey level
  double background_texture = 30.0;  // amplitude of a smooth random background pattern (0: flat)
  uint64_t seed = 1;

  // Throws Error(kInvalidArgument) naming the offending field.
  void validate() const;
};

class SyntheticCamera {
 public:
  // The largest camera the renderer simulates: 2^25 pixels (33.5 MP), and at most 2^27 ray
  // samples (pixels x supersample^2). Rendering holds about 90 bytes per pixel at the default
  // supersampling (rays, float images, noise): about 3 GB at the limit.
  static constexpr long long kMaxPixels = 1LL << 25;
  static constexpr long long kMaxSamples = 1LL << 27;
  // Throws Error(kInvalidArgument) if `truth` is invalid or beyond kMaxPixels / kMaxSamples.
  SyntheticCamera(const CameraModel& truth, const Board& board,
                  const RenderOptions& options = {});
  ~SyntheticCamera();
  SyntheticCamera(SyntheticCamera&&) noexcept;
  SyntheticCamera& operator=(SyntheticCamera&&) noexcept;

  const CameraModel& model() const;  // ground truth
  const Board& board() const;
  const RenderOptions& options() const;
  void set_options(const RenderOptions& options);  // keeps the cached ray map

  // Renders the board at T_cam_board. 8-bit grey, model().size(). The frame counter advances;
  // noise depends on (seed, frame index).
  cv::Mat render(const Pose& T_cam_board);
  uint64_t frames_rendered() const;

  // True projections of the target's corners at a pose (NaN behind the camera).
  std::vector<cv::Point2d> true_corners(const Pose& T_cam_board) const;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace posecal
