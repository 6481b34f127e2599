// `posecal serve` (station_server.hpp): sessions, their stepping threads, the event log, the
// live pictures and the HTTP routes. docs/serve.md describes the API.
#include "station_server.hpp"

#include <httplib.h>

#include <algorithm>
#include <atomic>
#include <condition_variable>
#include <csignal>
#include <deque>
#include <map>
#include <mutex>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <thread>
#include <utility>
#include <vector>

#include "cli_common.hpp"
#include "common/run_id.hpp"

namespace posecal::cli {

namespace {

constexpr size_t kMaxBodyBytes = 1 << 20;  // a request body above this: 413
constexpr size_t kMaxEvents = 100000;      // the event log keeps the newest this many
constexpr int kStepTimeoutMs = 200;        // one step's wait for a frame
constexpr int kStreamWaitMs = 1000;        // a stream's keep-alive interval
constexpr int kApiThreads = 16;  // HTTP threads beside those the streams hold (max_streams)

constexpr size_t kMaxWaitingConnections = 64;  // accepted, waiting for an HTTP thread; above: 503
constexpr int kRefusingThreads = 2;            // answer 503 to the connections above that

// Set in the threads that refuse: the pre-routing handler answers 503 there.
thread_local bool t_refusing = false;

// The server's connections: `workers` threads serve them, at most kMaxWaitingConnections wait for
// one; a connection beyond that is handed to one of kRefusingThreads, which answer its request
// 503 at once (httplib gives a queue only the job, not the socket, so the refusal has to read the
// request like any other; an idle connection holds a refusing thread for the 5 s read timeout,
// and the connections waiting for those are bounded by the process's file descriptors).
class BoundedConnections : public httplib::TaskQueue {
 public:
  explicit BoundedConnections(size_t workers) {
    for (size_t i = 0; i < workers; ++i) serving_.emplace_back([this] { run(serve_, false); });
    for (int i = 0; i < kRefusingThreads; ++i)
      refusing_.emplace_back([this] { run(refuse_, true); });
  }
  void enqueue(std::function<void()> fn) override {
    {
      std::lock_guard<std::mutex> lk(mu_);
      const bool full = serve_.size() >= kMaxWaitingConnections;
      (full ? refuse_ : serve_).push_back(std::move(fn));
    }
    cv_.notify_all();
  }
  void shutdown() override {
    {
      std::lock_guard<std::mutex> lk(mu_);
      down_ = true;
    }
    cv_.notify_all();
    for (auto& t : serving_) t.join();
    for (auto& t : refusing_) t.join();
  }

 private:
  void run(std::deque<std::function<void()>>& jobs, bool refusing) {
    t_refusing = refusing;
    for (;;) {
      std::function<void()> fn;
      {
        std::unique_lock<std::mutex> lk(mu_);
        cv_.wait(lk, [&] { return down_ || !jobs.empty(); });
        if (jobs.empty()) return;  // shut down, nothing left
        fn = std::move(jobs.front());
        jobs.pop_front();
      }
      fn();
    }
  }
  std::mutex mu_;
  std::condition_variable cv_;
  std::deque<std::function<void()>> serve_, refuse_;
  bool down_ = false;
  std::vector<std::thread> serving_, refusing_;
};

// The HTTP status of a failed ABI call.
int http_status(posecal_status s) {
  switch (s) {
    case POSECAL_E_INVALID_ARGUMENT:
      return 400;
    case POSECAL_E_NOT_FOUND:
      return 404;
    case POSECAL_E_STATE:
    case POSECAL_E_DEGENERATE:
      return 409;
    case POSECAL_E_UNSUPPORTED:
      return 501;
    case POSECAL_E_DEVICE:
      return 502;
    case POSECAL_E_TIMEOUT:
      return 504;
    default:
      return 500;
  }
}

// j[key] as a T, or `def` when j is not an object, has no such key, or holds another type (a
// status before the first frame has nulls).
template <class T>
T field(const Json& j, const char* key, T def) {
  if (!j.is_object()) return def;
  const auto it = j.find(key);
  if (it == j.end() || it->is_null()) return def;
  try {
    return it->get<T>();
  } catch (const std::exception&) {
    return def;
  }
}

void send_json(httplib::Response& res, const Json& j, int status = 200) {
  res.status = status;
  res.set_content(json_text(j) + "\n", "application/json");
}

void send_error(httplib::Response& res, int status, const std::string& message,
                posecal_status abi = POSECAL_OK) {
  Json j = {{"error", message}, {"status", status}};
  if (abi != POSECAL_OK) j["posecal_status"] = posecal_status_name(abi);
  send_json(res, j, status);
}

// A session the server steps.
struct Served {
  std::string id, camera;
  int order = 0;  // the n of id "sn"
  Json config;
  posecal_session* session = nullptr;
  std::mutex abi;                 // one ABI call on the session at a time
  std::atomic<int> waiting{0};    // requests waiting for `abi` (the stepper lets them in)
  std::atomic<bool> stop{false};  // the stepper ends
  std::atomic<int> viewers{0};    // live-view streams watching
  std::atomic<bool> want_picture{false};
  std::thread stepper;
  int width = 0, height = 0;  // the camera's image size once known
  int events = 0;             // events so far (under the station's event mutex)
  Clock::time_point last_picture{};
  // Left behind by the stepper, read by the HTTP threads (under `cache`).
  std::mutex cache;
  std::condition_variable picture_cv;
  Json status;
  Json result;        // once finished (null before, or without a calibration)
  std::string error;  // why the stepper stopped early, if it did
  std::vector<uchar> jpeg;
  long long picture_seq = 0;
  bool done = false;
  std::pair<void*, Served*> callback_user{nullptr, nullptr};  // the event callback's user data
};

struct Event {
  unsigned long long seq;  // over the whole station, from 1
  std::string session;
  std::string text;  // the JSON object
  std::string kind;
};

}  // namespace

struct StationServer::Impl {
  ServeOptions options;
  httplib::Server http;
  posecal_context* ctx = nullptr;
  std::atomic<bool> stopping{false};
  std::atomic<int> streams{0};

  std::mutex sessions_mu;
  std::map<std::string, std::shared_ptr<Served>> sessions;
  int opened = 0;  // sessions opened so far (their ids: s1, s2, ...)

  std::mutex events_mu;
  std::condition_variable events_cv;
  std::deque<Event> events;
  unsigned long long next_seq = 1;

  explicit Impl(ServeOptions o) : options(std::move(o)) {}

  std::shared_ptr<Served> find(const std::string& id) {
    std::lock_guard<std::mutex> lk(sessions_mu);
    const auto it = sessions.find(id);
    return it == sessions.end() ? nullptr : it->second;
  }

  // ---- Events ----
  void append_event(Served* s, const std::string& kind, Json j) {
    j["event"] = kind;
    j["session"] = s->id;
    stamp_event(&j);
    {
      std::lock_guard<std::mutex> lk(events_mu);
      j["seq"] = next_seq;
      j["session_seq"] = ++s->events;
      events.push_back({next_seq++, s->id, json_text(j), kind});
      if (events.size() > kMaxEvents) events.pop_front();
    }
    events_cv.notify_all();
  }

  static void on_event(void* user, const char* kind, const char* payload) {
    auto* pair = static_cast<std::pair<void*, Served*>*>(user);
    auto* impl = static_cast<Impl*>(pair->first);
    Json j = Json::object();
    try {
      j = Json::parse(payload ? payload : "{}");
      if (!j.is_object()) j = {{"payload", j}};
    } catch (const std::exception&) {
      j = {{"payload", payload ? payload : ""}};
    }
    impl->append_event(pair->second, kind ? kind : "?", std::move(j));
  }

  // ---- The stepping thread ----
  void render_picture(Served* s) {
    if (s->width <= 0 || s->height <= 0) return;
    cv::Mat bgr(s->height, s->width, CV_8UC3);
    posecal_image img{sizeof(posecal_image), s->width, s->height, static_cast<int32_t>(bgr.step[0]),
                      POSECAL_PIXEL_BGR8,    bgr.data};
    if (posecal_session_last_frame(s->session, &img) != POSECAL_OK) return;
    if (posecal_session_render_overlay(s->session, &img) != POSECAL_OK) return;
    std::vector<uchar> jpeg;
    if (!cv::imencode(".jpg", bgr, jpeg, {cv::IMWRITE_JPEG_QUALITY, 80})) return;
    {
      std::lock_guard<std::mutex> lk(s->cache);
      s->jpeg = std::move(jpeg);
      ++s->picture_seq;
    }
    s->picture_cv.notify_all();
  }

  // Status (and at the end the result) into the cache; true once the calibration has finished.
  bool refresh(Served* s) {
    Json status;
    try {
      status = fetch_status(s->session);
    } catch (const Failure& f) {
      std::lock_guard<std::mutex> lk(s->cache);
      s->error = f.message;
      return false;
    }
    s->width = field(status, "image_width", 0);
    s->height = field(status, "image_height", 0);
    const bool finished = field(status, "finished", false);
    Json result;
    // Once, when the session finishes (the first result renders the simulated test set).
    if (finished && s->result.is_null() && has_result(s->session)) {
      try {
        result = fetch_result(s->session);
      } catch (const Failure&) {
      }
    }
    std::lock_guard<std::mutex> lk(s->cache);
    s->status = std::move(status);
    if (finished && !result.is_null()) s->result = std::move(result);
    return finished;
  }

  void step_loop(Served* s) {
    std::string why;
    bool finished = false;
    while (!s->stop && !stopping) {
      posecal_status st;
      {
        std::lock_guard<std::mutex> lk(s->abi);
        st = posecal_session_step(s->session, kStepTimeoutMs);
        if (st != POSECAL_OK && st != POSECAL_E_TIMEOUT && st != POSECAL_E_DEVICE &&
            st != POSECAL_E_STATE) {
          why = std::string(posecal_status_name(st)) + ": " + posecal_last_error();
        }
        finished = refresh(s);
        const auto now = Clock::now();
        if ((s->viewers > 0 || s->want_picture) &&
            (finished ||
             now - s->last_picture >= std::chrono::milliseconds(options.frame_interval_ms))) {
          s->want_picture = false;
          s->last_picture = now;
          render_picture(s);
        }
      }
      if (finished || st == POSECAL_E_STATE || !why.empty()) break;
      if (st == POSECAL_E_DEVICE) std::this_thread::sleep_for(std::chrono::milliseconds(100));
      // Requests waiting for the session get it before the next step.
      for (int i = 0; i < 50 && s->waiting > 0; ++i)
        std::this_thread::sleep_for(std::chrono::milliseconds(2));
    }
    {
      std::lock_guard<std::mutex> lk(s->abi);
      refresh(s);
      render_picture(s);
    }
    Json fin;
    {
      std::lock_guard<std::mutex> lk(s->cache);
      if (!why.empty()) s->error = why;
      s->done = true;
      fin = {{"converged", field(s->status, "converged", false)},
             {"interrupted", field(s->status, "interrupted", false)},
             {"keyframes", field(s->status, "keyframes", 0)},
             {"error", s->error.empty() ? Json() : Json(s->error)}};
    }
    append_event(s, "finished", fin);  // the server's own: the session's stream ends here
    s->picture_cv.notify_all();
  }

  // Runs `fn` with the session's ABI mutex held (the stepper yields to waiting requests).
  template <class F>
  auto with_session(Served* s, F fn) {
    ++s->waiting;
    std::lock_guard<std::mutex> lk(s->abi);
    --s->waiting;
    return fn();
  }

  // ---- Sessions ----
  std::shared_ptr<Served> open(const std::string& camera, const Json& config) {
    {
      std::lock_guard<std::mutex> lk(sessions_mu);
      if (static_cast<int>(sessions.size()) >= options.max_sessions) {
        throw Failure{POSECAL_E_UNSUPPORTED, "the station serves at most " +
                                                 std::to_string(options.max_sessions) +
                                                 " sessions (--max-sessions); close one first"};
      }
    }
    if (camera == "external") {
      throw Failure{POSECAL_E_INVALID_ARGUMENT,
                    "camera \"external\": the server steps its cameras itself; open sim://, "
                    "aravis://, v4l2:// or images:// cameras"};
    }
    auto s = std::make_shared<Served>();
    s->camera = camera;
    s->config = config;
    if (!options.records.empty() && (config.is_null() || config.is_object()) &&
        !(config.is_object() && config.contains("records"))) {
      s->config["records"] = options.records;  // the station's store, unless the config names one
    }
    const std::string text = s->config.is_null() ? std::string() : json_text(s->config);
    check(posecal_session_open(ctx, camera.c_str(), text.empty() ? nullptr : text.c_str(),
                               &s->session));
    try {
      s->callback_user = {this, s.get()};
      check(posecal_session_set_callback(s->session, &Impl::on_event, &s->callback_user));
      refresh(s.get());
      std::lock_guard<std::mutex> lk(sessions_mu);
      s->order = ++opened;
      s->id = "s" + std::to_string(s->order);
      s->stepper = std::thread([this, raw = s.get()] { step_loop(raw); });
      sessions[s->id] = s;
    } catch (...) {
      posecal_session_close(s->session);  // never left open without its stepper
      throw;
    }
    return s;
  }

  void close(const std::shared_ptr<Served>& s) {
    s->stop = true;
    posecal_session_interrupt(s->session);
    if (s->stepper.joinable()) s->stepper.join();
    posecal_session_close(s->session);
    s->session = nullptr;
    s->picture_cv.notify_all();
    events_cv.notify_all();
  }

  Json summary(Served* s) {
    std::lock_guard<std::mutex> lk(s->cache);
    const Json& st = s->status;
    Json j = {{"id", s->id},
              {"camera", s->camera},
              {"state", field(st, "state", std::string("opened"))},
              {"finished", field(st, "finished", false)},
              {"converged", field(st, "converged", false)},
              {"interrupted", field(st, "interrupted", false)},
              {"keyframes", field(st, "keyframes", 0)},
              // The cap the page's keyframe bar fills towards (session_keys.def's default).
              {"max_keyframes", field(s->config, "max_keyframes", 20)},
              {"guidance", field(st, "guidance", std::string())},
              {"done", s->done},
              {"camera_connected", field(st, "camera_connected", true)},
              {"error", s->error.empty() ? Json() : Json(s->error)}};
    for (const char* k : {"expected_error_px", "expected_error_p90_px"})
      if (st.contains(k)) j[k] = st[k];
    if (s->result.is_object()) {
      for (const char* k : {"verdict", "verdict_reasons", "eps_gt", "expected_error_px"})
        if (s->result.contains(k)) j[k] = s->result[k];
    }
    return j;
  }

  // ---- HTTP ----
  bool authorised(const httplib::Request& req) const {
    if (options.token.empty()) return true;
    const std::string auth = req.get_header_value("Authorization");
    if (auth == "Bearer " + options.token) return true;
    return req.has_param("token") && req.get_param_value("token") == options.token;
  }

  // A stream slot, or false (503) when max_streams are open.
  bool take_stream(httplib::Response& res) {
    if (streams.fetch_add(1) >= options.max_streams) {
      --streams;
      send_error(res, 503,
                 "too many streams open (" + std::to_string(options.max_streams) +
                     ", --max-streams); close one or poll the JSON routes");
      return false;
    }
    return true;
  }

  // Server-Sent Events from the log: every event after `after` of `session` (all sessions when
  // empty), then, for one session, an "end" event once its "finished" event has been sent.
  void stream_events(httplib::Response& res, const std::string& session, unsigned long long after) {
    if (!take_stream(res)) return;
    res.set_header("Cache-Control", "no-cache");
    auto next = std::make_shared<unsigned long long>(after + 1);
    res.set_chunked_content_provider(
        "text/event-stream",
        [this, session, next](size_t, httplib::DataSink& sink) {
          std::string chunk;
          bool end = false;
          {
            std::unique_lock<std::mutex> lk(events_mu);
            const auto ready = [&] {
              return stopping || (!events.empty() && events.back().seq >= *next);
            };
            events_cv.wait_for(lk, std::chrono::milliseconds(kStreamWaitMs), ready);
            if (!events.empty() && events.front().seq > *next) {
              chunk += ": " + std::to_string(events.front().seq - *next) +
                       " events were dropped from the log\n\n";
              *next = events.front().seq;
            }
            for (const Event& e : events) {
              if (e.seq < *next) continue;
              *next = e.seq + 1;
              if (!session.empty() && e.session != session) continue;
              chunk += "id: " + std::to_string(e.seq) + "\nevent: " + e.kind + "\ndata: " + e.text +
                       "\n\n";
              if (!session.empty() && e.kind == "finished") end = true;
            }
          }
          if (!end && !session.empty() && !find(session)) end = true;  // closed meanwhile
          if (end) chunk += "event: end\ndata: {}\n\n";
          if (chunk.empty()) chunk = ": keep-alive\n\n";
          if (stopping) end = true;
          if (!sink.write(chunk.data(), chunk.size())) return false;
          if (end) sink.done();
          return true;
        },
        [this](bool) { --streams; });
  }

  // The live view: multipart JPEG pictures of the overlay, at most every frame_interval_ms.
  void stream_pictures(httplib::Response& res, const std::shared_ptr<Served>& s) {
    if (!take_stream(res)) return;
    ++s->viewers;
    res.set_header("Cache-Control", "no-cache");
    auto seen = std::make_shared<long long>(0);
    res.set_chunked_content_provider(
        "multipart/x-mixed-replace; boundary=posecalframe",
        [this, s, seen](size_t, httplib::DataSink& sink) {
          std::vector<uchar> jpeg;
          bool end = false;
          {
            std::unique_lock<std::mutex> lk(s->cache);
            s->picture_cv.wait_for(lk, std::chrono::milliseconds(kStreamWaitMs),
                                   [&] { return stopping || s->stop || s->picture_seq > *seen; });
            const bool fresh = s->picture_seq > *seen;
            end = stopping || s->stop || (s->done && !fresh);
            // A picture unchanged for kStreamWaitMs is sent again: it keeps the connection
            // alive and tells a viewer that has gone away (the write fails).
            if (!end) jpeg = s->jpeg;
            *seen = s->picture_seq;
          }
          if (!jpeg.empty()) {
            const std::string head =
                "--posecalframe\r\nContent-Type: image/jpeg\r\nContent-Length: " +
                std::to_string(jpeg.size()) + "\r\n\r\n";
            if (!sink.write(head.data(), head.size()) ||
                !sink.write(reinterpret_cast<const char*>(jpeg.data()), jpeg.size()) ||
                !sink.write("\r\n", 2)) {
              return false;
            }
          }
          if (end) sink.done();
          return true;
        },
        [this, s](bool) {
          --s->viewers;
          --streams;
        });
  }

  void routes() {
    auto& h = http;
    h.set_payload_max_length(kMaxBodyBytes);
    h.set_read_timeout(5, 0);
    h.set_write_timeout(5, 0);
    h.set_keep_alive_timeout(5);
    h.new_task_queue = [n = options.max_streams + kApiThreads] {
      return new BoundedConnections(static_cast<size_t>(n));
    };
    h.set_pre_routing_handler([this](const httplib::Request& req, httplib::Response& res) {
      if (t_refusing) {
        res.set_header("Connection", "close");
        res.set_header("Retry-After", "5");
        send_error(res, 503,
                   "too many connections: " + std::to_string(kMaxWaitingConnections) +
                       " are waiting for the server's " +
                       std::to_string(options.max_streams + kApiThreads) + " HTTP threads");
        return httplib::Server::HandlerResponse::Handled;
      }
      if (authorised(req)) return httplib::Server::HandlerResponse::Unhandled;
      send_error(res, 401, "a token is required: Authorization: Bearer TOKEN, or ?token=TOKEN");
      return httplib::Server::HandlerResponse::Handled;
    });
    h.set_error_handler([](const httplib::Request& req, httplib::Response& res) {
      if (!res.body.empty()) return;
      const std::string what = res.status == 404   ? "no such route: " + req.method + " " + req.path
                               : res.status == 413 ? "the request body is above " +
                                                         std::to_string(kMaxBodyBytes) + " bytes"
                                                   : "HTTP error";
      send_error(res, res.status, what);
    });
    h.set_exception_handler(
        [](const httplib::Request&, httplib::Response& res, std::exception_ptr ep) {
          std::string what = "unknown error";
          try {
            std::rethrow_exception(ep);
          } catch (const std::exception& e) {
            what = e.what();
          } catch (...) {
          }
          send_error(res, 500, "internal error: " + what);
        });

    h.Get("/", [](const httplib::Request&, httplib::Response& res) {
      res.set_content(serve_page_html(), "text/html; charset=utf-8");
    });
    h.Get("/api", [this](const httplib::Request&, httplib::Response& res) {
      std::lock_guard<std::mutex> lk(sessions_mu);
      send_json(res, {{"posecal", posecal_version()},
                      {"abi", posecal_abi_version()},
                      {"sessions", sessions.size()},
                      {"max_sessions", options.max_sessions},
                      {"streams", streams.load()},
                      {"max_streams", options.max_streams},
                      {"records", options.records.empty() ? Json() : Json(options.records)}});
    });
    h.Get("/api/cameras", [this](const httplib::Request&, httplib::Response& res) {
      try {
        send_json(res, Json::parse(fetch_json(
                           [&](char* b, size_t* n) { return posecal_list_cameras(ctx, b, n); })));
      } catch (const Failure& f) {
        send_error(res, http_status(f.status), f.message, f.status);
      }
    });
    // The station's record store (--records): its runs, newest first, and one run.
    const auto records = [this](auto fetch) {
      return [this, fetch](const httplib::Request& req, httplib::Response& res) {
        if (options.records.empty()) {
          send_error(res, 404, "no record store: start the server with --records PATH|URL");
          return;
        }
        try {
          send_json(res,
                    Json::parse(fetch_json([&](char* b, size_t* n) { return fetch(req, b, n); })));
        } catch (const Failure& f) {
          send_error(res, http_status(f.status), f.message, f.status);
        }
      };
    };
    h.Get("/api/records", records([this](const httplib::Request&, char* b, size_t* n) {
            return posecal_records_list(options.records.c_str(), b, n);
          }));
    h.Get(R"(/api/records/([^/]+))",
          records([this](const httplib::Request& req, char* b, size_t* n) {
            const std::string run = req.matches[1];
            return posecal_records_show(options.records.c_str(), run.c_str(), b, n);
          }));
    h.Get("/api/sessions", [this](const httplib::Request&, httplib::Response& res) {
      std::vector<std::shared_ptr<Served>> all;
      {
        std::lock_guard<std::mutex> lk(sessions_mu);
        for (const auto& [id, s] : sessions) all.push_back(s);
      }
      std::sort(all.begin(), all.end(), [](const auto& a, const auto& b) {
        return a->order < b->order;  // opened first, first
      });
      Json list = Json::array();
      for (const auto& s : all) list.push_back(summary(s.get()));
      send_json(res, list);
    });
    h.Post("/api/sessions", [this](const httplib::Request& req, httplib::Response& res) {
      Json body;
      try {
        body = Json::parse(req.body);
      } catch (const std::exception& e) {
        send_error(res, 400, std::string("the body is not JSON: ") + e.what());
        return;
      }
      if (!body.is_object() || !body.contains("camera") || !body["camera"].is_string()) {
        send_error(res, 400, "the body must be {\"camera\": URI, \"config\": {...}}");
        return;
      }
      const Json config = body.value("config", Json());
      if (!config.is_null() && !config.is_object()) {
        send_error(res, 400, "\"config\" must be an object of session keys (docs/c-api.md)");
        return;
      }
      for (const auto& [key, v] : body.items()) {
        if (key != "camera" && key != "config") {
          send_error(res, 400, "unknown key \"" + key + "\" (camera, config)");
          return;
        }
      }
      try {
        const auto s = open(body["camera"].get<std::string>(), config);
        send_json(res, {{"id", s->id}, {"camera", s->camera}}, 201);
      } catch (const Failure& f) {
        send_error(res, http_status(f.status), f.message, f.status);
      }
    });

    const std::string one = R"(/api/sessions/([^/]+))";
    // Runs a handler with the session named in the path, or answers 404.
    const auto with = [this](auto fn) {
      return [this, fn](const httplib::Request& req, httplib::Response& res) {
        const auto s = find(req.matches[1]);
        if (!s) {
          send_error(res, 404, "no session " + std::string(req.matches[1]));
          return;
        }
        try {
          fn(req, res, s);
        } catch (const Failure& f) {
          send_error(res, http_status(f.status), f.message, f.status);
        }
      };
    };
    h.Get(one, with([this](const httplib::Request&, httplib::Response& res,
                           const std::shared_ptr<Served>& s) {
            Json status;
            {
              std::lock_guard<std::mutex> lk(s->cache);
              status = s->status;
              status["id"] = s->id;
              status["done"] = s->done;
              status["error"] = s->error.empty() ? Json() : Json(s->error);
            }
            {
              std::lock_guard<std::mutex> lk(events_mu);
              status["events"] = s->events;
            }
            send_json(res, status);
          }));
    h.Get(one + "/result", with([this](const httplib::Request&, httplib::Response& res,
                                       const std::shared_ptr<Served>& s) {
            {
              std::lock_guard<std::mutex> lk(s->cache);
              if (s->result.is_object()) return send_json(res, s->result);
            }
            const Json r = with_session(s.get(), [&] {
              if (!has_result(s->session)) {
                throw Failure{POSECAL_E_STATE, "no calibration yet: it needs two keyframes"};
              }
              return fetch_result(s->session);
            });
            send_json(res, r);
          }));
    h.Get(one + "/target", with([this](const httplib::Request&, httplib::Response& res,
                                       const std::shared_ptr<Served>& s) {
            double r[3], t[3];
            with_session(s.get(), [&] { check(posecal_session_target_pose(s->session, r, t)); });
            send_json(res, {{"rvec", {r[0], r[1], r[2]}}, {"tvec", {t[0], t[1], t[2]}}});
          }));
    h.Post(one + "/reached", with([this](const httplib::Request&, httplib::Response& res,
                                         const std::shared_ptr<Served>& s) {
             with_session(s.get(), [&] { check(posecal_session_pose_reached(s->session)); });
             send_json(res, {{"id", s->id}, {"reached", true}});
           }));
    h.Post(one + "/skip", with([this](const httplib::Request&, httplib::Response& res,
                                      const std::shared_ptr<Served>& s) {
             with_session(s.get(), [&] { check(posecal_session_skip_target(s->session)); });
             send_json(res, {{"id", s->id}, {"skipped", true}});
           }));
    h.Post(one + "/abort", with([](const httplib::Request&, httplib::Response& res,
                                   const std::shared_ptr<Served>& s) {
             check(posecal_session_interrupt(s->session));  // any thread (docs/c-api.md)
             send_json(res, {{"id", s->id}, {"interrupted", true}});
           }));
    h.Post(one + "/save", with([this](const httplib::Request& req, httplib::Response& res,
                                      const std::shared_ptr<Served>& s) {
             Json body;
             try {
               body = Json::parse(req.body);
             } catch (const std::exception& e) {
               throw Failure{POSECAL_E_INVALID_ARGUMENT,
                             std::string("the body is not JSON: ") + e.what()};
             }
             if (!body.is_object() || !body.contains("path") || !body["path"].is_string() ||
                 (body.contains("format") && !body["format"].is_string())) {
               throw Failure{POSECAL_E_INVALID_ARGUMENT,
                             "the body must be {\"path\": FILE, \"format\": NAME (optional)}"};
             }
             const std::string path = body["path"], format = body.value("format", std::string());
             with_session(s.get(), [&] {
               check(posecal_session_save_as(s->session, path.c_str(),
                                             format.empty() ? nullptr : format.c_str()));
             });
             send_json(res, {{"id", s->id}, {"saved", path}});
           }));
    h.Delete(one, [this](const httplib::Request& req, httplib::Response& res) {
      std::shared_ptr<Served> s;
      {
        std::lock_guard<std::mutex> lk(sessions_mu);
        const auto it = sessions.find(req.matches[1]);
        if (it != sessions.end()) {
          s = it->second;
          sessions.erase(it);
        }
      }
      if (!s) return send_error(res, 404, "no session " + std::string(req.matches[1]));
      close(s);
      send_json(res, {{"id", s->id}, {"closed", true}});
    });
    h.Get(one + "/events", [this](const httplib::Request& req, httplib::Response& res) {
      if (!find(req.matches[1])) {
        return send_error(res, 404, "no session " + std::string(req.matches[1]));
      }
      stream_events(res, req.matches[1], after_param(req));
    });
    h.Get("/api/events", [this](const httplib::Request& req, httplib::Response& res) {
      stream_events(res, "", after_param(req));
    });
    h.Get(one + "/stream.mjpg",
          with([this](const httplib::Request&, httplib::Response& res,
                      const std::shared_ptr<Served>& s) { stream_pictures(res, s); }));
    h.Get(one + "/frame.jpg", with([](const httplib::Request&, httplib::Response& res,
                                      const std::shared_ptr<Served>& s) {
            s->want_picture = true;
            std::unique_lock<std::mutex> lk(s->cache);
            const long long before = s->picture_seq;
            s->picture_cv.wait_for(lk, std::chrono::seconds(2), [&] {
              return s->picture_seq > before || (s->done && !s->jpeg.empty());
            });
            if (s->jpeg.empty()) throw Failure{POSECAL_E_STATE, "no frame yet"};
            res.set_content(reinterpret_cast<const char*>(s->jpeg.data()), s->jpeg.size(),
                            "image/jpeg");
          }));
  }

  // Events after this sequence number: ?after=N, or the Last-Event-ID of a reconnecting client.
  static unsigned long long after_param(const httplib::Request& req) {
    std::string v = req.has_param("after") ? req.get_param_value("after")
                                           : req.get_header_value("Last-Event-ID");
    try {
      size_t used = 0;
      const unsigned long long n = v.empty() ? 0 : std::stoull(v, &used);
      return used == v.size() ? n : 0;
    } catch (const std::exception&) {
      return 0;
    }
  }
};

StationServer::StationServer(ServeOptions options)
    : impl_(std::make_unique<Impl>(std::move(options))) {
  const std::string& host = impl_->options.host;
  const bool loopback = host == "127.0.0.1" || host == "::1" || host == "localhost";
  if (!loopback && impl_->options.token.empty()) {
    throw UsageError{"--host " + host +
                     " is not the loopback address: give --token so that only controllers "
                     "that know it can open and close sessions"};
  }
  check(posecal_context_create(nullptr, &impl_->ctx));
  impl_->routes();
}

StationServer::~StationServer() {
  stop();
  std::vector<std::shared_ptr<Served>> all;
  {
    std::lock_guard<std::mutex> lk(impl_->sessions_mu);
    for (const auto& [id, s] : impl_->sessions) all.push_back(s);
    impl_->sessions.clear();
  }
  for (const auto& s : all) impl_->close(s);
  posecal_context_destroy(impl_->ctx);
}

int StationServer::bind() {
  const int port = impl_->options.port == 0
                       ? impl_->http.bind_to_any_port(impl_->options.host)
                       : (impl_->http.bind_to_port(impl_->options.host, impl_->options.port)
                              ? impl_->options.port
                              : -1);
  if (port <= 0) {
    throw Failure{POSECAL_E_IO, "cannot listen on " + impl_->options.host + ":" +
                                    std::to_string(impl_->options.port) +
                                    " (in use, or not an address of this machine)"};
  }
  return port;
}

void StationServer::run() { impl_->http.listen_after_bind(); }

void StationServer::stop() {
  impl_->stopping = true;
  impl_->events_cv.notify_all();
  {
    std::lock_guard<std::mutex> lk(impl_->sessions_mu);
    for (const auto& [id, s] : impl_->sessions) s->picture_cv.notify_all();
  }
  impl_->http.stop();
}

}  // namespace posecal::cli
