// posecal grab: N frames of a camera as PNG files.
#include <memory>

#include "commands.hpp"

namespace posecal::cli {

namespace {

struct GrabOptions {
  std::string camera, out;
  int count = 1, timeout_ms = 10000;
  bool json = false;
};

int run_grab(const GrabOptions& o) {
  Context c;
  const Json j = Json::parse(fetch_json([&](char* b, size_t* n) {
    return posecal_camera_grab(c.get(), o.camera.c_str(), o.count, o.out.c_str(), o.timeout_ms, b,
                               n);
  }));
  if (o.json) {
    std::printf("%s\n", json_text(j).c_str());
    return kOk;
  }
  for (const auto& f : j["files"]) std::printf("%s\n", f["file"].get<std::string>().c_str());
  std::printf("%zu frames from %s in %.0f ms\n", j["files"].size(), o.camera.c_str(),
              num_or(j, "wall_ms", 0));
  return kOk;
}

}  // namespace

Command add_grab(CLI::App* app) {
  auto o = std::make_shared<GrabOptions>();
  CLI::App* cmd = app->add_subcommand("grab", "save N frames of a camera as PNG files");
  cmd->add_option("--camera", o->camera, "the camera")
      ->type_name("URI")
      ->required()
      ->check(non_empty());
  cmd->add_option("--count", o->count, "frames to save")->required()->check(in_range(1, 100000));
  cmd->add_option("--out", o->out, "the folder of the PNG files (created if needed)")
      ->type_name("DIR")
      ->required()
      ->check(non_empty());
  cmd->add_option("--timeout-ms", o->timeout_ms,
                  "wait for a frame at most this long (default: 10000)")
      ->check(in_range(1, 600000));
  add_json_flag(cmd, &o->json, "print the files as one JSON object");
  return [o] { return run_grab(*o); };
}

}  // namespace posecal::cli
