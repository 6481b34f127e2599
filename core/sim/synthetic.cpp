#include "sim/synthetic.hpp"

#include <Eigen/Dense>
#include <algorithm>
#include <cmath>
#include <opencv2/imgproc.hpp>

#include "common/error.hpp"

namespace posecal {

void RenderOptions::validate() const {
  auto fail = [](const std::string& why) {
    throw Error(ErrorCode::kInvalidArgument, "render options: " + why);
  };
  if (renderer != Renderer::kRayCast && renderer != Renderer::kWarp) fail("unknown renderer");
  if (supersample < 1 || supersample > 8) fail("supersample must be in [1, 8]");
  if (!(blur_sigma_px >= 0 && blur_sigma_px <= 20)) fail("blur sigma must be in [0, 20] px");
  if (!(noise_sigma >= 0 && noise_sigma <= 100))
    fail("noise sigma must be in [0, 100] grey levels");
  if (!(paper_white >= 0 && paper_white <= 255)) fail("paper white must be in [0, 255]");
  if (!(ink_black >= 0 && ink_black <= 255)) fail("ink black must be in [0, 255]");
  if (!(paper_white > ink_black + 10))
    fail("paper white must exceed ink black by > 10 grey levels");
  if (!(exposure > 0 && exposure <= 10)) fail("exposure must be in (0, 10]");
  if (!(background >= 0 && background <= 255)) fail("background must be in [0, 255]");
  if (!(background_texture >= 0 && background_texture <= 128))
    fail("background texture in [0, 128]");
}

namespace {

constexpr int kTexelsPerSquare = 128;   // level 0; a multiple of 2^kMipLevels
constexpr int kMipLevels = 5;           // 128 .. 8 texels per square
constexpr double kMarginSquares = 1.0;  // white paper around the printed pattern

uint64_t mix(uint64_t x) {
  // splitmix64 finaliser: decorrelates (seed, frame) pairs.
  x += 0x9e3779b97f4a7c15ull;
  x = (x ^ (x >> 30)) * 0xbf58476d1ce4e5b9ull;
  x = (x ^ (x >> 27)) * 0x94d049bb133111ebull;
  return x ^ (x >> 31);
}

// kWarp's tone curve: grey level = 255 (radiance / 255)^(1 / 1.6).
constexpr double kGamma = 1.6;
double linear_radiance(double grey) { return 255.0 * std::pow(std::clamp(grey, 0.0, 255.0) / 255.0, kGamma); }

}  // namespace

struct SyntheticCamera::Impl {
  CameraModel model;
  Board board;
  RenderOptions options;
  cv::Mat rays;                 // CV_32FC2 normalised rays per sample
  std::vector<cv::Mat> levels;  // CV_8UC2: (albedo, coverage) per mip level
  std::vector<double> metres_per_texel;
  double margin_m = 0;
  cv::Mat background;         // CV_32F, output resolution, grey levels
  cv::Mat background_linear;  // the same in radiance (kWarp's inverse tone curve)
  uint64_t frame = 0;
  // kWarp: extent of the rays in normalised coordinates and the ideal image's scale.
  double ray_x0 = 0, ray_y0 = 0, ray_x1 = 0, ray_y1 = 0, warp_scale = 0;
  // Scratch buffers reused between frames.
  cv::Mat map, sampled, pixels, ideal;

  // kWarp samples pixel centres, except for a ray model, which it ray-casts (set_rays).
  bool warps() const {
    return options.renderer == Renderer::kWarp && !is_ray_model(model.lens_model());
  }
  int samples_per_pixel() const { return warps() ? 1 : options.supersample; }
  void set_rays();
  int mip_level(const Eigen::Matrix3d& H, double sample_step) const;
  cv::Rect sheet_roi(const Pose& T_cam_board) const;
  Eigen::Matrix3d texel_from_board(int level) const;
  void sample_board(const cv::Rect& roi, const Eigen::Matrix3f& M, int level);
  bool warp_board(const cv::Rect& roi, const Eigen::Matrix3d& H, const Eigen::Matrix3d& Hinv);
  cv::Mat composite(uint64_t frame_index) const;
  cv::Mat composite_linear(uint64_t frame_index) const;

  void build_background() {
    cv::RNG rng(mix(options.seed ^ 0x5eedba5eull));
    const int w = model.width(), h = model.height();
    background = cv::Mat(h, w, CV_32F, cv::Scalar(options.background));
    background_linear = cv::Mat(h, w, CV_32F, cv::Scalar(linear_radiance(options.background)));
    if (options.background_texture <= 0) return;
    // Two octaves of smooth noise: looks like an out-of-focus room, never like a board corner.
    for (int cells : {6, 23}) {
      cv::Mat coarse(cells * h / std::max(w, h) + 2, cells * w / std::max(w, h) + 2, CV_32F);
      rng.fill(coarse, cv::RNG::UNIFORM, -1.0, 1.0);
      cv::Mat fine;
      cv::resize(coarse, fine, cv::Size(w, h), 0, 0, cv::INTER_CUBIC);
      background += fine * (options.background_texture * (cells == 6 ? 1.0 : 0.35));
    }
    background_linear.create(background.size(), CV_32F);
    for (int i = 0; i < h; ++i)
      for (int j = 0; j < w; ++j)
        background_linear.at<float>(i, j) = static_cast<float>(linear_radiance(background.at<float>(i, j)));
  }
};

namespace {

// The renderer's memory grows with the pixels and the ray samples: both are bounded.
void check_render_size(const CameraModel& truth, const RenderOptions& options) {
  const long long pixels = static_cast<long long>(truth.width()) * truth.height();
  const long long ss = options.renderer == Renderer::kWarp && !is_ray_model(truth.lens_model())
                           ? 1
                           : options.supersample;
  if (pixels > SyntheticCamera::kMaxPixels || pixels * ss * ss > SyntheticCamera::kMaxSamples) {
    throw Error(ErrorCode::kInvalidArgument,
                "synthetic camera: " + std::to_string(truth.width()) + "x" +
                    std::to_string(truth.height()) + " (supersample " + std::to_string(ss) +
                    ") is beyond the simulator's limit of " +
                    std::to_string(SyntheticCamera::kMaxPixels) + " pixels and " +
                    std::to_string(SyntheticCamera::kMaxSamples) + " ray samples");
  }
}

}  // namespace

SyntheticCamera::SyntheticCamera(const CameraModel& truth, const Board& board,
                                 const RenderOptions& options)
    : impl_(std::make_unique<Impl>()) {
  std::string why;
  if (!truth.is_valid(&why)) throw Error(ErrorCode::kInvalidArgument, "synthetic camera: " + why);
  options.validate();
  check_render_size(truth, options);
  impl_->model = truth;
  impl_->board = board;
  impl_->options = options;
  impl_->set_rays();
  const BoardTexture tex = board.render(kTexelsPerSquare, kMarginSquares);
  impl_->margin_m = tex.margin_m;
  cv::Mat level;
  cv::Mat alpha(tex.image.size(), CV_8U, cv::Scalar(255));
  cv::merge(std::vector<cv::Mat>{tex.image, alpha}, level);
  double mpt = tex.metres_per_texel;
  for (int l = 0; l < kMipLevels; ++l) {
    impl_->levels.push_back(level);
    impl_->metres_per_texel.push_back(mpt);
    // Box filter by exactly 2: texel i of the next level is centred on texels 2i, 2i+1.
    cv::Mat next;
    cv::resize(level, next, cv::Size(level.cols / 2, level.rows / 2), 0, 0, cv::INTER_AREA);
    level = next;
    mpt *= 2;
  }
  impl_->build_background();
}

SyntheticCamera::~SyntheticCamera() = default;
SyntheticCamera::SyntheticCamera(SyntheticCamera&&) noexcept = default;
SyntheticCamera& SyntheticCamera::operator=(SyntheticCamera&&) noexcept = default;

const CameraModel& SyntheticCamera::model() const { return impl_->model; }
const Board& SyntheticCamera::board() const { return impl_->board; }
const RenderOptions& SyntheticCamera::options() const { return impl_->options; }
uint64_t SyntheticCamera::frames_rendered() const { return impl_->frame; }

void SyntheticCamera::set_options(const RenderOptions& options) {
  options.validate();
  check_render_size(impl_->model, options);
  const bool new_rays = options.supersample != impl_->options.supersample ||
                        options.renderer != impl_->options.renderer;
  const bool new_bg = options.seed != impl_->options.seed ||
                      options.background != impl_->options.background ||
                      options.background_texture != impl_->options.background_texture;
  impl_->options = options;
  if (new_rays) impl_->set_rays();
  if (new_bg) impl_->build_background();
}

std::vector<cv::Point2d> SyntheticCamera::true_corners(const Pose& T_cam_board) const {
  return project_points(impl_->model, T_cam_board, impl_->board.corners());
}

// The rays of every sample; for kWarp (pixel centres) also their extent, which the ideal pinhole
// image must cover, and its scale: twice the focal length, at most 8192 samples a side.
void SyntheticCamera::Impl::set_rays() {
  // A ray model (the fisheye) sees beyond 90 degrees: unit rays, always ray-cast (the ideal
  // pinhole image of kWarp cannot hold such a view). Otherwise the rays of the plane Z = 1.
  if (is_ray_model(model.lens_model())) {
    rays = model.direction_map(samples_per_pixel());
    return;
  }
  rays = model.ray_map(samples_per_pixel());
  if (options.renderer != Renderer::kWarp) return;
  ray_x0 = ray_y0 = std::numeric_limits<double>::infinity();
  ray_x1 = ray_y1 = -ray_x0;
  for (int i = 0; i < rays.rows; ++i) {
    const auto* r = rays.ptr<cv::Vec2f>(i);
    for (int j = 0; j < rays.cols; ++j) {
      if (!std::isfinite(r[j][0]) || !std::isfinite(r[j][1])) continue;
      ray_x0 = std::min<double>(ray_x0, r[j][0]), ray_x1 = std::max<double>(ray_x1, r[j][0]);
      ray_y0 = std::min<double>(ray_y0, r[j][1]), ray_y1 = std::max<double>(ray_y1, r[j][1]);
    }
  }
  if (!(ray_x1 > ray_x0 && ray_y1 > ray_y0))
    throw Error(ErrorCode::kInvalidArgument, "synthetic camera: the lens model maps no pixel to a ray");
  const double extent = std::max(ray_x1 - ray_x0, ray_y1 - ray_y0);
  warp_scale = std::min(model.fx() + model.fy(), 8190.0 / extent);
}

// Mip level: smallest texel footprint of one sample over the board's outline and centre
// (sharpest detail needed anywhere on the board), ignoring the lens' local magnification. H maps
// the board plane to normalised image coordinates; sample_step is one sample in normalised units.
int SyntheticCamera::Impl::mip_level(const Eigen::Matrix3d& H, double sample_step) const {
  double min_footprint_m = std::numeric_limits<double>::infinity();
  const cv::Size2d bs = board.board_size_m();
  for (const auto& B :
       {cv::Point2d(0, 0), cv::Point2d(bs.width, 0), cv::Point2d(0, bs.height),
        cv::Point2d(bs.width, bs.height), cv::Point2d(bs.width / 2, bs.height / 2)}) {
    const Eigen::Vector3d q = H * Eigen::Vector3d(B.x, B.y, 1.0);
    if (!(q.z() > 1e-9)) continue;
    // d(normalised)/d(board) at B, then its inverse gives board metres per normalised unit.
    Eigen::Matrix2d J;
    J << (H(0, 0) * q.z() - q.x() * H(2, 0)), (H(0, 1) * q.z() - q.x() * H(2, 1)),
        (H(1, 0) * q.z() - q.y() * H(2, 0)), (H(1, 1) * q.z() - q.y() * H(2, 1));
    J /= q.z() * q.z();
    const Eigen::Matrix2d Jinv = J.inverse();
    if (!Jinv.allFinite()) continue;
    const double footprint = Jinv.operatorNorm() * sample_step;
    min_footprint_m = std::min(min_footprint_m, footprint);
  }
  int level = 0;
  if (std::isfinite(min_footprint_m)) {
    const double texels = min_footprint_m / metres_per_texel[0];
    level = std::clamp(static_cast<int>(std::floor(std::log2(std::max(texels, 1.0)))), 0,
                       kMipLevels - 1);
  }
  return level;
}

// Only the pixels the printed sheet (board plus white margin) can cover need sampling: its
// outline, projected densely through the true model, bounds them. If any outline point cannot be
// projected (behind the camera), the whole frame.
cv::Rect SyntheticCamera::Impl::sheet_roi(const Pose& T_cam_board) const {
  const cv::Size2d bs = board.board_size_m();
  cv::Rect roi(0, 0, model.width(), model.height());
  {
    const double m0 = margin_m;
    const std::vector<cv::Point3d> sheet = {{-m0, -m0, 0},
                                            {bs.width + m0, -m0, 0},
                                            {bs.width + m0, bs.height + m0, 0},
                                            {-m0, bs.height + m0, 0}};
    std::vector<cv::Point3d> edge;
    constexpr int kSteps = 32;
    for (int e = 0; e < 4; ++e)
      for (int k = 0; k < kSteps; ++k)
        edge.push_back(sheet[e] +
                       (sheet[(e + 1) % 4] - sheet[e]) * (static_cast<double>(k) / kSteps));
    const auto proj = project_points(model, T_cam_board, edge);
    double x0 = 1e18, y0 = 1e18, x1 = -1e18, y1 = -1e18;
    bool ok = true;
    for (const auto& p : proj) {
      if (!std::isfinite(p.x) || !std::isfinite(p.y) || std::abs(p.x) > 1e6 ||
          std::abs(p.y) > 1e6) {
        ok = false;
        break;
      }
      x0 = std::min(x0, p.x), y0 = std::min(y0, p.y), x1 = std::max(x1, p.x),
      y1 = std::max(y1, p.y);
    }
    if (ok) {
      const int ix0 = std::max(0, static_cast<int>(std::floor(x0)) - 2);
      const int iy0 = std::max(0, static_cast<int>(std::floor(y0)) - 2);
      const int ix1 = std::min(model.width(), static_cast<int>(std::ceil(x1)) + 3);
      const int iy1 = std::min(model.height(), static_cast<int>(std::ceil(y1)) + 3);
      roi = ix1 > ix0 && iy1 > iy0 ? cv::Rect(ix0, iy0, ix1 - ix0, iy1 - iy0) : cv::Rect();
    }
  }
  return roi;
}

// Samples the board texture at `level` through the per-sample rays over `roi` into pixels, as
// (premultiplied albedo, coverage); M maps normalised coordinates to texels.
// Board (X, Y) -> texel (u, v) at a mip level: u = (X + margin) / m - 0.5.
Eigen::Matrix3d SyntheticCamera::Impl::texel_from_board(int level) const {
  const double m = metres_per_texel[level];
  Eigen::Matrix3d A;
  A << 1 / m, 0, margin_m / m - 0.5, 0, 1 / m, margin_m / m - 0.5, 0, 0, 1;
  return A;
}

void SyntheticCamera::Impl::sample_board(const cv::Rect& roi, const Eigen::Matrix3f& M, int level) {
  const int n = samples_per_pixel();
  pixels.create(model.size(), CV_8UC2);
  pixels.setTo(cv::Scalar(0, 0));
  if (!roi.empty()) {
    const cv::Rect sroi(roi.x * n, roi.y * n, roi.width * n, roi.height * n);
    const int W = sroi.width, Hh = sroi.height;
    map.create(Hh, W, CV_32FC2);
    // Rays (x, y, 1) of the plane, or unit rays (x, y, z) of a ray model: M maps either
    // homogeneously, and w = M(2, .) ray is 1 / (distance along the ray to the board plane), so
    // w > 0 says the ray meets the plane in front of the camera, whatever z's sign.
    const int ch = rays.channels();
    for (int i = 0; i < Hh; ++i) {
      const float* ray = rays.ptr<float>(sroi.y + i) + ch * sroi.x;
      float* out = map.ptr<float>(i);
      for (int j = 0; j < W; ++j) {
        const float x = ray[ch * j], y = ray[ch * j + 1], z = ch == 3 ? ray[ch * j + 2] : 1.0f;
        const float w = M(2, 0) * x + M(2, 1) * y + M(2, 2) * z;
        // NaN rays fail the test.
        const bool front = w > 1e-9f;
        const float inv = front ? 1.0f / w : 0.0f;
        out[2 * j] = front ? (M(0, 0) * x + M(0, 1) * y + M(0, 2) * z) * inv : -1e6f;
        out[2 * j + 1] = front ? (M(1, 0) * x + M(1, 1) * y + M(1, 2) * z) * inv : -1e6f;
      }
    }
    cv::remap(levels[level], sampled, map, cv::noArray(), cv::INTER_LINEAR,
              cv::BORDER_CONSTANT, cv::Scalar(0, 0));
    cv::Mat dst = pixels(roi);
    if (n > 1) {
      cv::resize(sampled, dst, roi.size(), 0, 0, cv::INTER_AREA);
    } else {
      sampled.copyTo(dst);
    }
  }

}

// kWarp: the sheet's part of the ideal pinhole image (board -> normalised coordinates is the
// homography H, so the sheet is the quadrilateral of its projected corners), drawn through the
// homography from the mip level whose texels match its samples, filtered by the pixel's area,
// then resampled at the pixel centres of `roi` through the true lens. False if a sheet corner is behind the camera (the
// homography would fold the plane's far side in): the caller ray-casts that frame.
bool SyntheticCamera::Impl::warp_board(const cv::Rect& roi, const Eigen::Matrix3d& H, const Eigen::Matrix3d& Hinv) {
  if (rays.channels() != 2) return false;  // a ray model's unit rays: ray-cast
  pixels.create(model.size(), CV_8UC2);
  pixels.setTo(cv::Scalar(0, 0));
  const cv::Size2d bs = board.board_size_m();
  double x0 = 1e18, y0 = 1e18, x1 = -1e18, y1 = -1e18;
  for (const auto& B : {cv::Point2d(-margin_m, -margin_m), cv::Point2d(bs.width + margin_m, -margin_m),
                        cv::Point2d(-margin_m, bs.height + margin_m), cv::Point2d(bs.width + margin_m, bs.height + margin_m)}) {
    const Eigen::Vector3d q = H * Eigen::Vector3d(B.x, B.y, 1.0);
    if (!(q.z() > 1e-9)) return false;
    x0 = std::min(x0, q.x() / q.z()), x1 = std::max(x1, q.x() / q.z());
    y0 = std::min(y0, q.y() / q.z()), y1 = std::max(y1, q.y() / q.z());
  }
  if (roi.empty()) return true;
  // The ideal image's pixel (u, v) is normalised ((u + 0.5) / s + ray_x0, ...) over the rays'
  // extent; only the sheet's bounding box (clipped to it, plus a bicubic margin) is drawn.
  const double sc = warp_scale;
  const int W = static_cast<int>(std::ceil((ray_x1 - ray_x0) * sc)) + 1;
  const int Hh = static_cast<int>(std::ceil((ray_y1 - ray_y0) * sc)) + 1;
  const int u0 = std::clamp(static_cast<int>(std::floor((x0 - ray_x0) * sc)) - 3, 0, W);
  const int v0 = std::clamp(static_cast<int>(std::floor((y0 - ray_y0) * sc)) - 3, 0, Hh);
  const int u1 = std::clamp(static_cast<int>(std::ceil((x1 - ray_x0) * sc)) + 4, 0, W);
  const int v1 = std::clamp(static_cast<int>(std::ceil((y1 - ray_y0) * sc)) + 4, 0, Hh);
  if (u1 <= u0 || v1 <= v0) return true;
  Eigen::Matrix3d D;  // ideal-image pixel of the clipped box -> normalised coordinates
  D << 1 / sc, 0, (u0 + 0.5) / sc + ray_x0, 0, 1 / sc, (v0 + 0.5) / sc + ray_y0, 0, 0, 1;
  const int level = mip_level(H, 1.0 / sc);
  const Eigen::Matrix3d T = texel_from_board(level) * Hinv * D;
  cv::Mat Tm(3, 3, CV_64F);
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) Tm.at<double>(r, c) = T(r, c);
  cv::warpPerspective(levels[level], ideal, Tm, cv::Size(u1 - u0, v1 - v0), cv::INTER_LINEAR | cv::WARP_INVERSE_MAP,
                      cv::BORDER_CONSTANT, cv::Scalar(0, 0));
  // The pixel's area, integrated in the ideal image (where it is about 2 x 2 samples): a
  // [1/4 1/2 1/4] tent per axis, which ignores how the lens stretches the pixel locally.
  const cv::Mat tent = (cv::Mat_<float>(3, 1) << 0.25f, 0.5f, 0.25f);
  cv::sepFilter2D(ideal, ideal, -1, tent, tent, cv::Point(-1, -1), 0, cv::BORDER_CONSTANT);
  map.create(roi.size(), CV_32FC2);
  for (int i = 0; i < roi.height; ++i) {
    const float* ray = rays.ptr<float>(roi.y + i) + 2 * roi.x;
    float* out = map.ptr<float>(i);
    for (int j = 0; j < roi.width; ++j) {
      // NaN rays (no unprojection) fall outside the ideal image: nothing of the board there.
      const float x = ray[2 * j], y = ray[2 * j + 1];
      const bool ok = std::isfinite(x) && std::isfinite(y);
      out[2 * j] = ok ? static_cast<float>((x - ray_x0) * sc - 0.5 - u0) : -1e6f;
      out[2 * j + 1] = ok ? static_cast<float>((y - ray_y0) * sc - 0.5 - v0) : -1e6f;
    }
  }
  cv::Mat dst = pixels(roi);
  cv::remap(ideal, dst, map, cv::noArray(), cv::INTER_CUBIC, cv::BORDER_CONSTANT, cv::Scalar(0, 0));
  return true;
}

// kWarp's composite: in linear radiance (the grey levels of paper, ink and background through
// the inverse tone curve), a defocus disc, shot and read noise, then the tone curve; 8-bit.
cv::Mat SyntheticCamera::Impl::composite_linear(uint64_t frame_index) const {
  const RenderOptions& o = options;
  auto linear = linear_radiance;
  const float ink = static_cast<float>(linear(o.ink_black));
  const float span = static_cast<float>(linear(o.paper_white) - linear(o.ink_black));
  const float expo = static_cast<float>(o.exposure);
  cv::Mat img(model.size(), CV_32F);
  for (int i = 0; i < img.rows; ++i) {
    const uchar* px = pixels.ptr<uchar>(i);
    const float* bg = background_linear.ptr<float>(i);
    float* out = img.ptr<float>(i);
    for (int j = 0; j < img.cols; ++j) {
      const float ap = px[2 * j] * (1.0f / 255.0f), c = px[2 * j + 1] * (1.0f / 255.0f);
      out[j] = expo * (c * ink + span * ap + (1.0f - c) * bg[j]);
    }
  }
  if (o.blur_sigma_px > 0) {
    // A uniform disc of radius R has the second moment R^2 / 4 per axis: R = 2 sigma. Its rim is
    // antialiased by 8 x 8 subsamples per kernel tap.
    const double R = 2.0 * o.blur_sigma_px;
    const int r = static_cast<int>(std::ceil(R));
    cv::Mat k(2 * r + 1, 2 * r + 1, CV_32F, cv::Scalar(0));
    for (int y = -r; y <= r; ++y)
      for (int x = -r; x <= r; ++x) {
        int inside = 0;
        for (int a = 0; a < 8; ++a)
          for (int b = 0; b < 8; ++b) {
            const double dx = x - 0.5 + (a + 0.5) / 8, dy = y - 0.5 + (b + 0.5) / 8;
            inside += dx * dx + dy * dy <= R * R;
          }
        k.at<float>(y + r, x + r) = static_cast<float>(inside);
      }
    k /= cv::sum(k)[0];
    cv::filter2D(img, img, -1, k, cv::Point(-1, -1), 0, cv::BORDER_REFLECT);
  }
  // Noise variance a + b * radiance, noise_sigma grey levels at mid grey after the tone curve
  // (half read noise, half shot noise there); the tone curve makes it about twice that at the
  // ink's grey and a little less at the paper's.
  const double mid = linear(128.0);
  const double slope = 128.0 / (kGamma * mid);  // d grey / d radiance at mid grey
  const double var_mid = std::pow(o.noise_sigma / slope, 2);
  cv::RNG rng(mix(o.seed * 0x100000001b3ull + frame_index));
  cv::Mat noise;
  if (o.noise_sigma > 0) {
    noise.create(img.size(), CV_32F);
    rng.fill(noise, cv::RNG::NORMAL, 0.0, 1.0);
  }
  // The tone curve, tabulated finely enough (1/16 radiance level) that no grey level moves.
  constexpr int kSteps = 16 * 255;
  std::vector<float> tone(kSteps + 2);
  for (int k = 0; k <= kSteps + 1; ++k) tone[k] = static_cast<float>(255.0 * std::pow(std::min(1.0, double(k) / kSteps), 1.0 / kGamma));
  cv::Mat out8(img.size(), CV_8U);
  for (int i = 0; i < img.rows; ++i) {
    const float* lin = img.ptr<float>(i);
    const float* nz = noise.empty() ? nullptr : noise.ptr<float>(i);
    uchar* out = out8.ptr<uchar>(i);
    for (int j = 0; j < img.cols; ++j) {
      double v = lin[j];
      if (nz) v += nz[j] * std::sqrt(var_mid * (0.5 + 0.5 * std::max(0.0, v) / mid));
      const double t = std::clamp(v, 0.0, 255.0) * (kSteps / 255.0);
      const int k = static_cast<int>(t);
      out[j] = cv::saturate_cast<uchar>(tone[k] + (tone[k + 1] - tone[k]) * (t - k));
    }
  }
  return out8;
}

// Composite: the sampled board over the background, then blur, exposure and noise; 8-bit.
cv::Mat SyntheticCamera::Impl::composite(uint64_t frame_index) const {
  const RenderOptions& o = options;
  // Premultiplied albedo a_p and coverage c (both 0..255) over the background.
  cv::Mat img(model.size(), CV_32F);
  const float ink = static_cast<float>(o.ink_black),
              span = static_cast<float>(o.paper_white - o.ink_black);
  const float expo = static_cast<float>(o.exposure);
  for (int i = 0; i < img.rows; ++i) {
    const uchar* px = pixels.ptr<uchar>(i);
    const float* bg = background.ptr<float>(i);
    float* out = img.ptr<float>(i);
    for (int j = 0; j < img.cols; ++j) {
      const float ap = px[2 * j] * (1.0f / 255.0f), c = px[2 * j + 1] * (1.0f / 255.0f);
      out[j] = expo * (c * ink + span * ap + (1.0f - c) * bg[j]);
    }
  }
  if (o.blur_sigma_px > 0) cv::GaussianBlur(img, img, cv::Size(0, 0), o.blur_sigma_px);
  if (o.noise_sigma > 0) {
    cv::RNG rng(mix(o.seed * 0x100000001b3ull + frame_index));
    cv::Mat noise(img.size(), CV_32F);
    rng.fill(noise, cv::RNG::NORMAL, 0.0, o.noise_sigma);
    img += noise;
  }
  cv::Mat out8;
  img.convertTo(out8, CV_8U);  // rounds and saturates
  return out8;
}

cv::Mat SyntheticCamera::render(const Pose& T_cam_board) {
  Impl& s = *impl_;
  if (!T_cam_board.is_finite())
    throw Error(ErrorCode::kInvalidArgument, "render: pose is not finite");
  const uint64_t frame_index = s.frame++;

  // Homography from the board plane (X, Y, 1) to normalised image coordinates: [r1 r2 t].
  const Eigen::Matrix3d R = T_cam_board.R();
  Eigen::Matrix3d H;
  H.col(0) = R.col(0);
  H.col(1) = R.col(1);
  H.col(2) = T_cam_board.t;
  Eigen::Matrix3d Hinv = H.inverse();
  if (!Hinv.allFinite()) {
    // Board plane seen edge-on through the centre of projection: nothing of it is visible.
    Hinv.setZero();
  }
  const cv::Rect roi = s.sheet_roi(T_cam_board);
  if (s.options.renderer == Renderer::kWarp && s.warp_board(roi, H, Hinv)) return s.composite_linear(frame_index);
  // Ray casting (and kWarp's fallback when the sheet reaches behind the camera, with its one
  // ray per pixel).
  const int n = s.samples_per_pixel();
  const int level = s.mip_level(H, 1.0 / (n * 0.5 * (s.model.fx() + s.model.fy())));
  const Eigen::Matrix3f M = (s.texel_from_board(level) * Hinv).cast<float>();
  s.sample_board(roi, M, level);
  return s.options.renderer == Renderer::kWarp ? s.composite_linear(frame_index) : s.composite(frame_index);
}

}  // namespace posecal
