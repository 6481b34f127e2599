#include "cli_common.hpp"

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <ctime>
#include <mutex>

#include "common/atomic_file.hpp"

namespace posecal::cli {

namespace {

// stdout and stderr carry lines from several threads (station) and from the event callback.
std::mutex g_out_mutex;

// The clock every event's "mono_ms" counts from: the first use, early in main.
const std::chrono::steady_clock::time_point g_start = std::chrono::steady_clock::now();


}  // namespace

std::string utc_iso8601_ms() {
  const auto now = std::chrono::system_clock::now();
  const auto ms = std::chrono::duration_cast<std::chrono::milliseconds>(now.time_since_epoch());
  const std::time_t seconds = static_cast<std::time_t>(ms.count() / 1000);
  std::tm tm{};
  gmtime_r(&seconds, &tm);
  char buf[96];  // room for any int in each field, so the compiler sees no truncation
  std::snprintf(buf, sizeof buf, "%04d-%02d-%02dT%02d:%02d:%02d.%03dZ", tm.tm_year + 1900,
                tm.tm_mon + 1, tm.tm_mday, tm.tm_hour, tm.tm_min, tm.tm_sec,
                static_cast<int>(ms.count() % 1000));
  return buf;
}

void stamp_event(Json* j) {
  if (!j->is_object() || !j->contains("event")) return;
  (*j)["time"] = utc_iso8601_ms();
  (*j)["mono_ms"] = std::chrono::duration_cast<std::chrono::milliseconds>(
                        std::chrono::steady_clock::now() - g_start)
                        .count();
}

void check(posecal_status s) {
  if (s != POSECAL_OK) throw Failure{s, posecal_last_error()};
}

std::string fetch_json(const std::function<posecal_status(char*, size_t*)>& call) {
  // A first guess of 64 KiB saves the second call almost always.
  std::string buf(65536, '\0');
  size_t size = buf.size();
  posecal_status s = call(buf.data(), &size);
  if (s == POSECAL_E_BUFFER_TOO_SMALL) {
    buf.assign(size, '\0');
    s = call(buf.data(), &size);
  }
  check(s);
  buf.resize(size - 1);
  return buf;
}

Json fetch_status(posecal_session* s) {
  return Json::parse(
      fetch_json([&](char* b, size_t* n) { return posecal_session_status(s, b, n); }));
}

Json fetch_result(posecal_session* s) {
  return Json::parse(
      fetch_json([&](char* b, size_t* n) { return posecal_session_result(s, b, n); }));
}

bool has_result(posecal_session* s) {
  size_t probe = 0;
  return posecal_session_result(s, nullptr, &probe) != POSECAL_E_STATE;
}

Context::Context() { check(posecal_context_create(nullptr, &ctx_)); }

Context::~Context() { posecal_context_destroy(ctx_); }

Session::Session(posecal_context* ctx, const std::string& uri, const Json& config) {
  check(posecal_session_open(ctx, uri.c_str(), json_text(config).c_str(), &s_));
}

Session::~Session() { posecal_session_close(s_); }

void write_line(FILE* out, const Json& j) {
  Json line = j;
  stamp_event(&line);
  std::lock_guard<std::mutex> lock(g_out_mutex);
  std::fprintf(out, "%s\n", json_text(line).c_str());
  std::fflush(out);
}

void print_error_line(const std::string& text) { print_text_line(stderr, text); }

void print_text_line(FILE* out, const std::string& text) {
  std::lock_guard<std::mutex> lock(g_out_mutex);
  std::fprintf(out, "%s\n", text.c_str());
  std::fflush(out);
}

void print_event_line(void* user, const char* kind, const char* payload) {
  const auto* sink = static_cast<const EventSink*>(user);
  Json j = Json::parse(payload, nullptr, false);
  if (j.is_discarded()) j = Json{{"payload", payload}};
  j["event"] = kind;
  if (!sink->camera.empty()) j["camera"] = sink->camera;
  write_line(sink->out, j);
}

std::string json_text(const Json& j, int indent) {
  return j.dump(indent, ' ', false, Json::error_handler_t::replace);
}

void check_output_file(const std::string& path, const std::vector<std::string>& extensions) {
  const bool known = std::any_of(extensions.begin(), extensions.end(), [&](const std::string& e) {
    return path.size() > e.size() && path.compare(path.size() - e.size(), e.size(), e) == 0;
  });
  if (!known) {
    std::string list;
    for (const auto& e : extensions) list += (list.empty() ? "" : ", ") + e;
    throw UsageError{"output file '" + path + "': use " + list};
  }
  std::string error;
  if (!check_output_path(path, &error)) throw Failure{POSECAL_E_IO, error};
}

const std::vector<std::string>& result_formats() {
  static const std::vector<std::string> formats = {"opencv", "ros", "mrcal", "kalibr", "halcon"};
  return formats;
}

std::vector<std::string> result_extensions(const std::string& format) {
  if (format.empty()) return {".yml", ".yaml", ".json", ".xml", ".cameramodel"};
  if (format == "opencv") return {".yml", ".yaml", ".json", ".xml"};
  if (format == "mrcal") return {".cameramodel"};
  if (format == "halcon") return {".dat", ".cal"};
  return {".yaml", ".yml"};  // ros, kalibr: YAML
}

void add_format_option(CLI::App* cmd, std::string* format) {
  std::string names;
  for (const auto& f : result_formats()) names += (names.empty() ? "" : "|") + f;
  cmd->add_option("--format", *format,
                  "the result file's format (default: by --out's extension: .cameramodel mrcal, "
                  "else opencv)")
      ->type_name(names)
      ->check(CLI::IsMember(result_formats()));
}

const char* format_arg(const std::string& format) {
  return format.empty() ? nullptr : format.c_str();
}

void write_text_file(const std::string& path, const std::string& text) {
  std::string error;
  if (!write_file_atomic(path, text, &error)) throw Failure{POSECAL_E_IO, error};
}

bool close_stdout() {
  errno = 0;
  bool ok = std::fflush(stdout) == 0 && !std::ferror(stdout);
  int err = errno;
  if (std::fclose(stdout) != 0 && ok) {
    ok = false;
    err = errno;
  }
  if (!ok) {
    std::fprintf(stderr, "posecal: error writing standard output%s\n",
                 err ? (": " + errno_text(err)).c_str() : "");
  }
  return ok;
}

Json summary(const Json& result, double wall_ms) {
  Json j;
  j["converged"] = result.value("converged", false);
  j["interrupted"] = result.value("interrupted", false);
  j["state"] = result.value("state", "");
  j["keyframes"] = result.value("keyframes", 0);
  j["frames_processed"] = result.value("frames_processed", 0);
  const Json order = result.value("covariance_order", Json::array());
  for (const auto& name : order) {
    const std::string n = name.get<std::string>();
    j[n] = result.value(n, Json());
  }
  j["covariance_order"] = order;
  j["std"] = result.value("std", Json());
  j["eps_res"] = result.value("eps_res", Json());
  for (const char* k : {"expected_error_px", "expected_error_p90_px", "expected_error_unit_px", "expected_error_limited_by"}) {
    j[k] = result.value(k, Json());
  }
  for (const char* k : {"eps_test",
                        "eps_gt",
                        "eps_gt_aligned",
                        "ground_truth",
                        "operator_attempts",
                        "failure",
                        "journal",
                        "resumed_keyframes",
                        "resume_identical",
                        "journal_note",
                        "seconds",
                        "verdict",
                        "verdict_reasons",
                        "spec",
                        "records",
                        "run_id",
                        "records_note",
                        "fleet",
                        "prior",
                        "held",
                        "held_reason",
                        "lens_model_choice"}) {
    if (result.contains(k)) j[k] = result[k];
  }
  j["camera"] = result.value("camera", Json());
  j["wall_ms"] = wall_ms;
  return j;
}

int calibration_exit_code(const Json& j) {
  if (!j.value("converged", false)) return kNotConverged;
  return j.value("verdict", "") == "fail" ? kSpecFailed : kOk;
}

void print_verdict(const Json& j) {
  if (j.contains("verdict")) {
    std::printf("quality spec %s: %s\n", j.value("spec", std::string()).c_str(),
                j.value("verdict", "") == "pass" ? "PASS" : "FAIL");
    for (const auto& r : j.value("verdict_reasons", Json::array()))
      if (r.is_string()) std::printf("  %s\n", r.get<std::string>().c_str());
  }
  // The fleet prior (--prior fleet) and the fleet outlier test, where they ran.
  if (j.contains("prior") && j["prior"].is_object()) {
    const Json& p = j["prior"];
    if (p.value("used", false)) {
      std::printf("fleet prior: %d units, stop at %.3f px\n", p.value("units", 0),
                  p.value("accuracy_px", 0.0));
    } else {
      std::printf("no fleet prior: %s\n", p.value("note", std::string()).c_str());
    }
  }
  if (j.contains("fleet") && j["fleet"].is_object() &&
      j["fleet"].value("outlier", Json()).is_boolean() && j["fleet"]["outlier"].get<bool>()) {
    // Either test flags (records/fleet.hpp): the distance against its bound, the parameter
    // most off against the one-parameter bound.
    const Json& f = j["fleet"];
    const Json dev = f.value("deviations", Json::array());
    const bool named = !dev.empty() && dev[0].is_object() && dev[0].value("z", Json()).is_number();
    std::printf(
        "FLEET OUTLIER: distance %.2f (bound %.2f), %s z %+.1f (bound %.2f), among %d "
        "units\n",
        f.value("distance", 0.0), f.value("threshold", 0.0),
        named ? dev[0].value("param", std::string("?")).c_str() : "?",
        named ? dev[0]["z"].get<double>() : 0.0, f.value("parameter_threshold", 0.0),
        f.value("units", 0));
  }
  // The record (--records), where there is one to speak of.
  if (j.contains("records_note") && j["records_note"].is_string()) {
    std::printf("record: %s\n", j["records_note"].get<std::string>().c_str());
  } else if (j.contains("run_id") && j["run_id"].is_string()) {
    std::printf("recorded as run %s in %s\n", j["run_id"].get<std::string>().c_str(),
                j.value("records", std::string()).c_str());
  }
}

double num_or(const Json& j, const std::string& key, double def) {
  return j.is_object() && j.contains(key) && j[key].is_number() ? j[key].get<double>() : def;
}

double ms_since(Clock::time_point t0) {
  return std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
}

std::string trim(const std::string& s) {
  const size_t a = s.find_first_not_of(" \t");
  if (a == std::string::npos) return "";
  return s.substr(a, s.find_last_not_of(" \t") - a + 1);
}

std::vector<std::string> split_list(const std::string& text) {
  std::vector<std::string> out;
  size_t start = 0;
  while (start <= text.size()) {
    size_t end = text.find(',', start);
    if (end == std::string::npos) end = text.size();
    const std::string item = trim(text.substr(start, end - start));
    if (!item.empty()) out.push_back(item);
    start = end + 1;
  }
  return out;
}

const CLI::Validator& non_empty() {
  static const CLI::Validator v(
      [](std::string& s) { return s.empty() ? std::string("must not be empty") : std::string(); },
      "");
  return v;
}

std::string number_text(double v) {
  char buf[32];
  if (std::fabs(v) < 1e15 && v == std::trunc(v)) {
    std::snprintf(buf, sizeof buf, "%lld", static_cast<long long>(v));
  } else {
    std::snprintf(buf, sizeof buf, "%g", v);
  }
  return buf;
}

CLI::Validator in_range(double lo, double hi) {
  const std::string range = "[" + number_text(lo) + ", " + number_text(hi) + "]";
  return CLI::Validator(
      [lo, hi, range](std::string& s) {
        char* end = nullptr;
        const double v = std::strtod(s.c_str(), &end);
        if (s.empty() || *end != '\0' || std::isnan(v)) return "'" + s + "' is not a number";
        if (v < lo || v > hi) return s + " is outside " + range;
        return std::string();
      },
      "in " + range);
}

std::string target_spec_help() {
  return "SPEC: charuco:COLSxROWS:SQUARE_M:MARKER_M:DICT (default "
         "charuco:9x6:0.028:0.0182:DICT_4X4_50)\n"
         "      chessboard:COLSxROWS:SQUARE_M (inner corners), e.g. chessboard:9x6:0.025";
}

void add_json_flag(CLI::App* cmd, bool* json, const std::string& what) {
  cmd->add_flag("--json", *json, what);
}

}  // namespace posecal::cli
