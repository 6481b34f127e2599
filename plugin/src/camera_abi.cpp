// Camera utilities behind the C ABI: feature listing, grabbing frames to PNG files, and the
// test-set evaluation of an existing calibration file.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <memory>
#include <opencv2/imgcodecs.hpp>

#include "abi_common.hpp"
#include "common/atomic_file.hpp"
#include "context.hpp"
#include "evaluation.hpp"
#include "io/model_file.hpp"
#include "json_report.hpp"
#include "posecal.h"
#include "sim/sim_camera.hpp"

using namespace posecal;
using posecal::abi::guarded;
using posecal::abi::require;
using Json = nlohmann::json;
using Clock = std::chrono::steady_clock;

namespace {

const char* kEvalOptions = "evaluate options";

// Feature values as JSON: numbers and booleans typed where the text parses, else the text.
Json typed_value(const FeatureInfo& f) {
  if (!f.readable) return nullptr;
  if (f.type == FeatureType::kInteger || f.type == FeatureType::kFloat) {
    try {
      size_t used = 0;
      if (f.type == FeatureType::kInteger) {
        const long long v = std::stoll(f.value, &used);
        if (used == f.value.size()) return v;
      } else {
        const double v = std::stod(f.value, &used);
        if (used == f.value.size()) return abi::number(v);
      }
    } catch (const std::exception&) {
      // Not a number (e.g. "" for an unavailable value): report the text as it is.
    }
  }
  if (f.type == FeatureType::kBoolean) {
    if (f.value == "true" || f.value == "1") return true;
    if (f.value == "false" || f.value == "0") return false;
  }
  return f.value;
}

Json typed_bound(const FeatureInfo& f, const std::string& text) {
  if (text.empty()) return nullptr;
  try {
    size_t used = 0;
    if (f.type == FeatureType::kInteger) {
      const long long v = std::stoll(text, &used);
      if (used == text.size()) return v;
    }
    used = 0;
    const double v = std::stod(text, &used);
    if (used == text.size()) return abi::number(v);
  } catch (const std::exception&) {
    // Not a number: reported as the text.
  }
  return text;
}

Json feature_json(const FeatureInfo& f) {
  Json j;
  j["name"] = f.name;
  j["type"] = feature_type_name(f.type);
  j["value"] = typed_value(f);
  j["access"] = f.readable && f.writable ? "read-write"
                : f.readable             ? "read-only"
                : f.writable             ? "write-only"
                                         : "none";
  j["unit"] = f.unit.empty() ? Json(nullptr) : Json(f.unit);
  if (f.min.empty() && f.max.empty()) {
    j["range"] = nullptr;
  } else {
    j["range"] = {{"min", typed_bound(f, f.min)}, {"max", typed_bound(f, f.max)}};
  }
  j["options"] = f.options.empty() ? Json(nullptr) : Json(f.options);
  return j;
}

void check_timeout(int timeout_ms, const char* name) {
  if (timeout_ms < 1 || timeout_ms > 600000) {
    throw Error(ErrorCode::kInvalidArgument,
                std::string(name) + " must be in [1, 600000], got " + std::to_string(timeout_ms));
  }
}

std::string args_key(std::initializer_list<std::string> parts) {
  std::string key;
  for (const auto& p : parts) key += p + '\x1f';
  return key;
}

// A camera streaming for the duration of a call: stopped however the call ends.
struct Streaming {
  std::unique_ptr<Camera> camera;
  explicit Streaming(std::unique_ptr<Camera> c) : camera(std::move(c)) { camera->start(); }
  ~Streaming() {
    try {
      camera->stop();
    } catch (...) {
      // A camera that cannot stop is gone already; the destructor must not throw.
    }
  }
};

int remaining_ms(Clock::time_point deadline) {
  const auto left =
      std::chrono::duration_cast<std::chrono::milliseconds>(deadline - Clock::now()).count();
  return left > 0 ? static_cast<int>(left) : 0;
}

// Writes frame_NNNNN.png into out_dir; its entry of the grab's "files".
Json save_png(const Frame& frame, const std::string& out_dir, int index) {
  namespace fs = std::filesystem;
  char name[32];
  std::snprintf(name, sizeof name, "frame_%05d.png", index);
  const std::string path = (fs::path(out_dir) / name).string();
  std::vector<uchar> png;
  bool ok = false;
  try {
    ok = cv::imencode(".png", frame.image, png);
  } catch (const cv::Exception& e) {
    throw Error(ErrorCode::kIo, "cannot encode '" + path + "': " + e.what());
  }
  if (!ok) throw Error(ErrorCode::kIo, "cannot encode '" + path + "' as PNG");
  std::string error;
  if (!write_file_atomic(path, {reinterpret_cast<const char*>(png.data()), png.size()}, &error)) {
    throw Error(ErrorCode::kIo, error);
  }
  return {{"file", path},
                   {"frame_id", frame.frame_id},
                   {"timestamp_ns", frame.timestamp_ns},
                   {"width", frame.image.cols},
                   {"height", frame.image.rows},
                   {"channels", frame.image.channels()},
                   {"source_format", pixel_format_name(frame.source_format)}};
}

// Saves `count` frames of a streaming camera as PNG files before `deadline`; the grab's "files".
// Throws Error naming how many were saved when the camera times out, vanishes or ends.
Json save_frames(Camera& camera, const char* camera_uri, int count, const char* out_dir,
                 Clock::time_point deadline, int timeout_ms) {
  Json files = Json::array();
  int saved = 0;
  while (saved < count) {
    Frame frame;
    const FrameStatus st = camera.next_frame(remaining_ms(deadline), &frame);
    const std::string so_far = " (" + std::to_string(saved) + " of " + std::to_string(count) +
                               " frames saved in '" + out_dir + "')";
    if (st == FrameStatus::kTimeout) {
      throw Error(ErrorCode::kTimeout, "no frame from '" + std::string(camera_uri) + "' within " +
                                           std::to_string(timeout_ms) + " ms" + so_far);
    }
    if (st == FrameStatus::kDisconnected) {
      throw Error(ErrorCode::kDevice,
                  "camera '" + std::string(camera_uri) + "' disconnected" + so_far);
    }
    if (st == FrameStatus::kEndOfStream) {
      throw Error(ErrorCode::kNotFound,
                  "camera '" + std::string(camera_uri) + "' has no more frames" + so_far);
    }
    if (frame.image.empty()) {  // a corrupt frame the backend could not decode
      if (remaining_ms(deadline) == 0) {
        throw Error(ErrorCode::kTimeout, "no usable frame from '" + std::string(camera_uri) +
                                             "' within " + std::to_string(timeout_ms) + " ms" +
                                             so_far);
      }
      continue;
    }
    files.push_back(save_png(frame, out_dir, saved));
    ++saved;
    if (saved < count && remaining_ms(deadline) == 0) {
      throw Error(ErrorCode::kTimeout,
                  "the grab did not finish within " + std::to_string(timeout_ms) + " ms (" +
                      std::to_string(saved) + " of " + std::to_string(count) +
                      " frames saved in '" + out_dir + "')");
    }
  }
  return files;
}

struct CameraTestSet {
  std::vector<Observation> frames;
  int seen = 0;  // frames read
};

// The first `want` frames of a streaming camera that show at least min_corners corners of the
// board, read until `deadline`. check_size(size, what) refuses a frame of the wrong size. Throws
// Error naming the camera when it vanishes, or when no frame shows the board.
template <class CheckSize>
CameraTestSet camera_test_set(Camera& camera, const char* camera_uri, const BoardSpec& spec, int want,
                              int min_corners, Clock::time_point deadline, int timeout_ms,
                              const CheckSize& check_size) {
  CameraTestSet out;
  std::vector<Observation>& test_set = out.frames;
  const Board board(spec);
  int seen = 0;
  bool ended = false;
  while (static_cast<int>(test_set.size()) < want && remaining_ms(deadline) > 0) {
    Frame frame;
    const FrameStatus st = camera.next_frame(remaining_ms(deadline), &frame);
    if (st == FrameStatus::kTimeout) break;
    if (st == FrameStatus::kDisconnected) {
      throw Error(ErrorCode::kDevice, "camera '" + std::string(camera_uri) +
                                          "' disconnected after " +
                                          std::to_string(test_set.size()) + " test frames");
    }
    if (st == FrameStatus::kEndOfStream) {
      ended = true;
      break;
    }
    if (frame.image.empty()) continue;
    ++seen;
    check_size(frame.image.size(), "the camera delivers");
    const Detection d = board.detect(frame.image);
    if (static_cast<int>(d.size()) >= min_corners) test_set.push_back(Observation::from(d));
  }
  if (test_set.empty()) {
    if (ended) {
      throw Error(ErrorCode::kDegenerate, "none of the " + std::to_string(seen) +
                                              " frames of '" + std::string(camera_uri) +
                                              "' shows " + std::to_string(min_corners) +
                                              " corners of " + spec.to_string());
    }
    throw Error(ErrorCode::kTimeout, "no frame showing the board (" + spec.to_string() +
                                         ") from '" + std::string(camera_uri) + "' within " +
                                         std::to_string(timeout_ms) + " ms (" +
                                         std::to_string(seen) + " frames seen)");
  }
  out.seen = seen;
  return out;
}

}  // namespace

extern "C" {

POSECAL_API posecal_status posecal_camera_features(posecal_context* ctx, const char* camera_uri,
                                                   char* buf, size_t* size) noexcept {
  return guarded(__func__, [&] {
    require(ctx, "ctx");
    require(camera_uri, "camera_uri");
    require(size, "size");
    const std::string key = args_key({camera_uri});
    std::string text;
    if (!ctx->impl->take_pending(__func__, key, &text)) {
      const std::unique_ptr<Camera> camera = ctx->impl->open(camera_uri, BoardSpec{});
      Json arr = Json::array();
      for (const FeatureInfo& f : camera->features()) arr.push_back(feature_json(f));
      text = abi::to_text(arr);
    }
    return abi::copy_out_kept(*ctx->impl, __func__, key, text, buf, size);
  });
}

POSECAL_API posecal_status posecal_camera_grab(posecal_context* ctx, const char* camera_uri,
                                               int count, const char* out_dir, int timeout_ms,
                                               char* buf, size_t* size) noexcept {
  return guarded(__func__, [&] {
    require(ctx, "ctx");
    require(camera_uri, "camera_uri");
    require(out_dir, "out_dir");
    require(size, "size");
    if (count < 1 || count > 100000) {
      throw Error(ErrorCode::kInvalidArgument,
                  "count must be in [1, 100000], got " + std::to_string(count));
    }
    check_timeout(timeout_ms, "timeout_ms");
    const std::string key =
        args_key({camera_uri, std::to_string(count), out_dir, std::to_string(timeout_ms)});
    std::string text;
    if (ctx->impl->take_pending(__func__, key, &text))
      return abi::copy_out_kept(*ctx->impl, __func__, key, text, buf, size);

    namespace fs = std::filesystem;
    std::error_code ec;
    fs::create_directories(out_dir, ec);
    if (ec || !fs::is_directory(out_dir)) {
      throw Error(ErrorCode::kIo, std::string("cannot create directory '") + out_dir + "'" +
                                      (ec ? ": " + ec.message() : std::string()));
    }
    Streaming s(ctx->impl->open(camera_uri, BoardSpec{}));
    const auto t0 = Clock::now();
    const Json files = save_frames(*s.camera, camera_uri, count, out_dir, t0 + std::chrono::milliseconds(timeout_ms), timeout_ms);
    Json j;
    j["camera"] = abi::device_json(s.camera->info());
    j["out_dir"] = out_dir;
    j["files"] = files;
    const CameraStats stats = s.camera->stats();
    j["frames_dropped"] = stats.frames_dropped;
    j["frames_incomplete"] = stats.frames_incomplete;
    j["wall_ms"] = std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
    return abi::copy_out_kept(*ctx->impl, __func__, key, abi::to_text(j), buf, size);
  });
}

namespace {

// A model whose image reaches (almost) 90 degrees off its axis (e.g. fx 1e-9) maps every board
// to a dot: PnP then "fits" boards micrometres away and eps_test means nothing.
void check_projects(const CameraModel& m, const std::string& path) {
  constexpr double kMaxOffAxisDeg = 89.5;
  double worst = 0;
  for (const double u : {0.0, (m.width() - 1) / 2.0, m.width() - 1.0}) {
    for (const double v : {0.0, (m.height() - 1) / 2.0, m.height() - 1.0}) {
      Eigen::Vector2d xn;
      const double deg =
          m.unproject(Eigen::Vector2d(u, v), &xn) ? std::atan(xn.norm()) * 180 / M_PI : 90.0;
      worst = std::max(worst, std::isfinite(deg) ? deg : 90.0);
    }
  }
  if (worst > kMaxOffAxisDeg) {
    throw Error(ErrorCode::kInvalidArgument,
                "evaluate: the model in '" + path + "' (fx " + std::to_string(m.fx()) + ", fy " +
                    std::to_string(m.fy()) + ") cannot project the test set: its image reaches " +
                    std::to_string(worst) + " degrees off axis (the limit is " +
                    std::to_string(kMaxOffAxisDeg) + ")");
  }
}

}  // namespace

POSECAL_API posecal_status posecal_evaluate(posecal_context* ctx, const char* result_path,
                                            const char* camera_uri, const char* options_json,
                                            char* buf, size_t* size) noexcept {
  return guarded(__func__, [&] {
    require(ctx, "ctx");
    require(result_path, "result_path");
    require(camera_uri, "camera_uri");
    require(size, "size");
    const Json o = abi::parse_options(
        options_json, {"target", "frames", "min_corners", "timeout_ms"}, kEvalOptions);
    const BoardSpec spec =
        o.contains("target") ? BoardSpec::parse(abi::get_string(o, "target", "", kEvalOptions))
                             : BoardSpec{};
    const int want = abi::get_int(o, "frames", 20, 1, 1000, kEvalOptions);
    const int min_corners = abi::get_int(o, "min_corners", 6, 4, 100000, kEvalOptions);
    const int timeout_ms = abi::get_int(o, "timeout_ms", 30000, 1, 600000, kEvalOptions);
    const std::string key = args_key({result_path, camera_uri, abi::to_text(o)});
    std::string text;
    if (ctx->impl->take_pending(__func__, key, &text))
      return abi::copy_out_kept(*ctx->impl, __func__, key, text, buf, size);

    const CameraModel estimate = read_camera_model(result_path);
    check_projects(estimate, result_path);
    const Uri uri = Uri::parse(camera_uri);
    ctx->impl->require_enabled(uri.scheme);
    const auto t0 = Clock::now();
    auto check_size = [&](cv::Size s, const std::string& what) {
      if (s.width != estimate.width() || s.height != estimate.height()) {
        throw Error(ErrorCode::kInvalidArgument,
                    "'" + std::string(result_path) + "' is a calibration of a " +
                        std::to_string(estimate.width()) + "x" + std::to_string(estimate.height()) +
                        " camera, " + what + " " + std::to_string(s.width) + "x" +
                        std::to_string(s.height));
      }
    };
    Json j;
    j["result_file"] = result_path;
    j["target"] = spec.to_string();
    std::vector<Observation> test_set;
    std::unique_ptr<CameraModel> truth;
    if (uri.scheme == "sim") {
      // The simulated camera's fixed test set (the one its live sessions report), and its truth.
      const SimCameraOptions so = sim_options_from_uri(uri, spec);
      check_size(so.truth.size(), "the simulated camera is");
      const std::unique_ptr<Camera> camera = make_sim_camera(so);
      j["camera"] = abi::device_json(camera->info());
      j["source"] = "sim_test_set";
      test_set = abi::sim_test_set(so);
      truth = std::make_unique<CameraModel>(so.truth);
      j["frames_seen"] = 50;
    } else {
      if (uri.scheme == "external") {
        throw Error(ErrorCode::kUnsupported,
                    "'external' gets frames only from a session's host: evaluate needs a camera");
      }
      // A real camera (or images://): the first `frames` frames that show at least min_corners
      // corners of the board.
      Streaming s(ctx->impl->open(camera_uri, spec));
      j["camera"] = abi::device_json(s.camera->info());
      j["source"] = "camera";
      const CameraTestSet cts = camera_test_set(*s.camera, camera_uri, spec, want, min_corners,
                                                t0 + std::chrono::milliseconds(timeout_ms), timeout_ms, check_size);
      test_set = cts.frames;
      j["frames_seen"] = cts.seen;
    }
    j["frames_collected"] = test_set.size();
    if (test_set.empty()) {
      throw Error(ErrorCode::kDegenerate,
                  "evaluate: no test frame from '" + std::string(camera_uri) +
                      "' showed the board: nothing to evaluate '" + result_path + "' on");
    }
    j.update(abi::evaluation_json(estimate, test_set, truth.get()));
    if (j["test_frames"].get<int>() == 0) {
      // A model that fits no frame's pose (e.g. fx 1e-9) is not a calibration of this camera.
      throw Error(ErrorCode::kInvalidArgument,
                  "evaluate: the model in '" + std::string(result_path) + "' (fx " +
                      std::to_string(estimate.fx()) + ", fy " + std::to_string(estimate.fy()) +
                      ") cannot project the test set: no pose fits any of the " +
                      std::to_string(test_set.size()) + " frames");
    }
    Json model;
    for (int i = 0; i < estimate.num_params(); ++i)
      model[estimate.param_names()[i]] = estimate.params()[i];
    j["model"] = model;
    j["image_width"] = estimate.width();
    j["image_height"] = estimate.height();
    if (truth) {
      Json t;
      for (int i = 0; i < truth->num_params(); ++i) t[truth->param_names()[i]] = truth->params()[i];
      j["ground_truth"] = t;
    }
    j["wall_ms"] = std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
    return abi::copy_out_kept(*ctx->impl, __func__, key, abi::to_text(j), buf, size);
  });
}

}  // extern "C"
