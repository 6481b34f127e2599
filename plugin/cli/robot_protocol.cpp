#include "robot_protocol.hpp"

#include <poll.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>

namespace posecal::cli {

namespace {

// Text from outside (the controller's line) as valid UTF-8: invalid bytes become U+FFFD, so the
// JSON printed with it is valid and nlohmann's dump never throws.
std::string valid_utf8(const std::string& text) {
  return Json::parse(Json(text).dump(-1, ' ', false, Json::error_handler_t::replace))
      .get<std::string>();
}

}  // namespace

bool LineReader::take_line(std::string* line) {
  const size_t nl = buffer_.find('\n');
  if (nl != std::string::npos) {
    *line = buffer_.substr(0, nl);
    buffer_.erase(0, nl + 1);
    if (!line->empty() && line->back() == '\r') line->pop_back();
    return true;
  }
  if (eof_ && !buffer_.empty()) {  // a last line without '\n'
    *line = std::move(buffer_);
    buffer_.clear();
    return true;
  }
  return false;
}

void LineReader::fill(long long timeout_ms) {
  pollfd p{fd_, POLLIN, 0};
  const int r = ::poll(&p, 1, static_cast<int>(std::min<long long>(timeout_ms, 1000000)));
  if (r <= 0) return;  // timeout or EINTR: the caller re-checks its deadline
  char buf[4096];
  const ssize_t n = ::read(fd_, buf, sizeof buf);
  if (n < 0 && errno == EINTR) return;
  if (n <= 0) {
    eof_ = true;
    return;
  }
  buffer_.append(buf, static_cast<size_t>(n));
  if (buffer_.size() > (1u << 20)) throw Failure{POSECAL_E_INVALID_ARGUMENT, "line too long"};
}

LineReader::Result LineReader::next(std::string* line, int timeout_ms) {
  const auto deadline = Clock::now() + std::chrono::milliseconds(timeout_ms);
  while (true) {
    if (take_line(line)) return Result::kLine;
    if (eof_) return Result::kEof;
    const auto left =
        std::chrono::duration_cast<std::chrono::milliseconds>(deadline - Clock::now()).count();
    if (left <= 0) return Result::kTimeout;
    fill(left);
  }
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

void RobotLink::after_step(posecal_session* s, const Json& status) {
  double r[3], t[3];
  if (posecal_session_target_pose(s, r, t) != POSECAL_OK) return;
  const std::vector<double> now{r[0], r[1], r[2], t[0], t[1], t[2]};
  if (now == last_target_) return;
  last_target_ = now;
  write_line(stdout, Json{{"event", "target"},
                          {"serial", ++serial_},
                          {"rvec", {r[0], r[1], r[2]}},
                          {"tvec", {t[0], t[1], t[2]}},
                          {"frame", "T_cam_board"},
                          {"state", status["state"]},
                          {"keyframes", status["keyframes"]},
                          {"target_parameter", status["target_parameter"]}});
  await_reply(s);
}

void RobotLink::await_reply(posecal_session* s) {
  while (true) {
    std::string line;
    const LineReader::Result rr = replies_.next(&line, reply_timeout_ms_);
    if (rr == LineReader::Result::kEof) {
      throw Failure{POSECAL_E_STATE, "--guide stdio: the controller closed stdin"};
    }
    if (rr == LineReader::Result::kTimeout) {
      throw Failure{POSECAL_E_TIMEOUT, "--guide stdio: no reply from the controller within " +
                                           std::to_string(reply_timeout_ms_ / 1000) + " s"};
    }
    const Reply reply = parse_reply(line);
    if (reply == Reply::kAbort) throw Failure{POSECAL_E_STATE, "aborted by the controller"};
    posecal_status rs = POSECAL_OK;
    if (reply == Reply::kReached) rs = posecal_session_pose_reached(s);
    if (reply == Reply::kSkip) rs = posecal_session_skip_target(s);
    if (reply != Reply::kInvalid && rs == POSECAL_OK) return;
    write_line(stdout, Json{{"event", "protocol_error"},
                            {"line", valid_utf8(line)},
                            {"message", reply == Reply::kInvalid
                                            ? "expected 'reached', 'skip', 'abort' or a JSON "
                                              "object {\"reached\": true}"
                                            : valid_utf8(posecal_last_error())}});
  }
}

}  // namespace posecal::cli
