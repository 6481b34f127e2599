// posecal calibrate: from a folder of images (--images DIR), or live with pose selection
// (--camera URI: guidance overlay in a window, or the robot protocol with --guide stdio).
#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <memory>

#include "commands.hpp"
#include "interrupt.hpp"
#include "live_window.hpp"
#include "robot_protocol.hpp"
#include "session_flags.hpp"

namespace posecal::cli {

namespace {

struct CalibrateOptions {
  std::string images, camera, out, format;
  bool json = false;
  // --images
  bool fix_principal_point = false, fix_aspect_ratio = false, zero_tangential = false;
  std::string camera_group;
  // --camera
  std::string guide = "overlay";
  bool no_window = false;
  double result_seconds = 15;  // the window's result screen: shown until a key or this long
  int timeout_ms = 2000;
  double max_seconds = 1800, reply_timeout_s = 600;
  // Also --images' --target: one flag, the session key's (the table's doc describes it).
  std::unique_ptr<SessionFlags> session;
};

// ---- --images ----

void print_images_result(const CalibrateOptions& o, const Json& j) {
  std::printf("calibrated group '%s' from %zu image(s), %zu not used; RMS %.4f px\n",
              j.value("camera_group", "").c_str(), j["used"].size(), j["rejected"].size(),
              num_or(j, "rms", -1));
  for (const auto& name : j["covariance_order"]) {
    const std::string n = name.get<std::string>();
    std::printf("  %-3s = %14.6f  +- %.6f\n", n.c_str(), num_or(j, n, NAN),
                num_or(j["std"], n, NAN));
  }
  for (const auto& r : j["rejected"]) {
    std::printf("  not used %s: %s\n", r["file"].get<std::string>().c_str(),
                r["reason"].get<std::string>().c_str());
  }
  print_verdict(j);
  if (!o.out.empty()) std::printf("written %s\n", o.out.c_str());
}

void print_image_progress(void*, const char*, const char* payload) {
  const Json p = Json::parse(payload, nullptr, false);
  if (p.is_discarded()) return;
  const std::string what = p.value("used", false)
                               ? std::to_string(p.value("corners", 0)) + " corners"
                               : "not used: " + p.value("reason", std::string());
  std::printf("[%d/%d] %s: %s\n", p.value("index", 0), p.value("total", 0),
              p.value("file", std::string()).c_str(), what.c_str());
  std::fflush(stdout);
}

int calibrate_images(const CalibrateOptions& o) {
  Context c;
  Json opts = Json::object();
  if (o.fix_principal_point) opts["fix_principal_point"] = true;
  if (o.fix_aspect_ratio) opts["fix_aspect_ratio"] = true;
  if (o.zero_tangential) opts["zero_tangential"] = true;
  const std::string target = o.session->config().value("target", "");
  posecal_calibration* cal = nullptr;
  if (!o.camera_group.empty()) opts["camera_group"] = o.camera_group;
  const std::string spec = o.session->config().value("spec", "");
  if (!spec.empty()) opts["spec"] = spec;
  // Text mode: one progress line per image as it is done (a long folder is not silent); --json
  // prints the one result document only.
  const posecal_event_fn progress = o.json ? nullptr : print_image_progress;
  check(posecal_calibrate_images_ex(c.get(), o.images.c_str(),
                                    target.empty() ? nullptr : target.c_str(),
                                    opts.dump().c_str(), progress, nullptr, &cal));
  const std::unique_ptr<posecal_calibration, void (*)(posecal_calibration*)> guard(
      cal, posecal_calibration_destroy);
  if (!o.out.empty()) {
    check(posecal_calibration_save_as(cal, o.out.c_str(), format_arg(o.format)));
  }
  const Json j = Json::parse(
      fetch_json([&](char* b, size_t* s) { return posecal_calibration_json(cal, b, s); }));
  if (o.json) {
    std::printf("%s\n", json_text(j).c_str());
  } else {
    print_images_result(o, j);
  }
  return j.value("verdict", "") == "fail" ? kSpecFailed : kOk;
}

// ---- --camera ----

struct LiveRun {
  bool stopped_by_user = false;
  bool interrupted = false;  // SIGINT / SIGTERM
  double wall_ms = 0;
};

// Steps the session until it finishes, the time is up or the user closes the window; shows
// the guidance (window, stderr) or runs the robot protocol.
LiveRun run_live(posecal_session* s, const CalibrateOptions& o, bool robot) {
  LiveWindow window(!robot && !o.no_window);
  if (!window.enabled() && !o.json && !robot) {
    std::fprintf(stderr, "posecal calibrate: no display; running headless\n");
  }
  RobotLink link(STDIN_FILENO, static_cast<int>(std::min(1e9, o.reply_timeout_s * 1000)));
  const auto t0 = Clock::now();
  LiveRun run;
  std::string last_guidance;
  int timeouts = 0;
  while (true) {
    if (interrupt_requested()) {
      check(posecal_session_interrupt(s));
      run.interrupted = true;
      break;
    }
    if (ms_since(t0) > o.max_seconds * 1000) {
      std::fprintf(stderr, "posecal calibrate: stopped after %.0f s without finishing\n",
                   o.max_seconds);
      break;
    }
    const posecal_status st = posecal_session_step(s, o.timeout_ms);
    if (st == POSECAL_E_STATE || st == POSECAL_E_NOT_FOUND) break;  // finished / end of images
    if (st == POSECAL_E_TIMEOUT || st == POSECAL_E_DEVICE) {
      if (++timeouts % 5 == 1)
        std::fprintf(stderr, "posecal calibrate: %s\n", posecal_last_error());
      continue;
    }
    check(st);
    timeouts = 0;
    const Json status = fetch_status(s);
    if (!window.show(s, status)) {
      run.stopped_by_user = true;
      break;
    }
    if (robot) {
      link.after_step(s, status);
    } else if (!o.json && status["guidance"].is_string() &&
               status["guidance"].get<std::string>() != last_guidance) {
      last_guidance = status["guidance"].get<std::string>();
      // Headless there is no overlay to align with: say so rather than refer to it.
      std::string said = last_guidance;
      const size_t at = window.enabled() ? std::string::npos : said.find("the overlay");
      if (at != std::string::npos) {
        said.replace(at, 11, "the target (not shown without a window; posecal serve shows it)");
      }
      std::fprintf(stderr, "[%d keyframes] %s\n", status["keyframes"].get<int>(), said.c_str());
    }
  }
  run.wall_ms = ms_since(t0);
  if (!run.interrupted && !run.stopped_by_user) window.hold_result(s, o.result_seconds);
  return run;
}

int report_live(posecal_session* s, const CalibrateOptions& o, bool robot, const LiveRun& run) {
  if (!has_result(s) && run.interrupted) {
    std::fprintf(stderr, "posecal calibrate: interrupted before two keyframes: nothing to save\n");
    return interrupt_exit_code();
  }
  if (!has_result(s)) {
    throw Failure{POSECAL_E_STATE,
                  std::string("no calibration: fewer than two keyframes were captured") +
                      (run.stopped_by_user ? " (window closed)" : "")};
  }
  const Json result = fetch_result(s);
  if (!o.out.empty()) check(posecal_session_save_as(s, o.out.c_str(), format_arg(o.format)));
  const Json j = summary(result, run.wall_ms);
  if (o.json || robot) {
    Json line = j;
    line["event"] = "result";
    if (!o.out.empty()) line["file"] = o.out;
    write_line(stdout, line);
  } else {
    std::printf("%s after %d keyframes; eps_res %.3f px\n",
                run.interrupted               ? "INTERRUPTED"
                : j["converged"].get<bool>() ? "converged"
                                             : "NOT converged",
                j["keyframes"].get<int>(), num_or(j, "eps_res", -1));
    print_verdict(j);
    if (!o.out.empty()) std::printf("written %s\n", o.out.c_str());
  }
  if (run.interrupted) return interrupt_exit_code();
  return calibration_exit_code(j);
}

int calibrate_camera(const CalibrateOptions& o) {
  Json cfg = o.session->config();
  const bool robot = o.guide == "stdio";
  if (robot) {
    // The protocol is the robot's: the session must expect reported poses.
    if (cfg.value("operator", "robot") != "robot") {
      throw UsageError{"--guide stdio is for --operator robot"};
    }
    cfg["operator"] = "robot";
  }
  Context c;
  Session s(c.get(), o.camera, cfg);
  EventSink sink{stdout, ""};
  if (o.json) check(posecal_session_set_callback(s.get(), print_event_line, &sink));
  return report_live(s.get(), o, robot, run_live(s.get(), o, robot));
}

int run_calibrate(const CalibrateOptions& o) {
  if (!o.out.empty()) check_output_file(o.out, result_extensions(o.format));
  if (!o.camera.empty()) return calibrate_camera(o);
  if (!o.images.empty()) return calibrate_images(o);
  throw UsageError{"calibrate needs --camera URI or --images DIR"};
}

void add_images_options(CLI::App* cmd, CalibrateOptions* o) {
  const std::string group = "with --images";
  cmd->add_flag("--fix-principal-point", o->fix_principal_point,
                "hold cx, cy at their initial value (the image centre)")
      ->group(group);
  cmd->add_flag("--fix-aspect-ratio", o->fix_aspect_ratio, "hold fy / fx at its initial value")
      ->group(group);
  cmd->add_flag("--zero-tangential", o->zero_tangential, "hold p1 = p2 = 0")->group(group);
  cmd->add_option("--camera-group", o->camera_group,
                  "where the folder mixes cameras or image sizes, calibrate this group: its name "
                  "(left@640x480), camera (left) or size (640x480); without it such a folder is "
                  "refused with the list of groups")
      ->group(group);
}

void add_camera_options(CLI::App* cmd, CalibrateOptions* o) {
  const std::string group = "with --camera";
  cmd->add_option("--guide", o->guide,
                  "overlay: guidance for a person (window, stderr); stdio: the robot protocol "
                  "(default: overlay)")
      ->check(CLI::IsMember({"overlay", "stdio"}))
      ->group(group);
  cmd->add_flag("--no-window", o->no_window, "no live window even with a display")->group(group);
  cmd->add_option("--result-seconds", o->result_seconds,
                  "the window shows the result until a key is pressed or this many seconds "
                  "(default 15; 0: closes at once)")
      ->check(CLI::Range(0.0, 3600.0))
      ->group(group);
  cmd->add_option("--timeout-ms", o->timeout_ms,
                  "wait for a frame at most this long (default: 2000)")
      ->check(in_range(0, 600000))
      ->group(group);
  cmd->add_option("--max-seconds", o->max_seconds, "give up after this long (default: 1800)")
      ->check(CLI::NonNegativeNumber)
      ->group(group);
  cmd->add_option("--reply-timeout-s", o->reply_timeout_s,
                  "--guide stdio: wait for the controller's reply at most this long (default: 600)")
      ->check(CLI::NonNegativeNumber)
      ->group(group);
}

}  // namespace

Command add_calibrate(CLI::App* app) {
  auto o = std::make_shared<CalibrateOptions>();
  CLI::App* cmd = app->add_subcommand(
      "calibrate", "calibrate from a folder of images, or live with pose selection");
  cmd->footer(
      "--images DIR: the images in name order; --target and the --images options apply.\n"
      "--camera URI: live; a window shows the camera and the target when DISPLAY is set;\n"
      "  --json prints one JSON event per line. --guide stdio (robot mode) prints each target\n"
      "  pose as a JSON line and waits for a line on stdin: 'reached' (or {\"reached\":true}),\n"
      "  'skip' or 'abort'.\n" +
      target_spec_help());
  CLI::Option* images = cmd->add_option("--images", o->images, "calibrate from this folder")
                            ->type_name("DIR")
                            ->check(non_empty());
  CLI::Option* camera = cmd->add_option("--camera", o->camera, "calibrate this camera live")
                            ->type_name("URI")
                            ->check(non_empty());
  images->excludes(camera);
  cmd->add_option("--out", o->out,
                  "write the calibration (.yml, .yaml, .json, .xml or .cameramodel)")
      ->type_name("FILE");
  add_format_option(cmd, &o->format);
  add_json_flag(cmd, &o->json, "print JSON (--camera: one event per line, then the result)");
  add_images_options(cmd, o.get());
  add_camera_options(cmd, o.get());
  o->session = std::make_unique<SessionFlags>(cmd);
  return [o] { return run_calibrate(*o); };
}

}  // namespace posecal::cli
