// Private network namespaces for tests and programs with several simulated GigE Vision cameras:
// each simulator needs its own address, which a private network namespace (unshare -n; root
// only) provides without touching the machine's interfaces. A program re-executes itself inside
// one and there brings the namespace's loopback up and adds 127.0.0.2 ... 127.0.0.N.
#pragma once

#include <signal.h>
#include <spawn.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cerrno>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <string>
#include <thread>
#include <vector>

extern char** environ;

namespace posecal::testing {

// Identity of this process's network namespace ("" if unknown).
inline std::string netns_inode() {
  struct stat st {};
  if (::stat("/proc/self/ns/net", &st) != 0) return "";
  return std::to_string(st.st_ino);
}

inline std::string self_exe() {
  char buf[4096];
  const ssize_t n = ::readlink("/proc/self/exe", buf, sizeof buf - 1);
  return n > 0 ? std::string(buf, static_cast<size_t>(n)) : "";
}

// Runs a program (PATH lookup) with extra environment and waits for it: its exit status, 126 if
// it could not be started, -1 if it was killed after timeout_ms (< 0: no limit).
inline int run(const std::vector<std::string>& args, int timeout_ms,
               const std::vector<std::string>& extra_env = {}) {
  std::vector<char*> argv;
  for (const auto& a : args) argv.push_back(const_cast<char*>(a.c_str()));
  argv.push_back(nullptr);
  std::vector<std::string> env_strings = extra_env;
  for (char** e = environ; *e != nullptr; ++e) env_strings.emplace_back(*e);
  std::vector<char*> envp;
  for (auto& e : env_strings) envp.push_back(e.data());
  envp.push_back(nullptr);
  pid_t pid = 0;
  if (::posix_spawnp(&pid, argv[0], nullptr, nullptr, argv.data(), envp.data()) != 0) return 126;
  const auto t0 = std::chrono::steady_clock::now();
  int status = 0;
  for (;;) {
    const pid_t r = ::waitpid(pid, &status, timeout_ms < 0 ? 0 : WNOHANG);
    if (r == pid) break;
    if (r < 0 && errno != EINTR) return 126;
    if (std::chrono::steady_clock::now() - t0 > std::chrono::milliseconds(timeout_ms)) {
      ::kill(pid, SIGKILL);
      ::waitpid(pid, &status, 0);
      return -1;
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  return WIFEXITED(status) ? WEXITSTATUS(status) : 128 + WTERMSIG(status);
}

constexpr const char* kParentNetnsVariable = "POSECAL_BENCH_PARENT_NETNS";

// For programs (not tests). Outside: re-executes this program under `unshare -n` and returns its
// exit status (77 when not root). Inside: returns -1 after checking that the namespace is
// private, bringing its loopback up and adding 127.0.0.2 ... 127.0.0.<addresses>; 1 on failure.
inline int enter_private_network(int argc, char** argv, int addresses) {
  const char* parent = std::getenv(kParentNetnsVariable);
  if (parent == nullptr) {
    if (::geteuid() != 0) {
      std::fprintf(stderr,
                   "needs root: each simulator needs its own address, which only a "
                   "private network namespace (unshare -n) provides\n");
      return 77;
    }
    std::vector<std::string> cmd = {"unshare", "-n", "--", self_exe()};
    for (int i = 1; i < argc; ++i) cmd.emplace_back(argv[i]);
    return run(cmd, -1, {std::string(kParentNetnsVariable) + "=" + netns_inode()});
  }
  // Never add addresses to the machine's own interfaces.
  if (netns_inode() == parent) {
    std::fprintf(stderr, "not in a private network namespace\n");
    return 1;
  }
  if (run({"ip", "link", "set", "lo", "up"}, 5000) != 0) {
    std::fprintf(stderr, "cannot bring the namespace's loopback up\n");
    return 1;
  }
  for (int i = 2; i <= addresses; ++i) {
    if (run({"ip", "addr", "add", "127.0.0." + std::to_string(i) + "/8", "dev", "lo"}, 5000) != 0) {
      std::fprintf(stderr, "cannot add 127.0.0.%d to the namespace's loopback\n", i);
      return 1;
    }
  }
  return -1;
}

}  // namespace posecal::testing
