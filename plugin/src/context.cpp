#include "context.hpp"

#include <algorithm>

#include "posecal/error.hpp"
#include "posecal/simulation.hpp"
#include "posecal/sources.hpp"
#include "posecal/v4l2_backend.hpp"

using posecal::Error;
using posecal::ErrorCode;

namespace {

// Backends this build knows, in listing order.
const std::vector<std::string>& known_backends() {
  static const std::vector<std::string> names = {"sim", "images", "external", "v4l2"};
  return names;
}

std::shared_ptr<posecal::CameraBackend> make_backend(const std::string& name) {
  if (name == "sim") return posecal::make_sim_backend();
  if (name == "images") return posecal::make_images_backend();
  if (name == "external") return posecal::make_external_backend();
  if (name == "v4l2") return posecal::make_v4l2_backend();
  throw Error(ErrorCode::kInternal, "no factory for backend '" + name + "'");
}

}  // namespace

posecal_context::posecal_context(const nlohmann::json& options) {
  std::vector<std::string> enabled = known_backends();
  if (options.contains("backends")) {
    const auto& b = options["backends"];
    if (!b.is_array())
      throw Error(ErrorCode::kInvalidArgument, "context options: 'backends' must be an array");
    enabled.clear();
    for (const auto& item : b) {
      if (!item.is_string())
        throw Error(ErrorCode::kInvalidArgument, "context options: backend names are strings");
      const std::string name = item.get<std::string>();
      const auto& known = known_backends();
      if (std::find(known.begin(), known.end(), name) == known.end()) {
        throw Error(ErrorCode::kInvalidArgument, "context options: unknown backend '" + name + "'");
      }
      enabled.push_back(name);
    }
  }
  for (const auto& name : enabled) manager_.add_backend(make_backend(name));
}
