// posecal station: several cameras calibrated concurrently (one thread each); one result file
// per camera named by its identity, and DIR/summary.json.
#include <algorithm>
#include <cctype>
#include <filesystem>
#include <fstream>
#include <memory>
#include <mutex>
#include <set>
#include <thread>

#include "commands.hpp"
#include "common/run_id.hpp"
#include "interrupt.hpp"
#include "session_flags.hpp"

namespace posecal::cli {

namespace {

struct StationOptions {
  std::string cameras, out_dir, format = "yml";
  bool json = false, events = false, force = false;
  int timeout_ms = 2000;
  double max_seconds = 1800;
  std::unique_ptr<SessionFlags> session;
};

// A camera's outcome besides the exit codes: stopped by SIGINT / SIGTERM.
constexpr int kInterrupted = -1;

struct StationJob {
  std::string uri;
  std::string journal;  // DIR/journal/<URI as a file name>.journal
  Json outcome;  // filled by the job's thread
  int exit = kFailure;
};

// What the camera threads share: read-only but for the result file names, which are claimed
// under the mutex.
struct StationShared {
  posecal_context* ctx = nullptr;
  const StationOptions* options = nullptr;
  Json config;  // the session config, built once before any thread starts
  std::mutex names_mutex;
  std::set<std::string> names;
};

// A camera id as a file name: letters, digits, '.', '_' and '-'; anything else becomes '_'.
std::string sanitise_id(const std::string& id) {
  std::string out;
  for (unsigned char ch : id) {
    out.push_back(std::isalnum(ch) || ch == '.' || ch == '_' || ch == '-' ? static_cast<char>(ch)
                                                                          : '_');
  }
  while (!out.empty() && out.front() == '.') out.erase(out.begin());  // no hidden files
  return out.empty() ? "camera" : out;
}

// --format: an OpenCV extension (yml, yaml, json, xml) or a format name (result_formats()).
bool is_format_name(const std::string& format) {
  const auto& names = result_formats();
  return std::find(names.begin(), names.end(), format) != names.end();
}

std::string file_extension(const std::string& format) {
  return is_format_name(format) ? result_extensions(format).front() : "." + format;
}

// The result file is named by the camera's identity; two cameras with one id get suffixes.
std::string claim_file(StationShared* shared, const std::string& id) {
  std::string name = sanitise_id(id);
  {
    std::lock_guard<std::mutex> lock(shared->names_mutex);
    const std::string base = name;
    for (int i = 2; shared->names.count(name); ++i) name = base + "-" + std::to_string(i);
    shared->names.insert(name);
  }
  return shared->options->out_dir + "/" + name + file_extension(shared->options->format);
}

// Text mode: a line for each step a person watching the station follows (keyframes, states,
// parameters, the camera coming and going), prefixed by the camera's URI.
void print_progress_text(void* user, const char* kind, const char* payload) {
  const auto* sink = static_cast<const EventSink*>(user);
  const Json p = Json::parse(payload, nullptr, false);
  if (p.is_discarded()) return;
  const std::string k = kind;
  std::string what;
  if (k == "captured") {
    what = "keyframe " + std::to_string(p.value("keyframes", 0)) + " captured";
  } else if (k == "state_changed") {
    what = p.value("from", std::string("?")) + " -> " + p.value("to", std::string("?"));
  } else if (k == "parameter_converged") {
    what = p.value("parameter", std::string("?")) + " converged (" +
           std::to_string(p.value("keyframes", 0)) + " keyframes)";
  } else if (k == "camera_disconnected" || k == "camera_reconnected" || k == "error" ||
             k == "target_skipped" || k == "keyframe_rejected" || k == "parameter_reopened") {
    std::string name = k;
    std::replace(name.begin(), name.end(), '_', ' ');
    what = name + ": " + p.value("message", std::string());
  } else {
    return;
  }
  print_text_line(sink->out, sink->camera + ": " + what);
}

// Text mode, every kProgressEveryMs: where a camera is, also when no event comes (a camera that
// does not see the board).
constexpr double kProgressEveryMs = 10000;

void print_heartbeat(posecal_session* s, const std::string& uri, double elapsed_ms) {
  const Json st = fetch_status(s);
  char line[96];
  std::snprintf(line, sizeof line, "%.0f s: %lld frames, %lld keyframes, ", elapsed_ms / 1000,
                st.value("frames", 0LL), st.value("keyframes", 0LL));
  print_text_line(stdout, uri + ": " + line + st.value("state", std::string("?")) + ": " +
                              st.value("guidance", std::string()));
}

void step_until_done(posecal_session* s, const StationOptions& o, const std::string& uri,
                     Clock::time_point t0) {
  int failures = 0;
  double next_heartbeat_ms = kProgressEveryMs;
  while (ms_since(t0) < o.max_seconds * 1000) {
    if (!o.json && ms_since(t0) >= next_heartbeat_ms) {
      print_heartbeat(s, uri, ms_since(t0));
      next_heartbeat_ms += kProgressEveryMs;
    }
    if (interrupt_requested()) {
      check(posecal_session_interrupt(s));
      return;
    }
    const posecal_status st = posecal_session_step(s, o.timeout_ms);
    if (st == POSECAL_E_STATE || st == POSECAL_E_NOT_FOUND) break;
    if (st == POSECAL_E_TIMEOUT || st == POSECAL_E_DEVICE) {
      if (++failures % 5 == 1)
        print_error_line("posecal station: " + uri + ": " + posecal_last_error());
      continue;
    }
    check(st);
    failures = 0;
  }
}

// Calibrates one camera into job->outcome; throws Failure.
void calibrate_one(StationShared* shared, StationJob* job, Clock::time_point t0) {
  const StationOptions& o = *shared->options;
  Json& out = job->outcome;
  Json config = shared->config;
  config["journal"] = job->journal;
  // Every camera's run is recorded, by default in DIR/records.sqlite (core/records).
  if (!config.contains("records")) config["records"] = o.out_dir + "/records.sqlite";
  // A run the store could not take by its finish waits in DIR/records-spool for the next run.
  if (!config.contains("records_spool")) config["records_spool"] = o.out_dir + "/records-spool";
  Session s(shared->ctx, job->uri, config);
  const Json camera = fetch_status(s.get())["camera"];
  out["camera"] = camera;
  EventSink sink{o.events ? stderr : stdout, job->uri};
  if (o.events) {
    check(posecal_session_set_callback(s.get(), print_event_line, &sink));
  } else if (!o.json) {
    check(posecal_session_set_callback(s.get(), print_progress_text, &sink));
    print_text_line(stdout, job->uri + ": calibrating camera '" + camera.value("id", "") + "'");
  }
  step_until_done(s.get(), o, job->uri, t0);
  out["interrupted"] = interrupt_requested();
  if (!has_result(s.get())) {
    // Why the session ended without a calibration (e.g. board_timeout_s), if it says.
    const Json st = fetch_status(s.get());
    const std::string why = st.contains("failure") ? " (" + st["failure"].get<std::string>() + ")" : "";
    throw Failure{POSECAL_E_STATE, "no calibration: fewer than two keyframes were captured" +
                                       std::string(interrupt_requested() ? " before the interrupt" : "") +
                                       why};
  }
  const std::string file = claim_file(shared, camera.value("id", ""));
  const std::string& format = shared->options->format;
  check(posecal_session_save_as(s.get(), file.c_str(),
                                is_format_name(format) ? format.c_str() : nullptr));
  const Json result = fetch_result(s.get());
  out["converged"] = result.value("converged", false);
  out["interrupted"] = result.value("interrupted", false);
  for (const char* k : {"state", "keyframes", "frames_processed", "eps_res", "failure"}) {
    out[k] = result.value(k, Json());
  }
  out["eps_test"] = result.value("eps_test", Json());
  out["eps_gt"] = result.value("eps_gt", Json());
  out["journal"] = result.value("journal", Json());
  out["resumed_keyframes"] = result.value("resumed_keyframes", 0);
  out["resume_identical"] = result.value("resume_identical", Json());
  for (const char* k : {"run_id", "records", "records_note"}) out[k] = result.value(k, Json());
  for (const char* k : {"verdict", "verdict_reasons", "spec", "fleet"})
    if (result.contains(k)) out[k] = result[k];
  out["file"] = file;
  out["error"] = nullptr;
  job->exit = calibration_exit_code(out);
  if (out["interrupted"].get<bool>()) job->exit = kInterrupted;
}

// A camera's thread: its outcome, whatever happens (one failed camera does not end the others).
void run_station_camera(StationShared* shared, StationJob* job) {
  const auto t0 = Clock::now();
  Json& out = job->outcome;
  out["uri"] = job->uri;
  try {
    calibrate_one(shared, job, t0);
  } catch (const Failure& f) {
    out["converged"] = false;
    out["error"] = f.message;
    out["status"] = posecal_status_name(f.status);
    job->exit = out.value("interrupted", false) ? kInterrupted : kFailure;
  } catch (const std::exception& e) {
    out["converged"] = false;
    out["error"] = e.what();
    job->exit = kFailure;
  }
  out["wall_ms"] = ms_since(t0);
}

void print_station_text(const Json& sum, const std::string& sum_path) {
  for (const auto& o : sum["cameras"]) {
    if (!o["error"].is_null()) {
      std::printf("%-40s %s: %s\n", o["uri"].get<std::string>().c_str(),
                  o.value("interrupted", false) ? "INTERRUPTED" : "FAILED",
                  o["error"].get<std::string>().c_str());
      continue;
    }
    char eps_test[64] = "";
    if (o["eps_test"].is_number()) {
      std::snprintf(eps_test, sizeof eps_test, ", eps_test %.3f px", o["eps_test"].get<double>());
    }
    std::printf(
        "%-40s %s, %d keyframes, eps_res %.3f px%s -> %s\n", o["uri"].get<std::string>().c_str(),
        o.value("interrupted", false) ? "INTERRUPTED"
        : o["converged"].get<bool>()   ? "converged"
                                       : "NOT converged",
        o["keyframes"].get<int>(),
        num_or(o, "eps_res", -1), eps_test, o["file"].get<std::string>().c_str());
    if (o.contains("verdict")) {
      std::string reasons;
      for (const auto& r : o.value("verdict_reasons", Json::array()))
        if (r.is_string()) reasons += "; " + r.get<std::string>();
      std::printf("%-40s quality spec: %s%s\n", "", o.value("verdict", "") == "pass" ? "PASS" : "FAIL",
                  reasons.c_str());
    }
    // The fleet outlier test, where it could be made (enough passed units in the records).
    const Json fleet = o.value("fleet", Json());
    if (fleet.is_object() && fleet.contains("outlier") && fleet["outlier"].is_boolean() &&
        fleet["outlier"].get<bool>()) {
      const Json dev = fleet.value("deviations", Json::array());
      // Either test flags (records/fleet.hpp): the distance and the parameter most off, each
      // against its bound.
      char most[96] = "";
      if (!dev.empty() && dev[0].is_object()) {
        std::snprintf(most, sizeof most, ", most off: %s z %+.1f (bound %.2f)",
                      dev[0].value("param", std::string("?")).c_str(), num_or(dev[0], "z", 0),
                      num_or(fleet, "parameter_threshold", -1));
      }
      std::printf("%-40s FLEET OUTLIER: distance %.2f (bound %.2f; %d units)%s\n", "",
                  num_or(fleet, "distance", -1), num_or(fleet, "threshold", -1),
                  fleet.value("units", 0), most);
    }
  }
  std::printf("%d of %d cameras converged in %.1f s%s; summary in %s\n",
              sum["converged"].get<int>(), sum["total"].get<int>(),
              sum["wall_ms"].get<double>() / 1000,
              sum["interrupted"].get<int>() > 0
                  ? (", " + std::to_string(sum["interrupted"].get<int>()) + " interrupted").c_str()
                  : "",
              sum_path.c_str());
}

// Runs every camera on its own thread; the summary of all of them.
Json run_cameras(const StationOptions& o, const std::vector<std::string>& uris, int* exit) {
  Context c;
  StationShared shared;
  shared.ctx = c.get();
  shared.options = &o;
  shared.config = o.session->config();
  std::vector<StationJob> jobs(uris.size());
  const auto t0 = Clock::now();
  {
    std::vector<std::thread> threads;
    // One journal per camera, named by its URI (a URI given twice gets -2, -3, ...): the same
    // command run again resumes each camera.
    std::set<std::string> journals;
    for (size_t i = 0; i < uris.size(); ++i) {
      std::string name = sanitise_id(uris[i]);
      for (int k = 2; journals.count(name); ++k) name = sanitise_id(uris[i]) + "-" + std::to_string(k);
      journals.insert(name);
      jobs[i].journal = o.out_dir + "/journal/" + name + ".journal";
    }
    for (size_t i = 0; i < uris.size(); ++i) {
      jobs[i].uri = uris[i];
      threads.emplace_back(run_station_camera, &shared, &jobs[i]);
    }
    for (auto& t : threads) t.join();
  }
  Json cams = Json::array();
  int converged = 0, interrupted = 0, passed = 0, judged = 0, outliers = 0;
  *exit = kOk;
  for (const auto& j : jobs) {
    cams.push_back(j.outcome);
    if (j.exit == kOk || j.exit == kSpecFailed) ++converged;
    if (j.exit == kInterrupted) ++interrupted;
    if (j.exit == kFailure) *exit = kFailure;  // a failed camera outweighs unconverged ones
    if (j.exit == kNotConverged && (*exit == kOk || *exit == kSpecFailed)) *exit = kNotConverged;
    if (j.exit == kSpecFailed && *exit == kOk) *exit = kSpecFailed;
    if (j.outcome.value("verdict", "") == "pass") ++passed;
    if (j.outcome.contains("verdict")) ++judged;
    const Json fleet = j.outcome.value("fleet", Json());
    if (fleet.is_object() && fleet.value("outlier", Json()) == Json(true)) ++outliers;
  }
  return {{"cameras", cams},
          {"total", jobs.size()},
          {"converged", converged},
          {"all_converged", converged == static_cast<int>(jobs.size())},
          {"interrupted", interrupted},
          {"out_dir", o.out_dir},
          // With a quality spec: the cameras whose result passed it (null without one).
          {"passed", judged > 0 ? Json(passed) : Json(nullptr)},
          // Cameras flagged by the fleet outlier test (records/fleet.hpp; each camera's "fleet").
          {"fleet_outliers", outliers},
          {"wall_ms", ms_since(t0)}};
}

// The summary of the run DIR holds, if it is one (absent, unreadable or not a summary: null).
Json previous_summary(const std::string& path) {
  std::error_code ec;
  if (!std::filesystem::is_regular_file(path, ec)) return nullptr;  // (a directory there: the
  try {                                                              // output check says so)
    std::ifstream in(path);
    const Json j = Json::parse(in, nullptr, false);
    return j.is_object() && j.contains("cameras") && j["cameras"].is_array() ? j : Json(nullptr);
  } catch (const std::exception&) {
    return nullptr;  // unreadable: not a run to protect
  }
}

// A station run's directory holds one run. A finished one (its summary, nothing interrupted) is
// not calibrated over without --force; an interrupted or killed one is resumed (the journals).
// --force removes the finished run's result files and journals first, so that no file of it
// is left beside the new run's (the records database keeps every run).
void claim_directory(const StationOptions& o, const std::string& sum_path) {
  const Json previous = previous_summary(sum_path);
  if (previous.is_null() || previous.value("interrupted", 0) > 0) return;
  if (!o.force) {
    throw UsageError{"'" + o.out_dir + "' holds a finished station run (" +
                     previous.value("station_run_id", std::string("summary.json")) +
                     ", finished " + previous.value("finished", std::string("earlier")) +
                     "): --force calibrates again into it (its result files and journals are "
                     "replaced; the records are kept), or choose another --out-dir"};
  }
  std::error_code ec;
  const auto dir = std::filesystem::weakly_canonical(o.out_dir, ec);
  for (const Json& cam : previous["cameras"]) {
    if (!cam.contains("file") || !cam["file"].is_string()) continue;
    const auto file = std::filesystem::weakly_canonical(cam["file"].get<std::string>(), ec);
    if (!ec && file.parent_path() == dir) std::filesystem::remove(file, ec);  // only its own
  }
  std::filesystem::remove_all(o.out_dir + "/journal", ec);
}

int run_station(const StationOptions& o) {
  const std::vector<std::string> uris = split_list(o.cameras);
  if (uris.empty()) throw UsageError{"--cameras needs at least one URI"};
  std::error_code ec;
  std::filesystem::create_directories(o.out_dir, ec);
  if (ec || !std::filesystem::is_directory(o.out_dir)) {
    throw Failure{POSECAL_E_IO, "cannot create directory '" + o.out_dir + "'" +
                                    (ec ? ": " + ec.message() : std::string())};
  }
  if (o.session->config().contains("journal")) {
    throw UsageError{"station keeps one journal per camera in DIR/journal/; --journal is for one camera"};
  }
  if (o.session->config().contains("run_id")) {
    throw UsageError{"station gives each camera a run id of its own; --run-id is for one camera"};
  }
  const std::string sum_path = o.out_dir + "/summary.json";
  claim_directory(o, sum_path);
  std::filesystem::create_directories(o.out_dir + "/journal", ec);
  check_output_file(sum_path, {".json"});  // before any camera is calibrated
  int exit = kOk;
  const std::string started = utc_iso8601_ms();
  Json sum = run_cameras(o, uris, &exit);
  // The run's own id and times; the records of its cameras carry their own run ids.
  sum["station_run_id"] = new_run_id();
  sum["started"] = started;
  sum["finished"] = utc_iso8601_ms();
  sum["posecal_version"] = posecal_version();
  sum["station_id"] = o.session->config().value("station_id", Json());
  Json interrupted_cameras = Json::array();
  for (const Json& cam : sum["cameras"])
    if (cam.value("interrupted", false)) interrupted_cameras.push_back(cam.value("uri", ""));
  sum["interrupted_cameras"] = interrupted_cameras;
  try {
    write_text_file(sum_path, json_text(sum, 2) + "\n");
  } catch (const Failure& f) {
    print_error_line("posecal station: " + f.message + " [" + posecal_status_name(f.status) + "]");
    exit = kFailure;
  }
  if (interrupt_requested()) exit = interrupt_exit_code();
  if (o.json) {
    std::printf("%s\n", json_text(sum).c_str());
  } else {
    print_station_text(sum, sum_path);
  }
  return exit;
}

}  // namespace

Command add_station(CLI::App* app) {
  auto o = std::make_shared<StationOptions>();
  CLI::App* cmd =
      app->add_subcommand("station", "calibrate several cameras concurrently (one thread each)");
  cmd->footer(
      "Writes DIR/<camera id>.<format> per camera and DIR/summary.json; keeps each\n"
      "camera's journal in DIR/journal/ (the same command again resumes an interrupted\n"
      "or killed run; a finished one is calibrated over only with --force) and every\n"
      "camera's record in DIR/records.sqlite (--records for another store, e.g. a\n"
      "postgresql:// URL; a run the store was away for waits in DIR/records-spool and\n"
      "is written into it by a later run).\n" +
      target_spec_help());
  cmd->add_option("--cameras", o->cameras, "the cameras")
      ->type_name("URI,URI,...")
      ->required()
      ->check(non_empty());
  cmd->add_option("--out-dir", o->out_dir, "the folder of the results (created if needed)")
      ->type_name("DIR")
      ->required()
      ->check(non_empty());
  std::vector<std::string> formats = {"yml", "yaml", "json", "xml"};
  formats.insert(formats.end(), result_formats().begin(), result_formats().end());
  cmd->add_option("--format", o->format,
                  "result file format: an OpenCV file's extension or a format name (ros: .yaml, "
                  "mrcal: .cameramodel, kalibr: .yaml, halcon: .dat; default: yml)")
      ->check(CLI::IsMember(formats));
  cmd->add_option("--timeout-ms", o->timeout_ms,
                  "wait for a frame at most this long (default: 2000)")
      ->check(in_range(0, 600000));
  cmd->add_option("--max-seconds", o->max_seconds,
                  "give up on a camera after this long (default: 1800)")
      ->check(CLI::NonNegativeNumber);
  add_json_flag(cmd, &o->json, "print the summary as one JSON object");
  cmd->add_flag("--force", o->force,
                "calibrate again into a directory that holds a finished run (its result files "
                "and journals are replaced; the records are kept)");
  cmd->add_flag("--events", o->events,
                "print every session's events as JSON lines on stderr (with \"camera\")");
  o->session = std::make_unique<SessionFlags>(cmd);
  return [o] { return run_station(*o); };
}

}  // namespace posecal::cli
