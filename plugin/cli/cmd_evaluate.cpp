// posecal evaluate: the test-set error (eps_test; eps_gt for sim://) of an existing calibration.
#include <memory>

#include "commands.hpp"

namespace posecal::cli {

namespace {

struct EvaluateOptions {
  std::string result, camera, target;
  int frames = 0, timeout_ms = 0, min_corners = 0;
  bool json = false;
  // The library's defaults apply to what was not given.
  CLI::Option *target_opt = nullptr, *frames_opt = nullptr, *timeout_opt = nullptr,
              *min_corners_opt = nullptr;
};

int run_evaluate(const EvaluateOptions& o) {
  Json opts = Json::object();
  if (o.target_opt->count()) opts["target"] = o.target;
  if (o.frames_opt->count()) opts["frames"] = o.frames;
  if (o.timeout_opt->count()) opts["timeout_ms"] = o.timeout_ms;
  if (o.min_corners_opt->count()) opts["min_corners"] = o.min_corners;
  Context c;
  const std::string text = opts.dump();
  const Json j = Json::parse(fetch_json([&](char* b, size_t* n) {
    return posecal_evaluate(c.get(), o.result.c_str(), o.camera.c_str(), text.c_str(), b, n);
  }));
  if (o.json) {
    std::printf("%s\n", j.dump().c_str());
    return kOk;
  }
  if (!j["eps_test"].is_number()) {  // the library reports this as an error; never print a figure
    throw Failure{POSECAL_E_DEGENERATE, "evaluate: no test-set error for " + o.result};
  }
  std::printf("%s on %s: eps_test %.4f px over %d frames (%d failed PnP)", o.result.c_str(),
              o.camera.c_str(), j["eps_test"].get<double>(), j["test_frames"].get<int>(),
              j["test_frames_failed"].get<int>());
  if (j["eps_gt"].is_number()) std::printf(", eps_gt %.4f px", j["eps_gt"].get<double>());
  std::printf("\n");
  return kOk;
}

}  // namespace

Command add_evaluate(CLI::App* app) {
  auto o = std::make_shared<EvaluateOptions>();
  CLI::App* cmd = app->add_subcommand(
      "evaluate", "test-set error (eps_test; eps_gt for sim://) of an existing calibration file");
  cmd->footer(target_spec_help());
  cmd->add_option("--result", o->result, "the calibration file (any format posecal writes, docs/formats.md)")
      ->type_name("FILE")
      ->required()
      ->check(non_empty());
  cmd->add_option("--camera", o->camera, "the camera the test frames come from")
      ->type_name("URI")
      ->required()
      ->check(non_empty());
  o->target_opt =
      cmd->add_option("--target", o->target,
                      "the board, SPEC (below; default: charuco:9x6:0.028:0.0182:DICT_4X4_50)")
          ->type_name("SPEC");
  o->frames_opt =
      cmd->add_option("--frames", o->frames, "test frames (default: 20)")->check(in_range(1, 1000));
  o->timeout_opt = cmd->add_option("--timeout-ms", o->timeout_ms,
                                   "wait for the frames at most this long (default: 30000)")
                       ->check(in_range(1, 600000));
  o->min_corners_opt =
      cmd->add_option("--min-corners", o->min_corners, "corners a test frame needs (default: 6)")
          ->check(in_range(4, 100000));
  add_json_flag(cmd, &o->json, "print the evaluation as one JSON object");
  return [o] { return run_evaluate(*o); };
}

}  // namespace posecal::cli
