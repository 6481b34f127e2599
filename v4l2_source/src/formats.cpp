// V4l2Camera: formats, frame sizes and frame intervals (ENUM_FMT, ENUM_FRAMESIZES,
// ENUM_FRAMEINTERVALS, TRY_FMT, G_FMT, G_PARM).
#include <fcntl.h>
#include <sys/mman.h>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>
#include <numeric>
#include <optional>

#include "camera_internal.hpp"

namespace posecal::v4l2 {

void V4l2CameraImpl::enumerate_formats() {
  formats_.clear();
  for (uint32_t i = 0; i < kMaxEnumerations; ++i) {
    v4l2_fmtdesc d{};
    d.index = i;
    d.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    if (const int err = ioctl(VIDIOC_ENUM_FMT, &d)) {
      if (err == EINVAL) break;
      fail("VIDIOC_ENUM_FMT", err);
    }
    V4l2Format f;
    f.fourcc = d.pixelformat;
    f.fourcc_text = fourcc_text(d.pixelformat);
    f.description = fixed_string(d.description, sizeof(d.description));
    f.pixel_format = pixel_format_of_fourcc(d.pixelformat);
    f.compressed = (d.flags & V4L2_FMT_FLAG_COMPRESSED) != 0;
    for (uint32_t j = 0; j < kMaxEnumerations; ++j) {
      v4l2_frmsizeenum s{};
      s.index = j;
      s.pixel_format = f.fourcc;
      if (const int err = ioctl(VIDIOC_ENUM_FRAMESIZES, &s)) {
        if (err == EINVAL || err == ENOTTY) break;
        fail("VIDIOC_ENUM_FRAMESIZES", err);
      }
      if (s.type == V4L2_FRMSIZE_TYPE_DISCRETE) {
        V4l2FrameSize size;
        size.width = static_cast<int>(s.discrete.width);
        size.height = static_cast<int>(s.discrete.height);
        frame_intervals(f.fourcc, size.width, size.height, &size);
        f.sizes.push_back(size);
        continue;
      }
      // Stepwise or continuous: one entry describes every size.
      f.stepwise = true;
      f.min_width = static_cast<int>(s.stepwise.min_width);
      f.max_width = static_cast<int>(s.stepwise.max_width);
      f.min_height = static_cast<int>(s.stepwise.min_height);
      f.max_height = static_cast<int>(s.stepwise.max_height);
      const bool continuous = s.type == V4L2_FRMSIZE_TYPE_CONTINUOUS;
      f.step_width = continuous ? 1 : std::max(1, static_cast<int>(s.stepwise.step_width));
      f.step_height = continuous ? 1 : std::max(1, static_cast<int>(s.stepwise.step_height));
      for (const auto& [w, h] :
           {std::pair{f.min_width, f.min_height}, {f.max_width, f.max_height}}) {
        V4l2FrameSize size;
        size.width = w;
        size.height = h;
        frame_intervals(f.fourcc, w, h, &size);
        f.sizes.push_back(size);
      }
      break;
    }
    formats_.push_back(std::move(f));
  }
}

void V4l2CameraImpl::frame_intervals(uint32_t fourcc, int width, int height, V4l2FrameSize* size) {
  size->intervals.clear();
  size->min_rate_hz = size->max_rate_hz = 0;
  for (uint32_t k = 0; k < kMaxEnumerations; ++k) {
    v4l2_frmivalenum e{};
    e.index = k;
    e.pixel_format = fourcc;
    e.width = static_cast<uint32_t>(width);
    e.height = static_cast<uint32_t>(height);
    if (const int err = ioctl(VIDIOC_ENUM_FRAMEINTERVALS, &e)) {
      if (err == EINVAL || err == ENOTTY) break;
      fail("VIDIOC_ENUM_FRAMEINTERVALS", err);
    }
    if (e.type == V4L2_FRMIVAL_TYPE_DISCRETE) {
      if (e.discrete.numerator && e.discrete.denominator) {
        size->intervals.push_back({e.discrete.numerator, e.discrete.denominator});
      }
      continue;
    }
    const auto rate = [](const v4l2_fract& f) {
      return f.numerator ? static_cast<double>(f.denominator) / f.numerator : 0.0;
    };
    size->min_rate_hz = rate(e.stepwise.max);
    size->max_rate_hz = rate(e.stepwise.min);
    break;
  }
  std::sort(size->intervals.begin(), size->intervals.end(),
            [](const auto& a, const auto& b) { return a.rate_hz() > b.rate_hz(); });
}

v4l2_pix_format V4l2CameraImpl::read_format() {
  v4l2_format f{};
  f.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
  if (const int err = ioctl(VIDIOC_G_FMT, &f)) fail("VIDIOC_G_FMT", err);
  return f.fmt.pix;
}

double V4l2CameraImpl::read_frame_rate(bool* settable) {
  v4l2_streamparm p{};
  p.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
  *settable = false;
  if (const int err = ioctl(VIDIOC_G_PARM, &p)) {
    if (err == ENOTTY || err == EINVAL) return 0;
    fail("VIDIOC_G_PARM", err);
  }
  *settable = (p.parm.capture.capability & V4L2_CAP_TIMEPERFRAME) != 0;
  const v4l2_fract& t = p.parm.capture.timeperframe;
  return t.numerator ? static_cast<double>(t.denominator) / t.numerator : 0;
}

const V4l2Format* V4l2CameraImpl::find_format(uint32_t fourcc) const {
  for (const auto& f : formats_) {
    if (f.fourcc == fourcc) return &f;
  }
  return nullptr;
}

uint32_t V4l2CameraImpl::fourcc_for(PixelFormat pf) const {
  std::vector<uint32_t> candidates;
  switch (pf) {
    case PixelFormat::kMJPEG:
      candidates = {V4L2_PIX_FMT_MJPEG, V4L2_PIX_FMT_JPEG};
      break;
    case PixelFormat::kYUYV:
      candidates = {V4L2_PIX_FMT_YUYV};
      break;
    case PixelFormat::kMono8:
      candidates = {V4L2_PIX_FMT_GREY};
      break;
    default:
      break;
  }
  for (uint32_t c : candidates) {
    if (find_format(c)) return c;
  }
  std::string offered;
  for (const auto& f : formats_) {
    if (f.pixel_format != PixelFormat::kUnknown) {
      offered += (offered.empty() ? "" : ", ") + std::string(pixel_format_name(f.pixel_format));
    }
  }
  throw Error(ErrorCode::kUnsupported,
              who() + ": pixel format " + pixel_format_name(pf) +
                  " is not supported (supported: " + (offered.empty() ? "none" : offered) + ")");
}

v4l2_pix_format V4l2CameraImpl::try_format(uint32_t fourcc, int width, int height) {
  v4l2_format f{};
  f.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
  f.fmt.pix.pixelformat = fourcc;
  f.fmt.pix.width = static_cast<uint32_t>(std::max(width, 0));
  f.fmt.pix.height = static_cast<uint32_t>(std::max(height, 0));
  f.fmt.pix.field = V4L2_FIELD_ANY;
  const int err = ioctl(VIDIOC_TRY_FMT, &f);
  if (err == 0) return f.fmt.pix;
  if (err != ENOTTY) fail("VIDIOC_TRY_FMT", err);
  // No TRY_FMT (optional before Linux 5.x for some drivers): pick the nearest listed size with
  // uvcvideo's rule, the smallest difference in covered area.
  const V4l2Format* fmt = find_format(fourcc);
  v4l2_pix_format out{};
  out.pixelformat = fourcc;
  out.width = f.fmt.pix.width;
  out.height = f.fmt.pix.height;
  if (fmt && fmt->stepwise) {
    const auto snap = [](int v, int lo, int hi, int step) {
      v = std::clamp(v, lo, hi);
      return std::min(lo + (v - lo + step / 2) / step * step, hi);
    };
    out.width = static_cast<uint32_t>(snap(width, fmt->min_width, fmt->max_width, fmt->step_width));
    out.height =
        static_cast<uint32_t>(snap(height, fmt->min_height, fmt->max_height, fmt->step_height));
  } else if (fmt && !fmt->sizes.empty()) {
    int64_t best = std::numeric_limits<int64_t>::max();
    for (const auto& s : fmt->sizes) {
      const int64_t covered = int64_t{std::min(width, s.width)} * std::min(height, s.height);
      const int64_t d = int64_t{width} * height + int64_t{s.width} * s.height - 2 * covered;
      if (d < best) {
        best = d;
        out.width = static_cast<uint32_t>(s.width);
        out.height = static_cast<uint32_t>(s.height);
      }
    }
  }
  return out;
}

std::optional<V4l2FrameSize::Interval> V4l2CameraImpl::nearest_interval(uint32_t fourcc, int width,
                                                                        int height,
                                                                        double rate_hz) {
  V4l2FrameSize size;
  frame_intervals(fourcc, width, height, &size);
  if (!size.intervals.empty()) {
    const auto best = std::min_element(
        size.intervals.begin(), size.intervals.end(), [&](const auto& a, const auto& b) {
          return std::abs(a.rate_hz() - rate_hz) < std::abs(b.rate_hz() - rate_hz);
        });
    return *best;
  }
  double r = rate_hz;
  if (size.max_rate_hz > 0) r = std::clamp(r, size.min_rate_hz, size.max_rate_hz);
  if (!(r > 0)) return std::nullopt;
  // Interval in 1/1000 s steps is finer than any UVC descriptor (100 ns units, but rates are
  // whole or NTSC fractions); reduce the fraction.
  uint32_t num = 1000, den = static_cast<uint32_t>(std::lround(r * 1000));
  const uint32_t g = std::gcd(num, den);
  return V4l2FrameSize::Interval{num / g, den / g};
}

}  // namespace posecal::v4l2
