#include "live_window.hpp"

#include <netdb.h>
#include <poll.h>
#include <sys/socket.h>
#include <sys/un.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstddef>
#include <cstdlib>
#include <cstring>

#include "interrupt.hpp"

#ifdef POSECAL_CLI_HIGHGUI
#include <xcb/xcb.h>

#include <chrono>
#include <future>
#include <memory>
#include <opencv2/core.hpp>
#include <opencv2/highgui.hpp>
#include <thread>
#endif

namespace posecal::cli {

namespace {

#ifdef POSECAL_CLI_HIGHGUI
constexpr const char* kWindowName = "posecal";
#endif

bool connect_with_timeout(int fd, const sockaddr* addr, socklen_t len) {
  if (::connect(fd, addr, len) == 0) return true;
  if (errno != EINPROGRESS) return false;
  pollfd p{fd, POLLOUT, 0};
  int err = 0;
  socklen_t err_len = sizeof err;
  return ::poll(&p, 1, 500) == 1 && ::getsockopt(fd, SOL_SOCKET, SO_ERROR, &err, &err_len) == 0 &&
         err == 0;
}

// Display N on this machine: /tmp/.X11-unix/XN, or the same path in the abstract namespace
// (Linux X servers listen on both).
bool unix_display_reachable(int n) {
  const std::string path = "/tmp/.X11-unix/X" + std::to_string(n);
  for (const bool abstract : {false, true}) {
    const int fd = ::socket(AF_UNIX, SOCK_STREAM | SOCK_NONBLOCK | SOCK_CLOEXEC, 0);
    if (fd < 0) return false;
    sockaddr_un addr{};
    addr.sun_family = AF_UNIX;
    std::memcpy(addr.sun_path + (abstract ? 1 : 0), path.c_str(), path.size());
    const socklen_t len =
        static_cast<socklen_t>(offsetof(sockaddr_un, sun_path) + path.size() + (abstract ? 1 : 0));
    const bool ok = connect_with_timeout(fd, reinterpret_cast<const sockaddr*>(&addr), len);
    ::close(fd);
    if (ok) return true;
  }
  return false;
}

// Display N on `host`: TCP port 6000 + N.
bool tcp_display_reachable(const std::string& host, int n) {
  addrinfo hints{};
  hints.ai_socktype = SOCK_STREAM;
  addrinfo* res = nullptr;
  if (::getaddrinfo(host.c_str(), std::to_string(6000 + n).c_str(), &hints, &res) != 0) {
    return false;
  }
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

#ifdef POSECAL_CLI_HIGHGUI
// An X connection to `display` that xcb accepts: the server completed the X11 handshake. A
// listener that accepts and then says nothing would block xcb_connect for ever, so it runs on
// its own thread and is given up (left blocked, the process ends it) after 3 s.
std::string x_connection_error(const std::string& display) {
  auto result = std::make_shared<std::promise<std::string>>();
  std::future<std::string> answer = result->get_future();
  std::thread([display, result] {
    xcb_connection_t* c = xcb_connect(display.c_str(), nullptr);
    const int err = xcb_connection_has_error(c);
    xcb_disconnect(c);
    result->set_value(err == 0 ? ""
                               : "the X connection failed (xcb error " + std::to_string(err) + ")");
  }).detach();
  if (answer.wait_for(std::chrono::seconds(3)) != std::future_status::ready) {
    return "the X server did not complete the handshake within 3 s";
  }
  return answer.get();
}
#endif

}  // namespace

bool x_display_reachable(const std::string& display) {
  const size_t colon = display.rfind(':');
  if (colon == std::string::npos) return false;
  const std::string host = display.substr(0, colon);
  const int n = std::atoi(display.substr(colon + 1).c_str());
  if (host.empty() || host == "unix") return unix_display_reachable(n);
  return tcp_display_reachable(host, n);
}

LiveWindow::LiveWindow(bool wanted) {
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
  // Qt aborts the process when its display is not a usable X server: open a real X
  // connection before highgui is touched.
  if (m != "force") {
    const std::string why = x_connection_error(display);
    if (!why.empty()) {
      std::fprintf(stderr,
                   "posecal calibrate: DISPLAY=%s is not a usable X server (%s); headless\n",
                   display, why.c_str());
      return;
    }
  }
  enabled_ = true;
#else
  (void)wanted;
#endif
}

LiveWindow::~LiveWindow() {
#ifdef POSECAL_CLI_HIGHGUI
  if (opened_) {
    try {
      cv::destroyAllWindows();
    } catch (...) {  // a destructor must not throw; the process is ending the window anyway
    }
  }
#endif
}

bool LiveWindow::show(posecal_session* s, const Json& status) {
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
      // WINDOW_GUI_NORMAL: no Qt toolbar (zoom and pan buttons) across the picture.
      cv::namedWindow(kWindowName, cv::WINDOW_NORMAL | cv::WINDOW_GUI_NORMAL);
      cv::resizeWindow(kWindowName, std::min(w, 1280), std::min(h, 1280) * std::min(w, 1280) / w);
      opened_ = true;
    }
    cv::imshow(kWindowName, m);
    const int key = cv::waitKey(1);
    if (key == 'q' || key == 27) return false;
    if (cv::getWindowProperty(kWindowName, cv::WND_PROP_VISIBLE) < 1) return false;
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

void LiveWindow::hold_result(posecal_session* s, double seconds) {
#ifdef POSECAL_CLI_HIGHGUI
  if (!enabled_ || !opened_ || seconds <= 0) return;
  try {
    if (!show(s, fetch_status(s))) return;
    std::fprintf(stderr,
                 "posecal calibrate: the result stays on screen; press a key to close "
                 "(or wait %.0f s)\n",
                 seconds);
    const auto t0 = Clock::now();
    while (ms_since(t0) < seconds * 1000 && !interrupt_requested()) {
      if (cv::waitKey(100) >= 0) break;
      if (cv::getWindowProperty(kWindowName, cv::WND_PROP_VISIBLE) < 1) break;
    }
  } catch (const std::exception& e) {
    std::fprintf(stderr, "posecal calibrate: no result screen (%s)\n", e.what());
  }
#else
  (void)s;
  (void)seconds;
#endif
}

}  // namespace posecal::cli
