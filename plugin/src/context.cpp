#include "context.hpp"

#include <algorithm>

#include "abi_common.hpp"
#include "common/error.hpp"
#include "sim/sim_camera.hpp"
#include "device/sources.hpp"
#ifndef POSECAL_ABI_NO_HW_BACKENDS
#include "posecal/aravis_backend.hpp"
#include "posecal/v4l2_backend.hpp"
#endif

using posecal::Error;
using posecal::ErrorCode;

namespace {

std::shared_ptr<posecal::CameraBackend> make_backend(const std::string& name) {
  if (name == "sim") return posecal::make_sim_backend();
  if (name == "images") return posecal::make_images_backend();
  if (name == "external") return posecal::make_external_backend();
#ifndef POSECAL_ABI_NO_HW_BACKENDS
  if (name == "aravis") return posecal::make_aravis_backend();
  if (name == "v4l2") return posecal::make_v4l2_backend();
#endif
  throw Error(ErrorCode::kInternal, "no factory for backend '" + name + "'");
}

}  // namespace

namespace posecal::abi {

const std::vector<std::string>& Context::known_backends() {
#ifndef POSECAL_ABI_NO_HW_BACKENDS
  static const std::vector<std::string> names = {"sim", "images", "external", "aravis", "v4l2"};
#else
  // The sanitizer copy of the library (plugin/CMakeLists.txt) has no hardware backends.
  static const std::vector<std::string> names = {"sim", "images", "external"};
#endif
  return names;
}

Context::Context(const nlohmann::json& options) {
  enabled_ = known_backends();
  if (options.contains("backends")) {
    const auto& b = options["backends"];
    if (!b.is_array())
      throw Error(ErrorCode::kInvalidArgument, "context options: 'backends' must be an array");
    enabled_.clear();
    for (const auto& item : b) {
      if (!item.is_string())
        throw Error(ErrorCode::kInvalidArgument, "context options: backend names are strings");
      const std::string name = item.get<std::string>();
      const auto& known = known_backends();
      if (std::find(known.begin(), known.end(), name) == known.end()) {
        std::string list;
        for (const auto& k : known) list += (list.empty() ? "" : ", ") + k;
        throw Error(ErrorCode::kInvalidArgument,
                    "context options: unknown backend '" + name + "' (known: " + list + ")");
      }
      if (std::find(enabled_.begin(), enabled_.end(), name) == enabled_.end()) {
        enabled_.push_back(name);
      }
    }
  }
  for (const auto& name : enabled_) manager_.add_backend(make_backend(name));
}

bool Context::enabled(const std::string& scheme) const {
  return std::find(enabled_.begin(), enabled_.end(), scheme) != enabled_.end();
}

void Context::require_enabled(const std::string& scheme) const {
  const auto& known = known_backends();
  if (std::find(known.begin(), known.end(), scheme) == known.end()) {
    throw Error(ErrorCode::kInvalidArgument, "unknown camera URI scheme '" + scheme + "'");
  }
  if (!enabled(scheme)) {
    throw Error(
        ErrorCode::kUnsupported,
        "backend '" + scheme + "' is not enabled in this context (context option 'backends')");
  }
}

std::vector<posecal::DeviceInfo> Context::list(std::vector<std::string>* errors) {
  return manager_.list(errors);
}

std::unique_ptr<posecal::Camera> Context::open(const std::string& uri_text,
                                               const posecal::BoardSpec& target) {
  const posecal::Uri uri = posecal::Uri::parse(uri_text);
  require_enabled(uri.scheme);
  if (uri.scheme == "sim") {
    // The sim backend renders its default board; a caller looking for another board needs it.
    return posecal::make_sim_camera(posecal::sim_options_from_uri(uri, target));
  }
  return manager_.open(uri_text);
}

bool Context::take_pending(const char* function, const std::string& args, std::string* text) {
  std::lock_guard<std::mutex> lock(pending_mutex_);
  const auto it = pending_.find({std::this_thread::get_id(), function});
  if (it == pending_.end()) return false;
  const bool same = it->second.args == args;
  if (same) *text = std::move(it->second.text);
  pending_.erase(it);  // a call with other arguments discards the kept output
  return same;
}

void Context::keep_pending(const char* function, const std::string& args, const std::string& text) {
  std::lock_guard<std::mutex> lock(pending_mutex_);
  pending_[{std::this_thread::get_id(), function}] = Pending{args, text};
}

posecal_status copy_out_kept(Context& ctx, const char* function, const std::string& args,
                             const std::string& text, char* buf, size_t* size) {
  const posecal_status s = copy_out(text, buf, size);
  if (s == POSECAL_E_BUFFER_TOO_SMALL) ctx.keep_pending(function, args, text);
  return s;
}

}  // namespace posecal::abi
