// posecal command line. Built on the C ABI only (posecal.h), so every command also exercises
// the interface that factory software uses.
//
// Exit codes: 0 success, 1 usage error, 2 failure, 3 finished but not converged.
#include <netdb.h>
#include <poll.h>
#include <sys/socket.h>
#include <sys/un.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cctype>
#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstddef>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <functional>
#include <map>
#include <mutex>
#include <nlohmann/json.hpp>
#include <set>
#include <string>
#include <thread>
#include <vector>

#include "posecal.h"

#ifdef POSECAL_CLI_HIGHGUI
#include <opencv2/core.hpp>
#include <opencv2/highgui.hpp>
#endif

namespace {

using Json = nlohmann::json;
using Clock = std::chrono::steady_clock;

enum Exit { kOk = 0, kUsage = 1, kFailure = 2, kNotConverged = 3 };

struct UsageError {
  std::string message;
};

// A failed ABI call (or a failure of the command itself): the status and the message.
struct Failure {
  posecal_status status;
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
    if (!has(k) || get(k).empty()) throw UsageError{"missing --" + k};
    return get(k);
  }
  double number(const std::string& k, double def) const {
    if (!has(k)) return def;
    try {
      size_t used = 0;
      const double v = std::stod(get(k), &used);
      if (used == get(k).size()) return v;
    } catch (const std::exception&) {
    }
    throw UsageError{"--" + k + " expects a number, got '" + get(k) + "'"};
  }
  int integer(const std::string& k, int def, int lo, int hi) const {
    const double v = number(k, def);
    if (v != static_cast<double>(static_cast<long long>(v)) || v < lo || v > hi) {
      throw UsageError{"--" + k + " expects an integer in [" + std::to_string(lo) + ", " +
                       std::to_string(hi) + "]"};
    }
    return static_cast<int>(v);
  }

 private:
  std::map<std::string, bool> flags_;
  std::map<std::string, std::string> values_;
};

void check(posecal_status s) {
  if (s != POSECAL_OK) throw Failure{s, posecal_last_error()};
}

// Calls a JSON-returning ABI function with the size protocol (a first guess of 64 KiB saves the
// second call almost always).
std::string fetch_json(const std::function<posecal_status(char*, size_t*)>& call) {
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

struct Context {
  posecal_context* ctx = nullptr;
  Context() { check(posecal_context_create(nullptr, &ctx)); }
  ~Context() { posecal_context_destroy(ctx); }
  Context(const Context&) = delete;
  Context& operator=(const Context&) = delete;
};

// RAII for a session handle.
struct Session {
  posecal_session* s = nullptr;
  Session() = default;
  ~Session() { posecal_session_close(s); }
  Session(const Session&) = delete;
  Session& operator=(const Session&) = delete;
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
      "            [--no-window] [--timeout-ms MS] [--max-seconds S] [--reply-timeout-s S]\n"
      "      live calibration with pose selection; a window shows the camera and the target when\n"
      "      DISPLAY is set; --json prints one JSON event per line; --guide stdio: robot mode,\n"
      "      prints each target pose as a JSON line and waits for a line on stdin:\n"
      "      'reached' (or {\"reached\":true}), 'skip' or 'abort'\n"
      "  station --cameras URI,URI,... --out-dir DIR [--target SPEC] [--json] [--events]\n"
      "          [--format yml|json] [--max-seconds S] [--timeout-ms MS]\n"
      "      calibrate several cameras concurrently (one thread each); DIR/<camera id>.yml per\n"
      "      camera and DIR/summary.json\n"
      "  evaluate --result FILE --camera URI [--target SPEC] [--frames N] [--timeout-ms MS] "
      "[--json]\n"
      "      test-set error (eps_test; eps_gt for sim://) of an existing calibration file\n"
      "  grab --camera URI --count N --out DIR [--timeout-ms MS] [--json]\n"
      "      save N frames as PNG files\n"
      "  features --camera URI [--json]\n"
      "      list the camera's settings (GenICam features, V4L2 controls)\n"
      "  simulate [--camera-model FILE] [--seed N] [--operator person|robot] [--noise GREY]\n"
      "           [--blur PX] [--out FILE] [--json] [--events]\n"
      "      full closed-loop calibration on a synthetic camera (default: sampled around a C525)\n"
      "  board --out FILE [--target SPEC] [--dpi N] [--margin M]\n"
      "      write the printable target at exact scale (.pdf vector, .png at DPI)\n"
      "  list [--json]\n"
      "      list the cameras of every backend\n"
      "  version\n"
      "\n"
      "pose selection (calibrate --camera, station, simulate): [--threshold R (0.1)]\n"
      "      [--max-keyframes N (20)] [--candidates N (6)] [--target-timeout-frames N]\n"
      "      [--fix P,P,... e.g. k2,k3: held at their initial value, 0 for distortion]\n"
      "      [--measure variance|std (variance: the paper's ratio test)] [--prospective-only]\n"
      "      [--score projection|variance (how candidate poses are compared; projection: the\n"
      "       expected projection error over the image)]\n"
      "      [--views N (0: rule poses only; N random views of the whole board also compete)]\n"
      "      [--views-serve-target (a view must also help the targeted parameter)]\n"
      "\n"
      "SPEC: charuco:COLSxROWS:SQUARE_M:MARKER_M:DICT (default "
      "charuco:9x6:0.028:0.0182:DICT_4X4_50)\n"
      "      chessboard:COLSxROWS:SQUARE_M (inner corners), e.g. chessboard:9x6:0.025\n"
      "exit codes: 0 ok, 1 usage, 2 failure, 3 finished but not converged\n",
      stderr);
}

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

// stdout is shared by event lines and protocol lines: one line at a time.
std::mutex g_out_mutex;

void write_line(FILE* out, const Json& j) {
  std::lock_guard<std::mutex> lock(g_out_mutex);
  std::fprintf(out, "%s\n", j.dump().c_str());
  std::fflush(out);
}

struct EventSink {
  FILE* out = stdout;
  std::string camera;  // added to each line when set (station)
};

void print_event_line(void* user, const char* kind, const char* payload) {
  const auto* sink = static_cast<const EventSink*>(user);
  Json j = Json::parse(payload, nullptr, false);
  if (j.is_discarded()) j = Json{{"payload", payload}};
  j["event"] = kind;
  if (!sink->camera.empty()) j["camera"] = sink->camera;
  write_line(sink->out, j);
}

Json session_config(const Args& args) {
  Json cfg = Json::object();
  if (args.has("target")) cfg["target"] = args.get("target");
  if (args.has("threshold")) cfg["convergence_threshold"] = args.number("threshold", 0.1);
  if (args.has("max-keyframes")) cfg["max_keyframes"] = args.integer("max-keyframes", 20, 3, 1000);
  if (args.has("candidates")) cfg["pose_candidates"] = args.integer("candidates", 6, 1, 64);
  if (args.has("views")) cfg["view_candidates"] = args.integer("views", 0, 0, 4096);
  if (args.flag("views-serve-target")) cfg["view_must_serve_target"] = true;
  if (args.has("target-timeout-frames")) {
    cfg["target_timeout_frames"] = args.integer("target-timeout-frames", 0, 0, 1000000);
  }
  if (args.has("measure")) cfg["convergence_measure"] = args.get("measure");
  if (args.flag("prospective-only")) cfg["measured_convergence"] = false;
  if (args.has("score")) cfg["candidate_score"] = args.get("score");
  if (args.has("fix")) {
    // A comma-separated list; the library names an unknown parameter.
    Json names = Json::array();
    const std::string list = args.get("fix");
    size_t start = 0;
    while (start <= list.size()) {
      const size_t comma = std::min(list.find(',', start), list.size());
      const std::string name = list.substr(start, comma - start);
      if (name.empty()) throw UsageError{"--fix: empty parameter name in '" + list + "'"};
      names.push_back(name);
      start = comma + 1;
    }
    cfg["fixed"] = names;
  }
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

double num_or(const Json& j, const char* key, double def) {
  return j.contains(key) && j[key].is_number() ? j[key].get<double>() : def;
}

double ms_since(Clock::time_point t0) {
  return std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
}

int cmd_simulate(const Args& args) {
  std::string uri = "sim://?seed=" + std::to_string(args.integer("seed", 1, 0, 2000000000));
  const std::string op = args.get("operator", "person");
  if (op != "person" && op != "robot") throw UsageError{"--operator must be person or robot"};
  uri += "&operator=" + op;
  if (args.has("noise")) uri += "&noise=" + percent_encode(args.get("noise"));
  if (args.has("blur")) uri += "&blur=" + percent_encode(args.get("blur"));
  if (args.has("camera-model")) uri += "&model=" + percent_encode(args.get("camera-model"));
  const int max_frames = args.integer("max-frames", 5000, 1, 10000000);
  const auto t0 = Clock::now();
  Context c;
  Session s;
  check(posecal_session_open(c.ctx, uri.c_str(), session_config(args).dump().c_str(), &s.s));
  EventSink sink{stderr, ""};
  if (args.flag("events")) check(posecal_session_set_callback(s.s, print_event_line, &sink));
  for (int frames = 0; frames < max_frames; ++frames) {
    const posecal_status st = posecal_session_step(s.s, 1000);
    if (st == POSECAL_E_STATE) break;  // finished
    check(st);
  }
  const double wall_ms = ms_since(t0);
  if (!has_result(s.s)) throw Failure{POSECAL_E_STATE, "no calibration: fewer than two keyframes"};
  if (args.has("out")) check(posecal_session_save(s.s, args.get("out").c_str()));
  const Json result = fetch_result(s.s);
  const Json j = summary(result, wall_ms);
  if (args.flag("json")) {
    std::printf("%s\n", j.dump().c_str());
  } else {
    std::printf(
        "%s after %d keyframes (%d frames, %.1f s); eps_res %.3f px, eps_test %.3f px, eps_gt "
        "%.3f px\n",
        j["converged"].get<bool>() ? "converged" : "NOT converged", j["keyframes"].get<int>(),
        j["frames_processed"].get<int>(), wall_ms / 1000.0, num_or(j, "eps_res", -1),
        num_or(j, "eps_test", -1), num_or(j, "eps_gt", -1));
    for (const char* k : {"fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"}) {
      std::printf("  %-3s = %14.6f  +- %.6f   (true %.6f)\n", k, num_or(j, k, NAN),
                  num_or(j["std"], k, NAN), num_or(j["ground_truth"], k, NAN));
    }
    if (args.has("out")) std::printf("written %s\n", args.get("out").c_str());
  }
  return j["converged"].get<bool>() ? kOk : kNotConverged;
}

// ---- Robot protocol on stdin/stdout (--guide stdio) ------------------------------------------

// Reads lines from a file descriptor with a timeout (poll + read: no stdio buffering, so the
// wait is bounded).
class LineReader {
 public:
  explicit LineReader(int fd) : fd_(fd) {}
  enum class Result { kLine, kEof, kTimeout };
  Result next(std::string* line, int timeout_ms) {
    const auto deadline = Clock::now() + std::chrono::milliseconds(timeout_ms);
    while (true) {
      const size_t nl = buffer_.find('\n');
      if (nl != std::string::npos) {
        *line = buffer_.substr(0, nl);
        buffer_.erase(0, nl + 1);
        if (!line->empty() && line->back() == '\r') line->pop_back();
        return Result::kLine;
      }
      if (eof_) {
        if (buffer_.empty()) return Result::kEof;
        *line = std::move(buffer_);
        buffer_.clear();
        return Result::kLine;
      }
      const auto left =
          std::chrono::duration_cast<std::chrono::milliseconds>(deadline - Clock::now()).count();
      if (left <= 0) return Result::kTimeout;
      pollfd p{fd_, POLLIN, 0};
      const int r = ::poll(&p, 1, static_cast<int>(std::min<long long>(left, 1000000)));
      if (r < 0 && errno == EINTR) continue;
      if (r <= 0) continue;  // timeout re-checked above
      char buf[4096];
      const ssize_t n = ::read(fd_, buf, sizeof buf);
      if (n < 0 && errno == EINTR) continue;
      if (n <= 0) {
        eof_ = true;
        continue;
      }
      buffer_.append(buf, static_cast<size_t>(n));
      if (buffer_.size() > (1u << 20)) throw Failure{POSECAL_E_INVALID_ARGUMENT, "line too long"};
    }
  }

 private:
  int fd_;
  std::string buffer_;
  bool eof_ = false;
};

enum class Reply { kReached, kSkip, kAbort, kInvalid };

std::string trim(const std::string& s) {
  const size_t a = s.find_first_not_of(" \t");
  if (a == std::string::npos) return "";
  return s.substr(a, s.find_last_not_of(" \t") - a + 1);
}

Reply parse_reply(const std::string& raw) {
  const std::string line = trim(raw);
  if (line == "reached" || line == "ok") return Reply::kReached;
  if (line == "skip") return Reply::kSkip;
  if (line == "abort") return Reply::kAbort;
  const Json j = Json::parse(line, nullptr, false);
  if (!j.is_object()) return Reply::kInvalid;
  auto yes = [&](const char* k) { return j.contains(k) && j[k].is_boolean() && j[k].get<bool>(); };
  if (yes("reached")) return Reply::kReached;
  if (yes("skip")) return Reply::kSkip;
  if (yes("abort")) return Reply::kAbort;
  return Reply::kInvalid;
}

// ---- Live window (only with a display) ------------------------------------------------------

// True if an X server answers at `display` ("[host]:N[.S]"): a GUI toolkit that cannot open
// its display ends the process (Qt aborts), so the CLI looks before it leaps.
bool x_display_reachable(const std::string& display) {
  const size_t colon = display.rfind(':');
  if (colon == std::string::npos) return false;
  const std::string host = display.substr(0, colon);
  const int n = std::atoi(display.substr(colon + 1).c_str());
  auto connect_with_timeout = [](int fd, const sockaddr* addr, socklen_t len) {
    if (::connect(fd, addr, len) == 0) return true;
    if (errno != EINPROGRESS) return false;
    pollfd p{fd, POLLOUT, 0};
    int err = 0;
    socklen_t err_len = sizeof err;
    return ::poll(&p, 1, 500) == 1 && ::getsockopt(fd, SOL_SOCKET, SO_ERROR, &err, &err_len) == 0 &&
           err == 0;
  };
  if (host.empty() || host == "unix") {
    const std::string path = "/tmp/.X11-unix/X" + std::to_string(n);
    for (const bool abstract : {false, true}) {  // Linux X servers also listen on "@path"
      const int fd = ::socket(AF_UNIX, SOCK_STREAM | SOCK_NONBLOCK | SOCK_CLOEXEC, 0);
      if (fd < 0) return false;
      sockaddr_un addr{};
      addr.sun_family = AF_UNIX;
      std::memcpy(addr.sun_path + (abstract ? 1 : 0), path.c_str(), path.size());
      const socklen_t len = static_cast<socklen_t>(offsetof(sockaddr_un, sun_path) + path.size() +
                                                   (abstract ? 1 : 0));
      const bool ok = connect_with_timeout(fd, reinterpret_cast<const sockaddr*>(&addr), len);
      ::close(fd);
      if (ok) return true;
    }
    return false;
  }
  addrinfo hints{};
  hints.ai_socktype = SOCK_STREAM;
  addrinfo* res = nullptr;
  if (::getaddrinfo(host.c_str(), std::to_string(6000 + n).c_str(), &hints, &res) != 0)
    return false;
  bool ok = false;
  for (addrinfo* a = res; a && !ok; a = a->ai_next) {
    const int fd = ::socket(a->ai_family, a->ai_socktype | SOCK_NONBLOCK | SOCK_CLOEXEC, 0);
    if (fd < 0) continue;
    ok = connect_with_timeout(fd, a->ai_addr, a->ai_addrlen);
    ::close(fd);
  }
  ::freeaddrinfo(res);
  return ok;
}

class LiveWindow {
 public:
  // Opens nothing until the first frame; disabled without highgui, without DISPLAY, or when
  // no X server answers there. POSECAL_WINDOW=0 disables it, POSECAL_WINDOW=force skips the
  // display check (e.g. with QT_QPA_PLATFORM=offscreen).
  explicit LiveWindow(bool wanted) {
#ifdef POSECAL_CLI_HIGHGUI
    const char* display = std::getenv("DISPLAY");
    const char* mode = std::getenv("POSECAL_WINDOW");
    const std::string m = mode ? mode : "";
    if (!wanted || m == "0" || display == nullptr || display[0] == '\0') return;
    if (m != "force" && !x_display_reachable(display)) {
      std::fprintf(stderr, "posecal calibrate: no X server answers at DISPLAY=%s; headless\n",
                   display);
      return;
    }
    enabled_ = true;
#else
    (void)wanted;
#endif
  }
  ~LiveWindow() {
#ifdef POSECAL_CLI_HIGHGUI
    if (opened_) {
      try {
        cv::destroyAllWindows();
      } catch (...) {
      }
    }
#endif
  }
  bool enabled() const { return enabled_; }
  // Shows the last frame with the guidance overlay. Returns false when the user closed the
  // window or pressed q/Esc.
  bool show(posecal_session* s, const Json& status) {
#ifdef POSECAL_CLI_HIGHGUI
    if (!enabled_ || !status["image_width"].is_number()) return true;
    const int w = status["image_width"].get<int>(), h = status["image_height"].get<int>();
    pixels_.resize(static_cast<size_t>(w) * h * 3);
    posecal_image img{sizeof(posecal_image), w, h, w * 3, POSECAL_PIXEL_BGR8, pixels_.data()};
    if (posecal_session_last_frame(s, &img) != POSECAL_OK) return true;
    check(posecal_session_render_overlay(s, &img));
    try {
      const cv::Mat m(h, w, CV_8UC3, pixels_.data());
      if (!opened_) {
        cv::namedWindow(kName, cv::WINDOW_NORMAL);
        cv::resizeWindow(kName, std::min(w, 1280), std::min(h, 1280) * std::min(w, 1280) / w);
        opened_ = true;
      }
      cv::imshow(kName, m);
      const int key = cv::waitKey(1);
      if (key == 'q' || key == 27) return false;
      if (cv::getWindowProperty(kName, cv::WND_PROP_VISIBLE) < 1) return false;
    } catch (const cv::Exception& e) {
      std::fprintf(stderr, "posecal calibrate: no window (%s); continuing headless\n", e.what());
      enabled_ = false;
    }
#else
    (void)s;
    (void)status;
#endif
    return true;
  }

 private:
  static constexpr const char* kName = "posecal";
  bool enabled_ = false;
  bool opened_ = false;
  std::vector<unsigned char> pixels_;
};

int cmd_calibrate_camera(const Args& args) {
  Context c;
  Session s;
  Json cfg = session_config(args);
  const std::string guide = args.get("guide", "overlay");
  if (guide != "overlay" && guide != "stdio") throw UsageError{"--guide must be overlay or stdio"};
  const bool robot = guide == "stdio";
  if (robot) cfg["operator"] = "robot";
  const int timeout_ms = args.integer("timeout-ms", 2000, 0, 600000);
  const double max_seconds = args.number("max-seconds", 1800);
  const int reply_timeout_ms =
      static_cast<int>(std::min(1e9, args.number("reply-timeout-s", 600) * 1000));
  check(posecal_session_open(c.ctx, args.get("camera").c_str(), cfg.dump().c_str(), &s.s));
  EventSink sink{stdout, ""};
  if (args.flag("json")) check(posecal_session_set_callback(s.s, print_event_line, &sink));
  LiveWindow window(!robot && !args.flag("no-window"));
  if (!window.enabled() && !args.flag("json") && !robot) {
    std::fprintf(stderr, "posecal calibrate: no display; running headless\n");
  }
  LineReader replies(STDIN_FILENO);
  const auto t0 = Clock::now();
  std::vector<double> last_target;
  std::string last_guidance;
  int serial = 0, timeouts = 0;
  bool stopped_by_user = false;
  while (true) {
    if (ms_since(t0) > max_seconds * 1000) {
      std::fprintf(stderr, "posecal calibrate: stopped after %.0f s without finishing\n",
                   max_seconds);
      break;
    }
    const posecal_status st = posecal_session_step(s.s, timeout_ms);
    if (st == POSECAL_E_STATE || st == POSECAL_E_NOT_FOUND) break;  // finished / end of images
    if (st == POSECAL_E_TIMEOUT || st == POSECAL_E_DEVICE) {
      if (++timeouts % 5 == 1)
        std::fprintf(stderr, "posecal calibrate: %s\n", posecal_last_error());
      continue;
    }
    check(st);
    timeouts = 0;
    const Json status = fetch_status(s.s);
    if (!window.show(s.s, status)) {
      stopped_by_user = true;
      break;
    }
    if (!args.flag("json") && !robot && status["guidance"].is_string() &&
        status["guidance"].get<std::string>() != last_guidance) {
      last_guidance = status["guidance"].get<std::string>();
      std::fprintf(stderr, "[%d keyframes] %s\n", status["keyframes"].get<int>(),
                   last_guidance.c_str());
    }
    if (!robot) continue;
    // Robot protocol: each new target as one JSON line; then wait for the controller's line.
    double r[3], t[3];
    if (posecal_session_target_pose(s.s, r, t) != POSECAL_OK) continue;
    const std::vector<double> now{r[0], r[1], r[2], t[0], t[1], t[2]};
    if (now == last_target) continue;
    last_target = now;
    write_line(stdout, Json{{"event", "target"},
                            {"serial", ++serial},
                            {"rvec", {r[0], r[1], r[2]}},
                            {"tvec", {t[0], t[1], t[2]}},
                            {"frame", "T_cam_board"},
                            {"state", status["state"]},
                            {"keyframes", status["keyframes"]},
                            {"target_parameter", status["target_parameter"]}});
    while (true) {
      std::string line;
      const LineReader::Result rr = replies.next(&line, reply_timeout_ms);
      if (rr == LineReader::Result::kEof) {
        throw Failure{POSECAL_E_STATE, "--guide stdio: the controller closed stdin"};
      }
      if (rr == LineReader::Result::kTimeout) {
        throw Failure{POSECAL_E_TIMEOUT, "--guide stdio: no reply from the controller within " +
                                             std::to_string(reply_timeout_ms / 1000) + " s"};
      }
      const Reply reply = parse_reply(line);
      if (reply == Reply::kAbort) throw Failure{POSECAL_E_STATE, "aborted by the controller"};
      posecal_status rs = POSECAL_OK;
      if (reply == Reply::kReached) rs = posecal_session_pose_reached(s.s);
      if (reply == Reply::kSkip) rs = posecal_session_skip_target(s.s);
      if (reply != Reply::kInvalid && rs == POSECAL_OK) break;
      write_line(stdout,
                 Json{{"event", "protocol_error"},
                      {"line", line},
                      {"message", reply == Reply::kInvalid
                                      ? "expected 'reached', 'skip', 'abort' or a JSON object "
                                        "{\"reached\": true}"
                                      : std::string(posecal_last_error())}});
    }
  }
  const double wall_ms = ms_since(t0);
  if (!has_result(s.s)) {
    throw Failure{POSECAL_E_STATE, std::string("no calibration: fewer than two keyframes were "
                                               "captured") +
                                       (stopped_by_user ? " (window closed)" : "")};
  }
  const Json result = fetch_result(s.s);
  if (args.has("out")) check(posecal_session_save(s.s, args.get("out").c_str()));
  const Json j = summary(result, wall_ms);
  if (args.flag("json") || robot) {
    Json line = j;
    line["event"] = "result";
    if (args.has("out")) line["file"] = args.get("out");
    write_line(stdout, line);
  } else {
    std::printf("%s after %d keyframes; eps_res %.3f px\n",
                j["converged"].get<bool>() ? "converged" : "NOT converged",
                j["keyframes"].get<int>(), num_or(j, "eps_res", -1));
    if (args.has("out")) std::printf("written %s\n", args.get("out").c_str());
  }
  return j["converged"].get<bool>() ? kOk : kNotConverged;
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
    return kOk;
  }
  std::printf("calibrated from %zu image(s), %zu rejected; RMS %.4f px\n", j["used"].size(),
              j["rejected"].size(), num_or(j, "rms", -1));
  for (const auto& name : j["covariance_order"]) {
    const std::string n = name.get<std::string>();
    std::printf("  %-3s = %14.6f  +- %.6f\n", n.c_str(), num_or(j, n.c_str(), NAN),
                num_or(j["std"], n.c_str(), NAN));
  }
  for (const auto& r : j["rejected"]) {
    std::printf("  rejected %s: %s\n", r["file"].get<std::string>().c_str(),
                r["reason"].get<std::string>().c_str());
  }
  if (args.has("out")) std::printf("written %s\n", args.get("out").c_str());
  return kOk;
}

// ---- station: several cameras at once --------------------------------------------------------

std::vector<std::string> split_list(const std::string& text) {
  std::vector<std::string> out;
  size_t start = 0;
  while (start <= text.size()) {
    size_t comma = text.find(',', start);
    if (comma == std::string::npos) comma = text.size();
    const std::string item = trim(text.substr(start, comma - start));
    if (!item.empty()) out.push_back(item);
    start = comma + 1;
  }
  return out;
}

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

struct StationJob {
  std::string uri;
  Json outcome;  // filled by the job's thread
  int exit = kFailure;
};

void run_station_camera(posecal_context* ctx, const Args& args, const std::string& out_dir,
                        const std::string& format, StationJob* job, std::mutex* names_mutex,
                        std::set<std::string>* names) {
  const auto t0 = Clock::now();
  Json& o = job->outcome;
  o["uri"] = job->uri;
  try {
    Session s;
    check(posecal_session_open(ctx, job->uri.c_str(), session_config(args).dump().c_str(), &s.s));
    const Json camera = fetch_status(s.s)["camera"];
    o["camera"] = camera;
    EventSink sink{stderr, job->uri};
    if (args.flag("events")) check(posecal_session_set_callback(s.s, print_event_line, &sink));
    const int timeout_ms = args.integer("timeout-ms", 2000, 0, 600000);
    const double max_ms = args.number("max-seconds", 1800) * 1000;
    int failures = 0;
    while (ms_since(t0) < max_ms) {
      const posecal_status st = posecal_session_step(s.s, timeout_ms);
      if (st == POSECAL_E_STATE || st == POSECAL_E_NOT_FOUND) break;
      if (st == POSECAL_E_TIMEOUT || st == POSECAL_E_DEVICE) {
        if (++failures % 5 == 1) {
          std::lock_guard<std::mutex> lock(g_out_mutex);
          std::fprintf(stderr, "posecal station: %s: %s\n", job->uri.c_str(), posecal_last_error());
        }
        continue;
      }
      check(st);
      failures = 0;
    }
    if (!has_result(s.s)) {
      throw Failure{POSECAL_E_STATE, "no calibration: fewer than two keyframes were captured"};
    }
    // The result file is named by the camera's identity; two cameras with one id get suffixes.
    std::string name = sanitise_id(camera.value("id", ""));
    {
      std::lock_guard<std::mutex> lock(*names_mutex);
      const std::string base = name;
      for (int i = 2; names->count(name); ++i) name = base + "-" + std::to_string(i);
      names->insert(name);
    }
    const std::string file = out_dir + "/" + name + "." + format;
    check(posecal_session_save(s.s, file.c_str()));
    const Json result = fetch_result(s.s);
    o["converged"] = result.value("converged", false);
    o["state"] = result["state"];
    o["keyframes"] = result["keyframes"];
    o["frames_processed"] = result["frames_processed"];
    o["eps_res"] = result["eps_res"];
    o["eps_test"] = result.contains("eps_test") ? result["eps_test"] : Json(nullptr);
    o["eps_gt"] = result.contains("eps_gt") ? result["eps_gt"] : Json(nullptr);
    o["file"] = file;
    o["error"] = nullptr;
    job->exit = o["converged"].get<bool>() ? kOk : kNotConverged;
  } catch (const Failure& f) {
    o["converged"] = false;
    o["error"] = f.message;
    o["status"] = posecal_status_name(f.status);
    job->exit = kFailure;
  } catch (const std::exception& e) {
    o["converged"] = false;
    o["error"] = e.what();
    job->exit = kFailure;
  }
  o["wall_ms"] = ms_since(t0);
}

int cmd_station(const Args& args) {
  const std::vector<std::string> uris = split_list(args.need("cameras"));
  if (uris.empty()) throw UsageError{"--cameras needs at least one URI"};
  const std::string out_dir = args.need("out-dir");
  const std::string format = args.get("format", "yml");
  if (format != "yml" && format != "yaml" && format != "json") {
    throw UsageError{"--format must be yml, yaml or json"};
  }
  session_config(args);  // usage errors before any thread starts
  args.integer("timeout-ms", 2000, 0, 600000);
  args.number("max-seconds", 1800);
  std::error_code ec;
  std::filesystem::create_directories(out_dir, ec);
  if (ec || !std::filesystem::is_directory(out_dir)) {
    throw Failure{POSECAL_E_IO, "cannot create directory '" + out_dir + "'" +
                                    (ec ? ": " + ec.message() : std::string())};
  }
  Context c;
  std::vector<StationJob> jobs(uris.size());
  std::mutex names_mutex;
  std::set<std::string> names;
  const auto t0 = Clock::now();
  {
    std::vector<std::thread> threads;
    for (size_t i = 0; i < uris.size(); ++i) {
      jobs[i].uri = uris[i];
      threads.emplace_back(run_station_camera, c.ctx, std::cref(args), std::cref(out_dir),
                           std::cref(format), &jobs[i], &names_mutex, &names);
    }
    for (auto& t : threads) t.join();
  }
  Json cams = Json::array();
  int exit = kOk;
  int converged = 0;
  for (const auto& j : jobs) {
    cams.push_back(j.outcome);
    if (j.exit == kOk) ++converged;
    if (j.exit == kFailure) exit = kFailure;
    if (j.exit == kNotConverged && exit == kOk) exit = kNotConverged;
  }
  const Json sum = {
      {"cameras", cams},        {"total", jobs.size()},
      {"converged", converged}, {"all_converged", converged == static_cast<int>(jobs.size())},
      {"out_dir", out_dir},     {"wall_ms", ms_since(t0)}};
  const std::string sum_path = out_dir + "/summary.json";
  if (FILE* f = std::fopen(sum_path.c_str(), "w")) {
    std::fprintf(f, "%s\n", sum.dump(2).c_str());
    std::fclose(f);
  } else {
    std::fprintf(stderr, "posecal station: cannot write %s\n", sum_path.c_str());
    exit = kFailure;
  }
  if (args.flag("json")) {
    std::printf("%s\n", sum.dump().c_str());
  } else {
    for (const auto& o : cams) {
      if (!o["error"].is_null()) {
        std::printf("%-40s FAILED: %s\n", o["uri"].get<std::string>().c_str(),
                    o["error"].get<std::string>().c_str());
        continue;
      }
      char eps_test[64] = "";
      if (o["eps_test"].is_number()) {
        std::snprintf(eps_test, sizeof eps_test, ", eps_test %.3f px", o["eps_test"].get<double>());
      }
      std::printf(
          "%-40s %s, %d keyframes, eps_res %.3f px%s -> %s\n", o["uri"].get<std::string>().c_str(),
          o["converged"].get<bool>() ? "converged" : "NOT converged", o["keyframes"].get<int>(),
          num_or(o, "eps_res", -1), eps_test, o["file"].get<std::string>().c_str());
    }
    std::printf("%d of %zu cameras converged in %.1f s; summary in %s\n", converged, jobs.size(),
                ms_since(t0) / 1000, sum_path.c_str());
  }
  return exit;
}

// ---- evaluate, grab, features ----------------------------------------------------------------

int cmd_evaluate(const Args& args) {
  const std::string result = args.need("result");
  const std::string camera = args.need("camera");
  Json opts = Json::object();
  if (args.has("target")) opts["target"] = args.get("target");
  if (args.has("frames")) opts["frames"] = args.integer("frames", 20, 1, 1000);
  if (args.has("timeout-ms")) opts["timeout_ms"] = args.integer("timeout-ms", 30000, 1, 600000);
  if (args.has("min-corners")) opts["min_corners"] = args.integer("min-corners", 6, 4, 100000);
  Context c;
  const std::string o = opts.dump();
  const Json j = Json::parse(fetch_json([&](char* b, size_t* n) {
    return posecal_evaluate(c.ctx, result.c_str(), camera.c_str(), o.c_str(), b, n);
  }));
  if (args.flag("json")) {
    std::printf("%s\n", j.dump().c_str());
    return kOk;
  }
  std::printf("%s on %s: eps_test %.4f px over %d frames (%d failed PnP)", result.c_str(),
              camera.c_str(), num_or(j, "eps_test", -1), j["test_frames"].get<int>(),
              j["test_frames_failed"].get<int>());
  if (j["eps_gt"].is_number()) std::printf(", eps_gt %.4f px", j["eps_gt"].get<double>());
  std::printf("\n");
  return kOk;
}

int cmd_grab(const Args& args) {
  const std::string camera = args.need("camera");
  const std::string out = args.need("out");
  if (!args.has("count")) throw UsageError{"missing --count"};
  const int count = args.integer("count", 1, 1, 100000);
  const int timeout_ms = args.integer("timeout-ms", 10000, 1, 600000);
  Context c;
  const Json j = Json::parse(fetch_json([&](char* b, size_t* n) {
    return posecal_camera_grab(c.ctx, camera.c_str(), count, out.c_str(), timeout_ms, b, n);
  }));
  if (args.flag("json")) {
    std::printf("%s\n", j.dump().c_str());
    return kOk;
  }
  for (const auto& f : j["files"]) std::printf("%s\n", f["file"].get<std::string>().c_str());
  std::printf("%zu frames from %s in %.0f ms\n", j["files"].size(), camera.c_str(),
              num_or(j, "wall_ms", 0));
  return kOk;
}

std::string value_text(const Json& v) {
  if (v.is_null()) return "-";
  if (v.is_string()) return v.get<std::string>();
  return v.dump();
}

int cmd_features(const Args& args) {
  const std::string camera = args.need("camera");
  Context c;
  const Json j = Json::parse(fetch_json(
      [&](char* b, size_t* n) { return posecal_camera_features(c.ctx, camera.c_str(), b, n); }));
  if (args.flag("json")) {
    std::printf("%s\n", j.dump().c_str());
    return kOk;
  }
  if (j.empty()) std::printf("%s has no settings\n", camera.c_str());
  for (const auto& f : j) {
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
    const std::string unit = f["unit"].is_string() ? f["unit"].get<std::string>() : "";
    std::printf("%-32s %-12s %-10s %s%s%s%s\n", f["name"].get<std::string>().c_str(),
                f["type"].get<std::string>().c_str(), f["access"].get<std::string>().c_str(),
                value_text(f["value"]).c_str(), unit.empty() ? "" : " ", unit.c_str(),
                extra.c_str());
  }
  return kOk;
}

int cmd_board(const Args& args) {
  const std::string target = args.get("target");
  const std::string out = args.need("out");
  check(posecal_write_target(target.empty() ? nullptr : target.c_str(), out.c_str(),
                             args.number("dpi", 300), args.number("margin", 0.01)));
  std::printf("written %s\n", out.c_str());
  return kOk;
}

int cmd_list(const Args& args) {
  Context c;
  const Json cams = Json::parse(
      fetch_json([&](char* b, size_t* s) { return posecal_list_cameras(c.ctx, b, s); }));
  if (args.flag("json")) {
    std::printf("%s\n", cams.dump().c_str());
    return kOk;
  }
  if (cams.empty()) std::printf("no cameras found\n");
  for (const auto& d : cams) {
    std::printf("%-50s %s %s (serial %s, %s)\n", d["uri"].get<std::string>().c_str(),
                d["vendor"].get<std::string>().c_str(), d["model"].get<std::string>().c_str(),
                d["serial"].get<std::string>().c_str(), d["transport"].get<std::string>().c_str());
  }
  return kOk;
}

}  // namespace

int main(int argc, char** argv) {
  if (argc < 2 || !std::strcmp(argv[1], "--help") || !std::strcmp(argv[1], "-h") ||
      !std::strcmp(argv[1], "help")) {
    print_usage();
    return argc < 2 ? kUsage : kOk;
  }
  if (posecal_abi_version() != POSECAL_ABI_VERSION) {
    std::fprintf(stderr, "posecal: library ABI %u does not match this program's %u\n",
                 posecal_abi_version(), POSECAL_ABI_VERSION);
    return kFailure;
  }
  const std::string cmd = argv[1];
  try {
    if (cmd == "calibrate") {
      return cmd_calibrate(Args(
          argc, argv, 2,
          {"json", "fix-principal-point", "fix-aspect-ratio", "zero-tangential", "no-window",
           "prospective-only", "views-serve-target"},
          {"images", "target", "out", "camera", "guide", "timeout-ms", "max-seconds", "threshold",
           "max-keyframes", "candidates", "target-timeout-frames", "reply-timeout-s", "fix", "measure", "score", "views"}));
    }
    if (cmd == "simulate") {
      return cmd_simulate(
          Args(argc, argv, 2, {"json", "events", "prospective-only", "views-serve-target"},
               {"camera-model", "seed", "operator", "noise", "blur", "out", "target", "threshold",
                "max-keyframes", "max-frames", "candidates", "target-timeout-frames", "fix", "measure",
                "score", "views"}));
    }
    if (cmd == "station") {
      return cmd_station(
          Args(argc, argv, 2, {"json", "events", "prospective-only", "views-serve-target"},
               {"cameras", "out-dir", "target", "format", "max-seconds", "timeout-ms", "threshold",
                "max-keyframes", "candidates", "target-timeout-frames", "fix", "measure", "score", "views"}));
    }
    if (cmd == "evaluate") {
      return cmd_evaluate(
          Args(argc, argv, 2, {"json"},
               {"result", "camera", "target", "frames", "timeout-ms", "min-corners"}));
    }
    if (cmd == "grab") {
      return cmd_grab(Args(argc, argv, 2, {"json"}, {"camera", "count", "out", "timeout-ms"}));
    }
    if (cmd == "features") return cmd_features(Args(argc, argv, 2, {"json"}, {"camera"}));
    if (cmd == "board") {
      return cmd_board(Args(argc, argv, 2, {}, {"out", "target", "dpi", "margin"}));
    }
    if (cmd == "list") return cmd_list(Args(argc, argv, 2, {"json"}, {}));
    if (cmd == "version") {
      std::printf("posecal %s (ABI %u)\n", posecal_version(), posecal_abi_version());
      return kOk;
    }
    throw UsageError{"unknown command '" + cmd + "'"};
  } catch (const UsageError& e) {
    std::fprintf(stderr, "posecal %s: %s (see posecal --help)\n", cmd.c_str(), e.message.c_str());
    return kUsage;
  } catch (const Failure& f) {
    std::fprintf(stderr, "posecal %s: %s [%s]\n", cmd.c_str(), f.message.c_str(),
                 posecal_status_name(f.status));
    return kFailure;
  } catch (const std::exception& e) {
    std::fprintf(stderr, "posecal %s: %s\n", cmd.c_str(), e.what());
    return kFailure;
  }
}
