// Exported entry points of libposecal.so (plugin/include/posecal.h). Each one is a thin shell:
// validate the C arguments, call core, and let abi::guarded() turn exceptions into statuses.
#include <chrono>
#include <memory>
#include <mutex>
#include <optional>

#include "abi_common.hpp"
#include "context.hpp"
#include "json_report.hpp"
#include "lens/lens_models.hpp"
#include "posecal.h"
#include "quality_gate.hpp"
#include "calib/offline.hpp"

using namespace posecal;
using posecal::abi::guarded;
using posecal::abi::require;

struct posecal_calibration {
  OfflineCalibration offline;
  BoardSpec board;
  std::string images_dir;
  double seconds = 0;  // the whole offline calibration's wall time
  std::optional<abi::QualitySpec> spec;
};

namespace {

void save_offline(const posecal_calibration* cal, const char* path, const char* format) {
  require(cal, "cal");
  require(path, "path");
  CalibrationFileExtras extras;
  extras.strings = {{"target", cal->board.to_string()}};
  abi::save_calibration(path, cal->offline.result, format, extras);
}

}  // namespace

extern "C" {

POSECAL_API unsigned posecal_abi_version(void) noexcept { return POSECAL_ABI_VERSION; }

POSECAL_API const char* posecal_version(void) noexcept { return POSECAL_VERSION_STRING; }

POSECAL_API const char* posecal_last_error(void) noexcept { return abi::last_error(); }

POSECAL_API const char* posecal_status_name(posecal_status status) noexcept {
  switch (status) {
    case POSECAL_OK:
      return "POSECAL_OK";
    case POSECAL_E_INVALID_ARGUMENT:
      return "POSECAL_E_INVALID_ARGUMENT";
    case POSECAL_E_NOT_FOUND:
      return "POSECAL_E_NOT_FOUND";
    case POSECAL_E_BUFFER_TOO_SMALL:
      return "POSECAL_E_BUFFER_TOO_SMALL";
    case POSECAL_E_TIMEOUT:
      return "POSECAL_E_TIMEOUT";
    case POSECAL_E_DEVICE:
      return "POSECAL_E_DEVICE";
    case POSECAL_E_STATE:
      return "POSECAL_E_STATE";
    case POSECAL_E_IO:
      return "POSECAL_E_IO";
    case POSECAL_E_INTERNAL:
      return "POSECAL_E_INTERNAL";
    case POSECAL_E_DEGENERATE:
      return "POSECAL_E_DEGENERATE";
    case POSECAL_E_UNSUPPORTED:
      return "POSECAL_E_UNSUPPORTED";
  }
  return "POSECAL_E_UNKNOWN";
}

POSECAL_API posecal_status posecal_context_create(const char* options_json,
                                                  posecal_context** out) noexcept {
  return guarded(__func__, [&] {
    require(out, "out");
    *out = nullptr;
    const auto opts = abi::parse_options(options_json, {"backends"}, "context options");
    auto ctx = std::make_unique<posecal_context>();
    ctx->impl = std::make_shared<abi::Context>(opts);
    *out = ctx.release();
    return POSECAL_OK;
  });
}

POSECAL_API void posecal_context_destroy(posecal_context* ctx) noexcept {
  abi::guarded_void(__func__, [&] { delete ctx; });
}

POSECAL_API posecal_status posecal_list_cameras(posecal_context* ctx, char* buf,
                                                size_t* size) noexcept {
  return guarded(__func__, [&] {
    require(ctx, "ctx");
    require(size, "size");
    std::string text;
    if (!ctx->impl->take_pending(__func__, "", &text)) {
      nlohmann::json arr = nlohmann::json::array();
      for (const DeviceInfo& d : ctx->impl->list(nullptr)) arr.push_back(abi::device_json(d));
      text = abi::to_text(arr);
    }
    return abi::copy_out_kept(*ctx->impl, __func__, "", text, buf, size);
  });
}

POSECAL_API posecal_status posecal_write_target(const char* target_spec, const char* path,
                                                double dpi, double margin_m) noexcept {
  return guarded(__func__, [&] {
    require(path, "path");
    const BoardSpec spec = target_spec ? BoardSpec::parse(target_spec) : BoardSpec{};
    Board(spec).write_printable(path, dpi, margin_m);
    return POSECAL_OK;
  });
}

POSECAL_API posecal_status posecal_write_target_ex(const char* target_spec, const char* path,
                                                   const char* options_json) noexcept {
  return guarded(__func__, [&] {
    require(path, "path");
    const char* what = "target options";
    const auto opts = abi::parse_options(options_json, {"paper", "dpi", "margin_m"}, what);
    PrintOptions o;
    o.paper = paper_from_name(abi::get_string(opts, "paper", "board", what));
    o.dpi = abi::get_double(opts, "dpi", 300, 50, 2400, what);
    o.margin_m = abi::get_double(opts, "margin_m", 0.01, 0, 0.999, what);
    const BoardSpec spec = target_spec ? BoardSpec::parse(target_spec) : BoardSpec{};
    Board(spec).write_printable(path, o);
    return POSECAL_OK;
  });
}

namespace {

posecal_status calibrate_images_with(posecal_context* ctx, const char* images_dir,
                                     const char* target_spec, const char* options_json,
                                     posecal_event_fn progress, void* user_data,
                                     posecal_calibration** out, const char* function) {
  return guarded(function, [&] {
    require(ctx, "ctx");
    require(images_dir, "images_dir");
    require(out, "out");
    *out = nullptr;
    const auto opts = abi::parse_options(options_json,
                                         {"fix_principal_point", "fix_aspect_ratio",
                                          "zero_tangential", "fixed", "min_corners",
                                          "camera_group", "spec"},
                                         "calibration options");
    const char* what = "calibration options";
    OfflineOptions o;
    o.calibration.fix_principal_point = abi::get_bool(opts, "fix_principal_point", false, what);
    o.calibration.fix_aspect_ratio = abi::get_bool(opts, "fix_aspect_ratio", false, what);
    o.calibration.zero_tangential = abi::get_bool(opts, "zero_tangential", false, what);
    o.calibration.fixed = abi::get_strings(opts, "fixed", what);
    o.min_corners = abi::get_int(opts, "min_corners", 6, 4, 100000, what);
    o.camera_group = abi::get_string(opts, "camera_group", "", what);
    std::string why;
    if (!o.calibration.is_valid(&why))
      throw Error(ErrorCode::kInvalidArgument, std::string(what) + ": " + why);
    if (progress) {
      o.progress = [&](const ImageProgress& p) {
        nlohmann::json j = {{"index", p.index}, {"total", p.total}, {"file", p.file},
                            {"corners", p.corners}, {"used", p.used}};
        if (!p.used) j["reason"] = p.reason;
        const std::string text = abi::to_text(j);
        try {
          progress(user_data, "image", text.c_str());
        } catch (...) {  // a host's exception must not unwind through the library
        }
      };
    }
    auto cal = std::make_unique<posecal_calibration>();
    const std::string spec = abi::get_string(opts, "spec", "", what);
    // Read before the images: a malformed specification costs no calibration.
    if (!spec.empty()) cal->spec = abi::read_quality_spec(spec, intrinsic_names(LensModel::kOpenCV5));
    cal->board = target_spec ? BoardSpec::parse(target_spec) : BoardSpec{};
    cal->images_dir = images_dir;
    const auto t0 = std::chrono::steady_clock::now();
    cal->offline = calibrate_images(images_dir, cal->board, o);
    cal->seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    *out = cal.release();
    return POSECAL_OK;
  });
}

}  // namespace

POSECAL_API posecal_status posecal_calibrate_images(posecal_context* ctx, const char* images_dir,
                                                    const char* target_spec,
                                                    const char* options_json,
                                                    posecal_calibration** out) noexcept {
  return calibrate_images_with(ctx, images_dir, target_spec, options_json, nullptr, nullptr, out,
                               __func__);
}

POSECAL_API posecal_status posecal_calibrate_images_ex(posecal_context* ctx,
                                                       const char* images_dir,
                                                       const char* target_spec,
                                                       const char* options_json,
                                                       posecal_event_fn progress, void* user_data,
                                                       posecal_calibration** out) noexcept {
  return calibrate_images_with(ctx, images_dir, target_spec, options_json, progress, user_data,
                               out, __func__);
}

POSECAL_API posecal_status posecal_calibration_json(const posecal_calibration* cal, char* buf,
                                                    size_t* size) noexcept {
  return guarded(__func__, [&] {
    require(cal, "cal");
    require(size, "size");
    nlohmann::json j = abi::calibration_json(cal->offline.result);
    j["target"] = cal->board.to_string();
    j["images_dir"] = cal->images_dir;
    j["frames_used"] = cal->offline.used.size();
    j["frames_rejected"] = cal->offline.rejected.size();
    j["used"] = cal->offline.used;
    j["camera_group"] = cal->offline.group;
    nlohmann::json groups = nlohmann::json::array();
    for (const auto& g : cal->offline.groups) {
      groups.push_back({{"name", g.name}, {"camera", g.camera}, {"width", g.size.width},
                        {"height", g.size.height}, {"images", g.files.size()}});
    }
    j["groups"] = groups;
    j["seconds"] = abi::number(cal->seconds);
    if (cal->spec) {
      // An offline calibration has no ratio test: "converged" is the solver's.
      j["converged"] = j.value("solver_converged", false);
      j.update(abi::quality_verdict(*cal->spec, j, static_cast<int>(cal->offline.used.size()),
                                    cal->seconds));
    }
    nlohmann::json rej = nlohmann::json::array();
    for (const auto& r : cal->offline.rejected)
      rej.push_back({{"file", r.file}, {"reason", r.reason}});
    j["rejected"] = rej;
    return abi::copy_out(abi::to_text(j), buf, size);
  });
}

POSECAL_API posecal_status posecal_calibration_save(const posecal_calibration* cal,
                                                    const char* path) noexcept {
  return guarded(__func__, [&] {
    save_offline(cal, path, nullptr);
    return POSECAL_OK;
  });
}

POSECAL_API posecal_status posecal_calibration_save_as(const posecal_calibration* cal,
                                                       const char* path,
                                                       const char* format) noexcept {
  return guarded(__func__, [&] {
    save_offline(cal, path, format);
    return POSECAL_OK;
  });
}

POSECAL_API void posecal_calibration_destroy(posecal_calibration* cal) noexcept {
  abi::guarded_void(__func__, [&] { delete cal; });
}

}  // extern "C"
