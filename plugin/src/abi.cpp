// Exported entry points of libposecal.so (plugin/include/posecal.h). Each one is a thin shell:
// validate the C arguments, call core, and let abi::guarded() turn exceptions into statuses.
#include <memory>
#include <mutex>

#include "abi_common.hpp"
#include "context.hpp"
#include "json_report.hpp"
#include "posecal.h"
#include "posecal/offline.hpp"

namespace posecal::abi {
const char* last_error();
}

using namespace posecal;
using posecal::abi::guarded;
using posecal::abi::require;

struct posecal_calibration {
  OfflineCalibration offline;
  TargetSpec target;
  std::string images_dir;
};

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
    *out = new posecal_context(opts);
    return POSECAL_OK;
  });
}

POSECAL_API void posecal_context_destroy(posecal_context* ctx) noexcept {
  guarded(__func__, [&] {
    delete ctx;
    return POSECAL_OK;
  });
}

POSECAL_API posecal_status posecal_list_cameras(posecal_context* ctx, char* buf,
                                                size_t* size) noexcept {
  return guarded(__func__, [&] {
    require(ctx, "ctx");
    require(size, "size");
    nlohmann::json arr = nlohmann::json::array();
    for (const DeviceInfo& d : ctx->manager().list()) arr.push_back(abi::device_json(d));
    return abi::copy_out(arr.dump(), buf, size);
  });
}

POSECAL_API posecal_status posecal_write_target(const char* target_spec, const char* path,
                                                double dpi, double margin_m) noexcept {
  return guarded(__func__, [&] {
    require(path, "path");
    const TargetSpec spec = target_spec ? TargetSpec::parse(target_spec) : TargetSpec{};
    Target(spec).write_printable(path, dpi, margin_m);
    return POSECAL_OK;
  });
}

POSECAL_API posecal_status posecal_calibrate_images(posecal_context* ctx, const char* images_dir,
                                                    const char* target_spec,
                                                    const char* options_json,
                                                    posecal_calibration** out) noexcept {
  return guarded(__func__, [&] {
    require(ctx, "ctx");
    require(images_dir, "images_dir");
    require(out, "out");
    *out = nullptr;
    const auto opts = abi::parse_options(
        options_json,
        {"fix_principal_point", "fix_aspect_ratio", "zero_tangential", "fixed", "min_corners"},
        "calibration options");
    OfflineOptions o;
    o.calibration.fix_principal_point = opts.value("fix_principal_point", false);
    o.calibration.fix_aspect_ratio = opts.value("fix_aspect_ratio", false);
    o.calibration.zero_tangential = opts.value("zero_tangential", false);
    o.calibration.fixed = opts.value("fixed", std::vector<std::string>{});
    o.min_corners = opts.value("min_corners", 6);
    if (o.min_corners < 4) throw Error(ErrorCode::kInvalidArgument, "min_corners must be >= 4");
    auto cal = std::make_unique<posecal_calibration>();
    cal->target = target_spec ? TargetSpec::parse(target_spec) : TargetSpec{};
    cal->images_dir = images_dir;
    cal->offline = calibrate_images(images_dir, cal->target, o);
    *out = cal.release();
    return POSECAL_OK;
  });
}

POSECAL_API posecal_status posecal_calibration_json(const posecal_calibration* cal, char* buf,
                                                    size_t* size) noexcept {
  return guarded(__func__, [&] {
    require(cal, "cal");
    require(size, "size");
    nlohmann::json j = abi::calibration_json(cal->offline.result);
    j["target"] = cal->target.to_string();
    j["images_dir"] = cal->images_dir;
    j["frames_used"] = cal->offline.used.size();
    j["frames_rejected"] = cal->offline.rejected.size();
    j["used"] = cal->offline.used;
    nlohmann::json rej = nlohmann::json::array();
    for (const auto& r : cal->offline.rejected)
      rej.push_back({{"file", r.file}, {"reason", r.reason}});
    j["rejected"] = rej;
    return abi::copy_out(j.dump(), buf, size);
  });
}

POSECAL_API posecal_status posecal_calibration_save(const posecal_calibration* cal,
                                                    const char* path) noexcept {
  return guarded(__func__, [&] {
    require(cal, "cal");
    require(path, "path");
    abi::save_calibration(path, cal->offline.result, {{"target", cal->target.to_string()}});
    return POSECAL_OK;
  });
}

POSECAL_API void posecal_calibration_destroy(posecal_calibration* cal) noexcept {
  guarded(__func__, [&] {
    delete cal;
    return POSECAL_OK;
  });
}

}  // extern "C"
