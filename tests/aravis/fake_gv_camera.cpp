#include "fake_gv_camera.hpp"

#include <cstring>

#include "board/views.hpp"

namespace posecal::testing {

std::shared_ptr<const FakeScene> make_scene(uint64_t seed, int n_views, uint32_t tag) {
  auto scene = std::make_shared<FakeScene>();
  scene->tag = tag;
  RenderOptions ro;
  ro.seed = seed;
  ro.noise_sigma = 1.0;
  SyntheticCamera camera(scene->model, scene->board, ro);
  ViewSampling vs;
  vs.max_tilt_deg = 35;
  vs.min_width_fraction = 0.4;
  vs.max_width_fraction = 0.7;
  for (const Pose& pose : random_board_views(seed, n_views, scene->model, scene->board, vs)) {
    scene->views.push_back(camera.render(pose));
  }
  return scene;
}

std::vector<uint8_t> raw_from_grey(const cv::Mat& grey, PixelFormat format) {
  CV_Assert(grey.type() == CV_8UC1 && grey.isContinuous());
  const size_t n = grey.total();
  const uint8_t* g = grey.ptr<uint8_t>();
  std::vector<uint8_t> raw;
  switch (format) {
    case PixelFormat::kMono8:
    case PixelFormat::kBayerRG8:
    case PixelFormat::kBayerGR8:
    case PixelFormat::kBayerGB8:
    case PixelFormat::kBayerBG8:
      raw.assign(g, g + n);
      break;
    case PixelFormat::kMono16:
      raw.resize(2 * n);
      for (size_t i = 0; i < n; ++i) {  // little endian, as GVSP sends it
        raw[2 * i] = 0x5a;
        raw[2 * i + 1] = g[i];
      }
      break;
    case PixelFormat::kRGB8:
      raw.resize(3 * n);
      for (size_t i = 0; i < n; ++i) {
        raw[3 * i] = g[i];
        raw[3 * i + 1] = g[i];
        raw[3 * i + 2] = static_cast<uint8_t>(255 - g[i]);
      }
      break;
    default:
      CV_Error(cv::Error::StsBadArg, "raw_from_grey: format not simulated");
  }
  return raw;
}

FakeGvCamera::FakeGvCamera(std::string serial, std::string address,
                           std::shared_ptr<const FakeScene> scene)
    : serial_(std::move(serial)), address_(std::move(address)), scene_(std::move(scene)) {}

FakeGvCamera::FakeGvCamera(std::string serial, std::string address, PayloadSource source)
    : serial_(std::move(serial)), address_(std::move(address)), source_(std::move(source)) {}

FakeGvCamera::~FakeGvCamera() { stop(); }

bool FakeGvCamera::start() {
  if (gv_ != nullptr) return true;
  // The GigE Vision bootstrap register holds 16 bytes including the NUL. Aravis refuses longer
  // serial numbers with a critical warning but still runs a simulator without a camera behind it.
  if (serial_.size() >= 16) return false;
  gv_ = arv_gv_fake_camera_new(address_.c_str(), serial_.c_str());
  if (gv_ == nullptr || !arv_gv_fake_camera_is_running(gv_)) {
    stop();
    return false;
  }
  g_object_set(gv_, "gvsp-lost-ratio", lost_ratio_, nullptr);
  arv_fake_camera_set_fill_pattern(arv_gv_fake_camera_get_fake_camera(gv_), &FakeGvCamera::fill,
                                   this);
  return true;
}

void FakeGvCamera::stop() {
  if (gv_ != nullptr) g_object_unref(gv_);  // joins the simulator thread, closes its sockets
  gv_ = nullptr;
}

void FakeGvCamera::set_lost_packet_ratio(double ratio) {
  lost_ratio_ = ratio;
  if (gv_ != nullptr) g_object_set(gv_, "gvsp-lost-ratio", ratio, nullptr);
}

cv::Mat FakeGvCamera::expected_grey(uint64_t frame_id, const cv::Rect& roi) const {
  const cv::Mat& view = scene_->views[frame_id % scene_->views.size()];
  cv::Mat out(roi.size(), CV_8UC1, cv::Scalar(0));
  const cv::Rect inside = roi & cv::Rect(0, 0, view.cols, view.rows);
  if (inside.area() > 0) view(inside).copyTo(out(inside - roi.tl()));
  // Stamp: tag and frame id (little endian) in the first pixels of the first row.
  uint8_t stamp[8];
  std::memcpy(stamp, &scene_->tag, 4);
  const uint32_t id = static_cast<uint32_t>(frame_id);
  std::memcpy(stamp + 4, &id, 4);
  for (int i = 0; i < 8 && i < out.cols; ++i) out.at<uint8_t>(0, i) = stamp[i];
  return out;
}

std::vector<uint8_t> FakeGvCamera::expected_raw(uint64_t frame_id, PixelFormat format,
                                                const cv::Rect& roi) const {
  return raw_from_grey(expected_grey(frame_id, roi), format);
}

cv::Mat FakeGvCamera::expected_engine(uint64_t frame_id, PixelFormat format,
                                      const cv::Rect& roi) const {
  std::vector<uint8_t> raw = expected_raw(frame_id, format, roi);
  return convert_to_engine(format, raw.data(), raw.size(), roi.width, roi.height, 0).clone();
}

void FakeGvCamera::fill(ArvBuffer* buffer, void* self_ptr, guint32 /*exposure_us*/,
                        guint32 /*gain*/, ArvPixelFormat arv_format) {
  // Runs on the simulator's thread, under its fill-pattern lock.
  auto* self = static_cast<FakeGvCamera*>(self_ptr);
  PixelFormat format = PixelFormat::kUnknown;
  switch (arv_format) {
    case ARV_PIXEL_FORMAT_MONO_8:
      format = PixelFormat::kMono8;
      break;
    case ARV_PIXEL_FORMAT_MONO_16:
      format = PixelFormat::kMono16;
      break;
    case ARV_PIXEL_FORMAT_RGB_8_PACKED:
      format = PixelFormat::kRGB8;
      break;
    case ARV_PIXEL_FORMAT_BAYER_RG_8:
      format = PixelFormat::kBayerRG8;
      break;
    case ARV_PIXEL_FORMAT_BAYER_GR_8:
      format = PixelFormat::kBayerGR8;
      break;
    case ARV_PIXEL_FORMAT_BAYER_GB_8:
      format = PixelFormat::kBayerGB8;
      break;
    case ARV_PIXEL_FORMAT_BAYER_BG_8:
      format = PixelFormat::kBayerBG8;
      break;
    default:
      return;
  }
  const cv::Rect roi(arv_buffer_get_image_x(buffer), arv_buffer_get_image_y(buffer),
                     arv_buffer_get_image_width(buffer), arv_buffer_get_image_height(buffer));
  const uint64_t id = arv_buffer_get_frame_id(buffer);
  // The simulator allocated the payload size (checked before it calls us); Aravis' getter reports
  // 0 bytes here because nothing was "received" yet.
  size_t ignored = 0;
  auto* data = static_cast<uint8_t*>(const_cast<void*>(arv_buffer_get_data(buffer, &ignored)));
  if (self->source_) {
    const auto raw = self->source_(id, format, roi);
    const size_t bytes =
        static_cast<size_t>(roi.area()) * ARV_PIXEL_FORMAT_BIT_PER_PIXEL(arv_format) / 8;
    if (!raw || raw->size() != bytes) {
      self->rejects_->fetch_add(1);
      return;
    }
    std::memcpy(data, raw->data(), raw->size());
  } else {
    const std::vector<uint8_t> raw = self->expected_raw(id, format, roi);
    std::memcpy(data, raw.data(), raw.size());
  }
  self->last_id_->store(id);
  self->filled_->fetch_add(1);
}

}  // namespace posecal::testing
