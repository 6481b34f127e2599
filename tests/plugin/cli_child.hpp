// Running the posecal command line from the plugin tests: to completion through the shell
// (run_cli, shell), or as a child process whose output the test reads line by line while it
// sends it signals (CliChild). The test target defines POSECAL_CLI, the CLI's path.
#pragma once

#include <fcntl.h>
#include <poll.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <array>
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <functional>
#include <string>
#include <vector>

namespace posecal_test {

struct CliRun {
  int status = -1;  // the exit code; -1 if the CLI died of a signal
  std::string out;
};

// Runs a shell command line; stdout and stderr as the command line redirects them.
inline CliRun shell_raw(const std::string& cmd) {
  CliRun r;
  FILE* p = popen(cmd.c_str(), "r");
  if (!p) return r;
  std::array<char, 4096> buf;
  size_t n;
  while ((n = fread(buf.data(), 1, buf.size(), p)) > 0) r.out.append(buf.data(), n);
  const int rc = pclose(p);
  r.status = WIFEXITED(rc) ? WEXITSTATUS(rc) : -1;
  return r;
}

// Runs a shell command line without DISPLAY; stdout and stderr merged into `out`.
inline CliRun shell(const std::string& cmd) {
  return shell_raw("{ unset DISPLAY; " + cmd + "; } 2>&1");
}

// Runs the CLI with `args` through the shell; stderr is merged into `out` unless
// `stdout_only`. `env` replaces the default environment change (no display).
inline CliRun run_cli(const std::string& args, bool stdout_only = false,
                      const std::string& env = "-u DISPLAY") {
  return shell_raw("env " + env + " " + std::string(POSECAL_CLI) + " " + args +
                   (stdout_only ? " 2>/dev/null" : " 2>&1"));
}

// The CLI as a child process without DISPLAY: one of its streams (`read`) comes to the test
// through a pipe, read line by line; the other goes to `other_file`. Killed and reaped when it
// goes out of scope.
class CliChild {
 public:
  enum class Stream { kStdout, kStderr };

  CliChild(const std::vector<std::string>& args, Stream read,
           const std::filesystem::path& other_file) {
    int fds[2];
    if (::pipe(fds) != 0) return;
    pid_ = ::fork();
    if (pid_ == 0) {
      const int piped = read == Stream::kStdout ? STDOUT_FILENO : STDERR_FILENO;
      const int filed = read == Stream::kStdout ? STDERR_FILENO : STDOUT_FILENO;
      ::dup2(fds[1], piped);
      const int file = ::open(other_file.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
      ::dup2(file, filed);
      ::close(fds[0]);
      ::unsetenv("DISPLAY");
      const std::string cli = POSECAL_CLI;
      std::vector<char*> argv{const_cast<char*>(cli.c_str())};
      for (const auto& a : args) argv.push_back(const_cast<char*>(a.c_str()));
      argv.push_back(nullptr);
      ::execv(cli.c_str(), argv.data());
      ::_exit(127);
    }
    ::close(fds[1]);
    in_ = fds[0];
  }
  CliChild(const CliChild&) = delete;
  CliChild& operator=(const CliChild&) = delete;
  ~CliChild() {
    if (pid_ > 0 && !reaped_) {
      ::kill(pid_, SIGKILL);
      ::waitpid(pid_, nullptr, 0);
    }
    if (in_ >= 0) ::close(in_);
  }

  // Reads lines until `done(line)` holds for one or `timeout_s` passes; false on timeout or at
  // the end of the output.
  bool wait_for(const std::function<bool(const std::string&)>& done, double timeout_s) {
    using Clock = std::chrono::steady_clock;
    const auto t0 = Clock::now();
    while (std::chrono::duration<double>(Clock::now() - t0).count() < timeout_s) {
      for (size_t nl; (nl = buf_.find('\n')) != std::string::npos;) {
        const std::string line = buf_.substr(0, nl);
        buf_.erase(0, nl + 1);
        lines_.push_back(line);
        if (done(line)) return true;
      }
      pollfd p{in_, POLLIN, 0};
      if (::poll(&p, 1, 100) <= 0) continue;
      char chunk[8192];
      const ssize_t n = ::read(in_, chunk, sizeof chunk);
      if (n <= 0) return false;
      buf_.append(chunk, static_cast<size_t>(n));
    }
    return false;
  }
  void signal(int signo) const { ::kill(pid_, signo); }
  void kill9() {
    ::kill(pid_, SIGKILL);
    ::waitpid(pid_, nullptr, 0);
    reaped_ = true;
  }
  // The raw wait status, after draining the output for up to `timeout_s`; a child that has
  // not exited 10 s after that (its output can end before its exit) is killed (WIFSIGNALED).
  int wait_status(double timeout_s) {
    wait_for([](const std::string&) { return false; }, timeout_s);
    int status = 0;
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(10);
    pid_t done = 0;
    while ((done = ::waitpid(pid_, &status, WNOHANG)) == 0 &&
           std::chrono::steady_clock::now() < deadline) {
      ::usleep(10000);
    }
    if (done == 0) {
      ::kill(pid_, SIGKILL);
      ::waitpid(pid_, &status, 0);
    }
    reaped_ = true;
    return status;
  }
  // The exit code as wait_status() ends it; -1 if the child died of a signal.
  int finish(double timeout_s) {
    const int status = wait_status(timeout_s);
    return WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  }
  const std::vector<std::string>& lines() const { return lines_; }
  std::string log() const {
    std::string all;
    for (const auto& l : lines_) all += l + "\n";
    return all;
  }

 private:
  pid_t pid_ = -1;
  int in_ = -1;
  bool reaped_ = false;
  std::string buf_;
  std::vector<std::string> lines_;
};

}  // namespace posecal_test
