// The robot protocol of `calibrate --camera --guide stdio`: each new target pose as one JSON line
// on stdout, then one line from the controller on stdin ('reached' or {"reached": true},
// 'skip', 'abort').
#pragma once

#include <string>
#include <vector>

#include "cli_common.hpp"

namespace posecal::cli {

// Reads lines from a file descriptor with a timeout (poll + read: no stdio buffering, so the
// wait is bounded).
class LineReader {
 public:
  explicit LineReader(int fd) : fd_(fd) {}
  enum class Result { kLine, kEof, kTimeout };
  Result next(std::string* line, int timeout_ms);

 private:
  bool take_line(std::string* line);
  // Waits up to `timeout_ms` for input and appends what arrived (nothing on a timeout).
  void fill(long long timeout_ms);

  int fd_;
  std::string buffer_;
  bool eof_ = false;
};

enum class Reply { kReached, kSkip, kAbort, kInvalid };

Reply parse_reply(const std::string& line);

// The CLI's side of the protocol for one session.
class RobotLink {
 public:
  RobotLink(int fd, int reply_timeout_ms) : replies_(fd), reply_timeout_ms_(reply_timeout_ms) {}
  // After a step: when the session has a new target, prints it, waits for the controller's
  // reply and acts on it. Throws Failure when the controller aborts, goes away or is silent.
  void after_step(posecal_session* s, const Json& status);

 private:
  void await_reply(posecal_session* s);

  LineReader replies_;
  int reply_timeout_ms_;
  std::vector<double> last_target_;
  int serial_ = 0;
};

}  // namespace posecal::cli
