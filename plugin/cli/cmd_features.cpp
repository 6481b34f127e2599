// posecal features: a camera's settings (GenICam features, V4L2 controls).
#include <memory>

#include "commands.hpp"

namespace posecal::cli {

namespace {

struct FeaturesOptions {
  std::string camera;
  bool json = false;
};

std::string value_text(const Json& v) {
  if (v.is_null()) return "-";
  if (v.is_string()) return v.get<std::string>();
  return v.dump();
}

// " [min, max]" and " {a|b|c}" where the feature has a range or options.
std::string range_and_options(const Json& f) {
  std::string extra;
  // (append, not operator+: GCC 12's -Wrestrict misfires on string concatenation chains)
  if (f["range"].is_object()) {
    extra.append(" [").append(value_text(f["range"]["min"])).append(", ");
    extra.append(value_text(f["range"]["max"])).append("]");
  }
  if (f["options"].is_array()) {
    extra.append(" {");
    bool first = true;
    for (const auto& o : f["options"]) {
      if (!first) extra.append("|");
      extra.append(value_text(o));
      first = false;
    }
    extra.append("}");
  }
  return extra;
}

int run_features(const FeaturesOptions& o) {
  Context c;
  const Json j = Json::parse(fetch_json([&](char* b, size_t* n) {
    return posecal_camera_features(c.get(), o.camera.c_str(), b, n);
  }));
  if (o.json) {
    std::printf("%s\n", json_text(j).c_str());
    return kOk;
  }
  if (j.empty()) std::printf("%s has no settings\n", o.camera.c_str());
  for (const auto& f : j) {
    const std::string unit = f["unit"].is_string() ? f["unit"].get<std::string>() : "";
    std::printf("%-32s %-12s %-10s %s%s%s%s\n", f["name"].get<std::string>().c_str(),
                f["type"].get<std::string>().c_str(), f["access"].get<std::string>().c_str(),
                value_text(f["value"]).c_str(), unit.empty() ? "" : " ", unit.c_str(),
                range_and_options(f).c_str());
  }
  return kOk;
}

}  // namespace

Command add_features(CLI::App* app) {
  auto o = std::make_shared<FeaturesOptions>();
  CLI::App* cmd = app->add_subcommand(
      "features", "list the camera's settings (GenICam features, V4L2 controls)");
  cmd->add_option("--camera", o->camera, "the camera")
      ->type_name("URI")
      ->required()
      ->check(non_empty());
  add_json_flag(cmd, &o->json, "print the settings as one JSON array");
  return [o] { return run_features(*o); };
}

}  // namespace posecal::cli
