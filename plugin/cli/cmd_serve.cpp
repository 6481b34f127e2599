// posecal serve: the station as an HTTP server (station_server.hpp, docs/serve.md).
#include <memory>
#include <thread>

#include "commands.hpp"
#include "interrupt.hpp"
#include "station_server.hpp"

namespace posecal::cli {

namespace {

// Serves until SIGINT or SIGTERM, then closes every session (each is interrupted first, so what
// it calibrated stays in its journal and records) and exits 0: for a server the signal is the
// normal way to stop. A second signal ends the process at once (interrupt.hpp).
int run_serve(const ServeOptions& o, bool json) {
  StationServer server(o);
  const int port = server.bind();
  const std::string url = "http://" + o.host + ":" + std::to_string(port) + "/";
  if (json) {
    write_line(stdout, {{"listening", url}, {"host", o.host}, {"port", port}});
  } else {
    print_text_line(stdout, "posecal serve: listening on " + url +
                                (o.token.empty() ? "" : " (token required)") + "; Ctrl-C stops it");
  }
  std::thread loop([&server] { server.run(); });
  while (!interrupt_requested()) std::this_thread::sleep_for(std::chrono::milliseconds(100));
  server.stop();
  loop.join();
  if (!json) print_text_line(stdout, "posecal serve: stopped");
  return kOk;
}

}  // namespace

Command add_serve(CLI::App* app) {
  auto o = std::make_shared<ServeOptions>();
  auto json = std::make_shared<bool>(false);
  CLI::App* cmd = app->add_subcommand(
      "serve",
      "serve the station over HTTP: a JSON API to open, follow and close calibration sessions, "
      "their events (Server-Sent Events), live views (MJPEG) and a page for browsers");
  cmd->add_option("--host", o->host,
                  "address to listen on (default 127.0.0.1; any other needs --token)")
      ->check(non_empty());
  cmd->add_option("--port", o->port, "TCP port (default 8321; 0: any free port, printed)")
      ->check(CLI::Range(0, 65535));
  cmd->add_option("--token", o->token,
                  "required of every request: 'Authorization: Bearer TOKEN' or '?token=TOKEN'");
  cmd->add_option("--max-sessions", o->max_sessions, "sessions open at once (default 16)")
      ->check(CLI::Range(1, 256));
  cmd->add_option("--max-streams", o->max_streams,
                  "event and live-view streams open at once (default 16; more: 503)")
      ->check(CLI::Range(1, 64));
  cmd->add_option("--records", o->records,
                  "the station's record store (SQLite file or postgresql:// URL): sessions "
                  "without a \"records\" key record there; GET /api/records reads it")
      ->check(non_empty());
  add_json_flag(cmd, json.get(), "print the listening address as one JSON line");
  cmd->footer(
      "Routes (docs/serve.md): GET /api/cameras; POST /api/sessions {\"camera\": URI, "
      "\"config\": {...}};\n  GET /api/sessions; GET|DELETE /api/sessions/ID; GET "
      "/api/sessions/ID/result|target|events|stream.mjpg|frame.jpg;\n  POST "
      "/api/sessions/ID/reached|skip|abort|save; GET /api/events; GET /api/records[/RUN_ID];\n  "
      "GET / (the page).\n"
      "SIGINT / SIGTERM close every session and exit 0.");
  return [o, json] { return run_serve(*o, *json); };
}

}  // namespace posecal::cli
