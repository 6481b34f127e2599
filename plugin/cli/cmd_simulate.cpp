// posecal simulate: the full closed loop on the built-in simulated camera (sim://).
#include <cmath>
#include <memory>
#include <vector>

#include "commands.hpp"
#include "common/percent_encoding.hpp"
#include "interrupt.hpp"
#include "session_flags.hpp"

namespace posecal::cli {

namespace {

struct SimulateOptions {
  int seed = 1;
  std::string noise, blur, camera_model, out, format;
  int max_frames = 5000;
  bool json = false, events = false;
  std::unique_ptr<SessionFlags> session;
};

// The sim:// URI of the options. The operator is not in it: it is a session key, and the
// library makes the simulated operator follow the session's.
std::string sim_uri(const SimulateOptions& o) {
  std::string uri = "sim://?seed=" + std::to_string(o.seed);
  if (!o.noise.empty()) uri += "&noise=" + percent_encode(o.noise);
  if (!o.blur.empty()) uri += "&blur=" + percent_encode(o.blur);
  if (!o.camera_model.empty()) uri += "&model=" + percent_encode(o.camera_model);
  return uri;
}

// The expected-error map at cols x rows points, edge to edge (posecal.h); NaN as null.
Json expected_error_map(posecal_session* s, int cols, int rows) {
  std::vector<float> values(static_cast<size_t>(cols) * rows);
  check(posecal_session_expected_error_map(s, values.data(), cols, rows, 0));
  Json px = Json::array();
  for (int j = 0; j < rows; ++j) {
    Json row = Json::array();
    for (int i = 0; i < cols; ++i) {
      const float v = values[static_cast<size_t>(j) * cols + i];
      row.push_back(std::isfinite(v) ? Json(v) : Json(nullptr));
    }
    px.push_back(row);
  }
  return Json{{"cols", cols}, {"rows", rows}, {"px", px}};
}

void print_text_summary(const SimulateOptions& o, const Json& j, double wall_ms) {
  std::printf(
      "%s after %d keyframes (%d frames, %.1f s); eps_res %.3f px, eps_test %.3f px, eps_gt "
      "%.3f px\n",
      j.value("interrupted", false) ? "INTERRUPTED"
      : j["converged"].get<bool>() ? "converged"
                                   : "NOT converged",
      j["keyframes"].get<int>(),
      j["frames_processed"].get<int>(), wall_ms / 1000.0, num_or(j, "eps_res", -1),
      num_or(j, "eps_test", -1), num_or(j, "eps_gt", -1));
  if (j["expected_error_px"].is_number() && j["expected_error_p90_px"].is_number()) {
    std::printf("  expected error %.3f px RMS, 9 of 10 such calibrations within %.3f px (the "
                "calibration's own prediction of eps_gt)\n",
                j["expected_error_px"].get<double>(), j["expected_error_p90_px"].get<double>());
  }
  const Json none = Json::object();
  const Json& truth = j.contains("ground_truth") ? j["ground_truth"] : none;
  for (const auto& name : j["covariance_order"]) {
    const std::string k = name.get<std::string>();
    std::printf("  %-3s = %14.6f  +- %.6f   (true %.6f)\n", k.c_str(), num_or(j, k, NAN),
                num_or(j["std"], k, NAN), num_or(truth, k, NAN));
  }
  print_verdict(j);
  if (!o.out.empty()) std::printf("written %s\n", o.out.c_str());
}

int run_simulate(const SimulateOptions& o) {
  if (!o.out.empty()) check_output_file(o.out, result_extensions(o.format));
  const auto t0 = Clock::now();
  Context c;
  Session s(c.get(), sim_uri(o), o.session->config());
  EventSink sink{stderr, ""};
  if (o.events) check(posecal_session_set_callback(s.get(), print_event_line, &sink));
  for (int frames = 0; frames < o.max_frames; ++frames) {
    if (interrupt_requested()) {
      check(posecal_session_interrupt(s.get()));
      break;
    }
    const posecal_status st = posecal_session_step(s.get(), 1000);
    if (st == POSECAL_E_STATE) break;  // finished
    check(st);
  }
  const double wall_ms = ms_since(t0);
  if (!has_result(s.get())) {
    if (interrupt_requested()) return interrupt_exit_code();
    throw Failure{POSECAL_E_STATE, "no calibration: fewer than two keyframes"};
  }
  if (!o.out.empty()) {
    check(posecal_session_save_as(s.get(), o.out.c_str(), format_arg(o.format)));
  }
  Json j = summary(fetch_result(s.get()), wall_ms);
  if (o.json) j["expected_error_map"] = expected_error_map(s.get(), 16, 9);
  if (o.json) {
    std::printf("%s\n", json_text(j).c_str());
  } else {
    print_text_summary(o, j, wall_ms);
  }
  if (j.value("interrupted", false)) return interrupt_exit_code();
  return calibration_exit_code(j);
}

}  // namespace

Command add_simulate(CLI::App* app) {
  auto o = std::make_shared<SimulateOptions>();
  CLI::App* cmd = app->add_subcommand(
      "simulate",
      "full closed-loop calibration on a synthetic camera (default: sampled around a C525)");
  cmd->footer(target_spec_help());
  cmd->add_option("--seed", o->seed, "the simulated camera and operator (default: 1)")
      ->check(in_range(0, 2000000000));
  cmd->add_option("--camera-model", o->camera_model,
                  "the true camera as a calibration file (default: sampled from the seed)")
      ->type_name("FILE");
  cmd->add_option("--noise", o->noise, "image noise sigma, grey levels, 0..50 (default: 2)")
      ->type_name("GREY");
  cmd->add_option("--blur", o->blur, "image blur sigma, pixels, 0..10 (default: 0.8)")
      ->type_name("PX");
  cmd->add_option("--max-frames", o->max_frames, "stop after this many frames (default: 5000)")
      ->check(in_range(1, 10000000));
  cmd->add_option("--out", o->out,
                  "write the calibration (.yml, .yaml, .json, .xml or .cameramodel)")
      ->type_name("FILE");
  add_format_option(cmd, &o->format);
  add_json_flag(cmd, &o->json, "print the summary as one JSON object");
  cmd->add_flag("--events", o->events, "print the session's events as JSON lines on stderr");
  o->session = std::make_unique<SessionFlags>(cmd);
  return [o] { return run_simulate(*o); };
}

}  // namespace posecal::cli
