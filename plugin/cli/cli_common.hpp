// What every posecal command shares: exit codes and errors, ABI handles and the JSON size
// protocol, event and line output, the calibration summary, and small helpers.
#pragma once

#include <CLI/CLI.hpp>
#include <chrono>
#include <cstddef>
#include <cstdio>
#include <functional>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "posecal.h"

namespace posecal::cli {

using Json = nlohmann::json;
using Clock = std::chrono::steady_clock;

// 4: converged, but the result fails the quality specification (--spec).
enum Exit { kOk = 0, kUsage = 1, kFailure = 2, kNotConverged = 3, kSpecFailed = 4 };

// A usage error found after parsing (e.g. two options that exclude each other): exit code 1.
struct UsageError {
  std::string message;
};

// A failed ABI call (or a failure of the command itself): the status and the message.
struct Failure {
  posecal_status status;
  std::string message;
};

// Throws the ABI's last error for a failed call.
void check(posecal_status s);

// Calls a JSON-returning ABI function with the size protocol.
std::string fetch_json(const std::function<posecal_status(char*, size_t*)>& call);

Json fetch_status(posecal_session* s);
Json fetch_result(posecal_session* s);
// True once the session has a calibration (two keyframes or more).
bool has_result(posecal_session* s);

class Context {
 public:
  Context();
  ~Context();
  Context(const Context&) = delete;
  Context& operator=(const Context&) = delete;
  posecal_context* get() const { return ctx_; }

 private:
  posecal_context* ctx_ = nullptr;
};

class Session {
 public:
  // Opens `uri` with the session config `config` (a JSON object).
  Session(posecal_context* ctx, const std::string& uri, const Json& config);
  ~Session();
  Session(const Session&) = delete;
  Session& operator=(const Session&) = delete;
  posecal_session* get() const { return s_; }

 private:
  posecal_session* s_ = nullptr;
};

// Writes one JSON line and flushes. Event lines, protocol lines and the station's messages
// share stdout/stderr across threads: one line at a time. A line with an "event" key gets its
// timestamps (stamp_event).
void write_line(FILE* out, const Json& j);
// UTC wall time with milliseconds, ISO 8601: "2026-12-03T11:55:01.123Z".
std::string utc_iso8601_ms();
// Adds "time" (UTC, ISO 8601 with milliseconds) and "mono_ms" (a monotonic clock's
// milliseconds since the program started) to an event object; other JSON is left alone.
void stamp_event(Json* j);
// Prints a message line to stderr under the same lock as write_line.
void print_error_line(const std::string& text);
// Prints a text line to `out` under the same lock, flushed (progress lines of several threads).
void print_text_line(FILE* out, const std::string& text);

// Where a session's events go: one JSON line per event.
struct EventSink {
  FILE* out = stdout;
  std::string camera;  // added to each line when set (station)
};

// posecal_event_fn for an EventSink.
void print_event_line(void* user, const char* kind, const char* payload);

// The exit code of a finished calibration's summary or result: kNotConverged, kSpecFailed when
// it converged but its quality verdict is "fail", else kOk.
int calibration_exit_code(const Json& j);
// Text mode: the quality verdict line(s), if the result has a verdict.
void print_verdict(const Json& j);  // and the record's run id or note

// The summary every calibration command prints with --json; the intrinsics are the result's
// covariance_order (whatever the lens model's parameters are).
Json summary(const Json& result, double wall_ms);

// JSON text of `j` (indent < 0: one line). Text from outside (a URI, a camera's name) may be
// invalid UTF-8: it is replaced with U+FFFD, never a reason to lose the output.
std::string json_text(const Json& j, int indent = -1);

// Before any work: `path` (a result file with one of `extensions`) can be written. Throws
// UsageError for a wrong extension, Failure(POSECAL_E_IO) naming the cause otherwise.
void check_output_file(const std::string& path, const std::vector<std::string>& extensions);
// Writes `text` to `path` atomically (temporary file, fsync, rename); Failure(POSECAL_E_IO)
// naming the cause; the previous file is kept on failure.
void write_text_file(const std::string& path, const std::string& text);

// ---- Result files (--out FILE, --format NAME) ----
// The formats posecal_session_save_as writes: opencv, ros, mrcal, kalibr, halcon
// (docs/formats.md).
const std::vector<std::string>& result_formats();
// The extensions a result file may have: by extension when `format` is empty (.yml, .yaml, .json,
// .xml, .cameramodel), else those of the format (the first is the one the station uses).
std::vector<std::string> result_extensions(const std::string& format);
// Adds --format to a command that writes a result (an unknown name is a usage error naming it).
void add_format_option(CLI::App* cmd, std::string* format);
// The ABI's format argument: NULL for "" (by the file's extension).
const char* format_arg(const std::string& format);

// Flushes and closes stdout as coreutils' close_stdout does; false (with a message on stderr)
// if anything written to it was lost (a full disk, a closed pipe, /dev/full).
bool close_stdout();

// j[key] if it is a number, else `def`.
double num_or(const Json& j, const std::string& key, double def);
double ms_since(Clock::time_point t0);
std::string trim(const std::string& s);
// The comma-separated items of `text`, trimmed; empty items are dropped.
std::vector<std::string> split_list(const std::string& text);

// ---- CLI11 helpers ----

// Rejects an empty value (e.g. --camera ""), as the previous parser's "missing --camera" did.
const CLI::Validator& non_empty();
// A number in [lo, hi], inclusive. (CLI::Range prints its limits with std::to_string:
// "0.000001 to 0.999000" for the table's [1e-6, 0.999].)
CLI::Validator in_range(double lo, double hi);
// A limit as a person writes it: 1000000, 0.999, 1e-06.
std::string number_text(double v);
// The help text of --target's SPEC (the footer of the commands that take a board).
std::string target_spec_help();
// Adds the --json flag every command has.
void add_json_flag(CLI::App* cmd, bool* json, const std::string& what);

// A subcommand's runner: registered before parsing, bound to the options it parsed into, called
// after parsing succeeded.
using Command = std::function<int()>;

}  // namespace posecal::cli
