// `posecal serve`: the station as an HTTP server (issue 18, item 2). Controllers in any language
// open calibration sessions on cameras the server steps itself (sim://, aravis://, v4l2://,
// images://), read their status, target pose and result, tell a robot's pose reached, skip,
// abort and close them, follow their events (Server-Sent Events) and watch them live (MJPEG
// with the operator overlay); a browser gets a self-contained page of every camera.
//
// Built on the C ABI only, as every command (posecal.h), and on Debian's cpp-httplib. One
// stepping thread per session; all ABI calls on a session go through its mutex (a session is
// used by one thread at a time, docs/c-api.md); the HTTP threads read the status, pictures and
// events the stepping thread leaves behind, so a slow client never stalls a camera.
// Routes, limits and errors: docs/serve.md.
#pragma once

#include <memory>
#include <string>

namespace posecal::cli {

struct ServeOptions {
  std::string host = "127.0.0.1";
  int port = 8321;    // 0: any free port (the bound one is printed and returned by bind())
  std::string token;  // required (Authorization: Bearer T, or ?token=T) when set
  int max_sessions = 16;
  int max_streams = 16;         // event and picture streams at once; above: 503
  int frame_interval_ms = 100;  // the live view's pace (at most 10 pictures a second)
  // The station's record store (a SQLite file or a postgresql:// URL; empty: none): sessions
  // opened without a "records" key record there, and /api/records reads it.
  std::string records;
};

class StationServer {
 public:
  explicit StationServer(ServeOptions options);
  ~StationServer();  // stops the server and closes every session
  StationServer(const StationServer&) = delete;
  StationServer& operator=(const StationServer&) = delete;

  // Binds the listening socket; returns the port. Throws Failure naming the cause.
  int bind();
  // Serves until stop() (from any thread). Returns when the listening loop has ended.
  void run();
  void stop();

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

// The page at "/" (serve_page.cpp): HTML, CSS and JavaScript in one document, no build step.
const char* serve_page_html();

}  // namespace posecal::cli
