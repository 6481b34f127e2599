// posecal command line. Built on the C ABI only (posecal.h), so every command also exercises
// the interface that factory software uses.
#include <algorithm>
#include <cctype>
#include <chrono>
#include <cstdio>
#include <cstring>
#include <functional>
#include <map>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "posecal.h"

namespace {

using Json = nlohmann::json;

struct UsageError {
  std::string message;
};

// Parsed "--key value" / "--flag" arguments after the command name.
class Args {
 public:
  Args(int argc, char** argv, int first, const std::vector<std::string>& flags,
       const std::vector<std::string>& options) {
    for (int i = first; i < argc; ++i) {
      const std::string a = argv[i];
      if (a.rfind("--", 0) != 0) throw UsageError{"unexpected argument '" + a + "'"};
      const std::string key = a.substr(2);
      if (std::find(flags.begin(), flags.end(), key) != flags.end()) {
        flags_[key] = true;
      } else if (std::find(options.begin(), options.end(), key) != options.end()) {
        if (i + 1 >= argc) throw UsageError{"option '" + a + "' needs a value"};
        values_[key] = argv[++i];
      } else {
        throw UsageError{"unknown option '" + a + "'"};
      }
    }
  }
  bool flag(const std::string& k) const { return flags_.count(k) > 0; }
  bool has(const std::string& k) const { return values_.count(k) > 0; }
  std::string get(const std::string& k, const std::string& def = "") const {
    auto it = values_.find(k);
    return it == values_.end() ? def : it->second;
  }
  std::string need(const std::string& k) const {
    if (!has(k)) throw UsageError{"missing --" + k};
    return get(k);
  }
  double number(const std::string& k, double def) const {
    if (!has(k)) return def;
    try {
      size_t used = 0;
      const double v = std::stod(get(k), &used);
      if (used != get(k).size()) throw 0;
      return v;
    } catch (...) {
      throw UsageError{"--" + k + " expects a number, got '" + get(k) + "'"};
    }
  }

 private:
  std::map<std::string, bool> flags_;
  std::map<std::string, std::string> values_;
};

// A failed ABI call: the status and the library's message.
struct Failure {
  posecal_status status;
  std::string message;
};

void check(posecal_status s) {
  if (s != POSECAL_OK) throw Failure{s, posecal_last_error()};
}

// Calls a JSON-returning ABI function with the size-query protocol.
std::string fetch_json(const std::function<posecal_status(char*, size_t*)>& call) {
  size_t size = 0;
  posecal_status s = call(nullptr, &size);
  if (s != POSECAL_E_BUFFER_TOO_SMALL) check(s);
  std::string buf(size, '\0');
  check(call(buf.data(), &size));
  buf.resize(size - 1);
  return buf;
}

struct Context {
  posecal_context* ctx = nullptr;
  Context() { check(posecal_context_create(nullptr, &ctx)); }
  ~Context() { posecal_context_destroy(ctx); }
};

void print_usage() {
  std::fputs(
      "usage: posecal <command> [options]\n"
      "\n"
      "commands:\n"
      "  calibrate --images DIR [--target SPEC] [--out FILE] [--json]\n"
      "            [--fix-principal-point] [--fix-aspect-ratio] [--zero-tangential]\n"
      "      calibrate from a folder of images (name order); FILE is .yml/.yaml/.json\n"
      "  calibrate --camera URI [--target SPEC] [--out FILE] [--json] [--guide overlay|stdio]\n"
      "      live calibration with pose selection; --json prints one JSON event per line;\n"
      "      --guide stdio: robot mode, prints each target pose as a JSON line and waits for a\n"
      "      line on stdin saying the robot reached it\n"
      "  simulate [--camera-model FILE] [--seed N] [--operator person|robot] [--noise GREY]\n"
      "           [--blur PX] [--out FILE] [--json] [--events]\n"
      "      full closed-loop calibration on a synthetic camera (default: sampled around a C525)\n"
      "  board --out FILE [--target SPEC] [--dpi N] [--margin M]\n"
      "      write the printable target at exact scale (.pdf vector, .png at DPI)\n"
      "  list [--json]\n"
      "      list the cameras of every backend\n"
      "  version\n"
      "\n"
      "SPEC: charuco:COLSxROWS:SQUARE_M:MARKER_M:DICT (default "
      "charuco:9x6:0.028:0.0182:DICT_4X4_50)\n"
      "      chessboard:COLSxROWS:SQUARE_M (inner corners), e.g. chessboard:9x6:0.025\n",
      stderr);
}

// RAII for a session handle.
struct Session {
  posecal_session* s = nullptr;
  ~Session() { posecal_session_close(s); }
};

std::string percent_encode(const std::string& in) {
  std::string out;
  for (unsigned char c : in) {
    if (std::isalnum(c) || c == '/' || c == '.' || c == '_' || c == '-' || c == '~') {
      out.push_back(static_cast<char>(c));
    } else {
      char buf[4];
      std::snprintf(buf, sizeof buf, "%%%02X", c);
      out += buf;
    }
  }
  return out;
}

Json fetch_status(posecal_session* s) {
  return Json::parse(fetch_json([&](char* b, size_t* n) { return posecal_session_status(s, b, n); }));
}

Json fetch_result(posecal_session* s) {
  return Json::parse(fetch_json([&](char* b, size_t* n) { return posecal_session_result(s, b, n); }));
}

void print_event_line(void* user, const char* kind, const char* payload) {
  auto* out = static_cast<FILE*>(user);
  Json j = Json::parse(payload);
  j["event"] = kind;
  std::fprintf(out, "%s\n", j.dump().c_str());
  std::fflush(out);
}

Json session_config(const Args& args) {
  Json cfg = Json::object();
  if (args.has("target")) cfg["target"] = args.get("target");
  if (args.has("threshold")) cfg["convergence_threshold"] = args.number("threshold", 0.1);
  if (args.has("max-keyframes")) cfg["max_keyframes"] = static_cast<int>(args.number("max-keyframes", 20));
  if (args.has("candidates")) cfg["pose_candidates"] = static_cast<int>(args.number("candidates", 1));
  return cfg;
}

// The summary every calibration command prints with --json.
Json summary(const Json& result, double wall_ms) {
  Json j;
  j["converged"] = result.value("converged", false);
  j["state"] = result.value("state", "");
  j["keyframes"] = result.value("keyframes", 0);
  j["frames_processed"] = result.value("frames_processed", 0);
  for (const char* k : {"fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"}) j[k] = result[k];
  j["std"] = result["std"];
  j["eps_res"] = result["eps_res"];
  for (const char* k : {"eps_test", "eps_gt", "ground_truth", "operator_attempts", "failure"}) {
    if (result.contains(k)) j[k] = result[k];
  }
  j["camera"] = result["camera"];
  j["wall_ms"] = wall_ms;
  return j;
}

int cmd_simulate(const Args& args) {
  std::string uri = "sim://?seed=" + std::to_string(static_cast<long long>(args.number("seed", 1)));
  const std::string op = args.get("operator", "person");
  if (op != "person" && op != "robot") throw UsageError{"--operator must be person or robot"};
  uri += "&operator=" + op;
  if (args.has("noise")) uri += "&noise=" + args.get("noise");
  if (args.has("blur")) uri += "&blur=" + args.get("blur");
  if (args.has("camera-model")) uri += "&model=" + percent_encode(args.get("camera-model"));
  const int max_frames = static_cast<int>(args.number("max-frames", 5000));
  const auto t0 = std::chrono::steady_clock::now();
  Context c;
  Session s;
  check(posecal_session_open(c.ctx, uri.c_str(), session_config(args).dump().c_str(), &s.s));
  if (args.flag("events")) check(posecal_session_set_callback(s.s, print_event_line, stderr));
  int frames = 0;
  for (; frames < max_frames; ++frames) {
    const posecal_status st = posecal_session_step(s.s, 1000);
    if (st == POSECAL_E_STATE) break;  // finished
    check(st);
  }
  const double wall_ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
  if (args.has("out")) check(posecal_session_save(s.s, args.get("out").c_str()));
  const Json result = fetch_result(s.s);
  const Json j = summary(result, wall_ms);
  if (args.flag("json")) {
    std::printf("%s\n", j.dump().c_str());
  } else {
    std::printf("%s after %d keyframes (%d frames, %.1f s); eps_res %.3f px, eps_test %.3f px, eps_gt %.3f px\n",
                j["converged"].get<bool>() ? "converged" : "NOT converged", j["keyframes"].get<int>(),
                j["frames_processed"].get<int>(), wall_ms / 1000.0, j["eps_res"].get<double>(),
                j["eps_test"].is_number() ? j["eps_test"].get<double>() : -1.0,
                j["eps_gt"].is_number() ? j["eps_gt"].get<double>() : -1.0);
    for (const char* k : {"fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"}) {
      std::printf("  %-3s = %14.6f  +- %.6f   (true %.6f)\n", k, j[k].get<double>(), j["std"][k].get<double>(),
                  j["ground_truth"][k].get<double>());
    }
    if (args.has("out")) std::printf("written %s\n", args.get("out").c_str());
  }
  return j["converged"].get<bool>() ? 0 : 3;
}

int cmd_calibrate_camera(const Args& args) {
  Context c;
  Session s;
  Json cfg = session_config(args);
  const std::string guide = args.get("guide", "overlay");
  if (guide != "overlay" && guide != "stdio") throw UsageError{"--guide must be overlay or stdio"};
  if (guide == "stdio") cfg["operator"] = "robot";
  check(posecal_session_open(c.ctx, args.get("camera").c_str(), cfg.dump().c_str(), &s.s));
  // Events go to stdout as JSON lines with --json.
  if (args.flag("json")) check(posecal_session_set_callback(s.s, print_event_line, stdout));
  const int timeout_ms = static_cast<int>(args.number("timeout-ms", 2000));
  const double max_seconds = args.number("max-seconds", 1800);
  const auto t0 = std::chrono::steady_clock::now();
  std::vector<double> last_target;
  int timeouts = 0;
  while (true) {
    const double elapsed = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    if (elapsed > max_seconds) {
      std::fprintf(stderr, "posecal calibrate: stopped after %.0f s without converging\n", elapsed);
      break;
    }
    const posecal_status st = posecal_session_step(s.s, timeout_ms);
    if (st == POSECAL_E_STATE || st == POSECAL_E_NOT_FOUND) break;  // finished / end of images
    if (st == POSECAL_E_TIMEOUT || st == POSECAL_E_DEVICE) {
      if (++timeouts % 5 == 1) std::fprintf(stderr, "posecal calibrate: %s\n", posecal_last_error());
      continue;
    }
    check(st);
    timeouts = 0;
    if (guide == "stdio") {
      // Robot protocol: print each new target as a JSON line, wait for the controller's line.
      double r[3], t[3];
      if (posecal_session_target_pose(s.s, r, t) == POSECAL_OK) {
        const std::vector<double> now{r[0], r[1], r[2], t[0], t[1], t[2]};
        if (now != last_target) {
          last_target = now;
          Json line = {{"event", "target"}, {"rvec", {r[0], r[1], r[2]}}, {"tvec", {t[0], t[1], t[2]}},
                       {"status", fetch_status(s.s)}};
          std::printf("%s\n", line.dump().c_str());
          std::fflush(stdout);
          char buf[4096];
          if (!std::fgets(buf, sizeof buf, stdin)) throw UsageError{"--guide stdio: controller closed stdin"};
          check(posecal_session_pose_reached(s.s));
        }
      }
    }
  }
  const double wall_ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
  size_t probe = 0;
  if (posecal_session_result(s.s, nullptr, &probe) == POSECAL_E_STATE) {
    throw Failure{POSECAL_E_STATE, "no calibration: fewer than two keyframes were captured"};
  }
  const Json result = fetch_result(s.s);
  if (args.has("out")) check(posecal_session_save(s.s, args.get("out").c_str()));
  const Json j = summary(result, wall_ms);
  if (args.flag("json")) {
    Json line = j;
    line["event"] = "result";
    std::printf("%s\n", line.dump().c_str());
  } else {
    std::printf("%s after %d keyframes; eps_res %.3f px\n", j["converged"].get<bool>() ? "converged" : "NOT converged",
                j["keyframes"].get<int>(), j["eps_res"].get<double>());
    if (args.has("out")) std::printf("written %s\n", args.get("out").c_str());
  }
  return j["converged"].get<bool>() ? 0 : 3;
}

int cmd_calibrate(const Args& args) {
  if (args.has("camera") && args.has("images")) throw UsageError{"use either --camera or --images"};
  if (args.has("camera")) return cmd_calibrate_camera(args);
  if (!args.has("images")) throw UsageError{"calibrate needs --camera URI or --images DIR"};
  Context c;
  Json opts = Json::object();
  if (args.flag("fix-principal-point")) opts["fix_principal_point"] = true;
  if (args.flag("fix-aspect-ratio")) opts["fix_aspect_ratio"] = true;
  if (args.flag("zero-tangential")) opts["zero_tangential"] = true;
  const std::string target = args.get("target");
  posecal_calibration* cal = nullptr;
  check(posecal_calibrate_images(c.ctx, args.get("images").c_str(),
                                 target.empty() ? nullptr : target.c_str(), opts.dump().c_str(),
                                 &cal));
  struct Guard {
    posecal_calibration* p;
    ~Guard() { posecal_calibration_destroy(p); }
  } guard{cal};
  if (args.has("out")) check(posecal_calibration_save(cal, args.get("out").c_str()));
  const Json j = Json::parse(
      fetch_json([&](char* b, size_t* s) { return posecal_calibration_json(cal, b, s); }));
  if (args.flag("json")) {
    std::printf("%s\n", j.dump().c_str());
    return 0;
  }
  std::printf("calibrated from %zu image(s), %zu rejected; RMS %.4f px\n", j["used"].size(),
              j["rejected"].size(), j["rms"].is_number() ? j["rms"].get<double>() : -1.0);
  for (const auto& name : j["covariance_order"]) {
    const std::string n = name.get<std::string>();
    std::printf("  %-3s = %14.6f  +- %.6f\n", n.c_str(), j[n].get<double>(),
                j["std"][n].is_number() ? j["std"][n].get<double>() : -1.0);
  }
  for (const auto& r : j["rejected"]) {
    std::printf("  rejected %s: %s\n", r["file"].get<std::string>().c_str(),
                r["reason"].get<std::string>().c_str());
  }
  if (args.has("out")) std::printf("written %s\n", args.get("out").c_str());
  return 0;
}

int cmd_board(const Args& args) {
  const std::string target = args.get("target");
  check(posecal_write_target(target.empty() ? nullptr : target.c_str(), args.need("out").c_str(),
                             args.number("dpi", 300), args.number("margin", 0.01)));
  std::printf("written %s\n", args.get("out").c_str());
  return 0;
}

int cmd_list(const Args& args) {
  Context c;
  const Json cams = Json::parse(
      fetch_json([&](char* b, size_t* s) { return posecal_list_cameras(c.ctx, b, s); }));
  if (args.flag("json")) {
    std::printf("%s\n", cams.dump().c_str());
    return 0;
  }
  if (cams.empty()) std::printf("no cameras found\n");
  for (const auto& d : cams) {
    std::printf("%-50s %s %s (serial %s, %s)\n", d["uri"].get<std::string>().c_str(),
                d["vendor"].get<std::string>().c_str(), d["model"].get<std::string>().c_str(),
                d["serial"].get<std::string>().c_str(), d["transport"].get<std::string>().c_str());
  }
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  if (argc < 2 || !std::strcmp(argv[1], "--help") || !std::strcmp(argv[1], "-h") ||
      !std::strcmp(argv[1], "help")) {
    print_usage();
    return argc < 2 ? 1 : 0;
  }
  if (posecal_abi_version() != POSECAL_ABI_VERSION) {
    std::fprintf(stderr, "posecal: library ABI %u does not match this program's %u\n",
                 posecal_abi_version(), POSECAL_ABI_VERSION);
    return 2;
  }
  const std::string cmd = argv[1];
  try {
    if (cmd == "calibrate") {
      return cmd_calibrate(Args(argc, argv, 2, {"json", "fix-principal-point", "fix-aspect-ratio", "zero-tangential"},
                                {"images", "target", "out", "camera", "guide", "timeout-ms", "max-seconds",
                                 "threshold", "max-keyframes", "candidates"}));
    }
    if (cmd == "simulate") {
      return cmd_simulate(Args(argc, argv, 2, {"json", "events"},
                               {"camera-model", "seed", "operator", "noise", "blur", "out", "target", "threshold",
                                "max-keyframes", "max-frames", "candidates"}));
    }
    if (cmd == "board")
      return cmd_board(Args(argc, argv, 2, {}, {"out", "target", "dpi", "margin"}));
    if (cmd == "list") return cmd_list(Args(argc, argv, 2, {"json"}, {}));
    if (cmd == "version") {
      std::printf("posecal %s (ABI %u)\n", posecal_version(), posecal_abi_version());
      return 0;
    }
    throw UsageError{"unknown command '" + cmd + "'"};
  } catch (const UsageError& e) {
    std::fprintf(stderr, "posecal %s: %s (see posecal --help)\n", cmd.c_str(), e.message.c_str());
    return 1;
  } catch (const Failure& f) {
    std::fprintf(stderr, "posecal %s: %s [%s]\n", cmd.c_str(), f.message.c_str(),
                 posecal_status_name(f.status));
    return 2;
  } catch (const std::exception& e) {
    std::fprintf(stderr, "posecal %s: %s\n", cmd.c_str(), e.what());
    return 2;
  }
}
