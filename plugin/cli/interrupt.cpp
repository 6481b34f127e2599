#include "interrupt.hpp"

#include <signal.h>

#include <atomic>

namespace posecal::cli {

namespace {

// Written by the handler, read by every session thread of a station: a lock-free atomic (safe
// in a signal handler) rather than a volatile sig_atomic_t, which is only safe for the thread the
// signal interrupts (ThreadSanitizer reported the station threads' reads as a data race).
std::atomic<int> g_signal{0};
static_assert(std::atomic<int>::is_always_lock_free, "the signal flag must be lock-free");

// Async-signal-safe: a flag the command loops poll between frames, or, the second time, the
// default action (the process ends by the signal, as a user pressing Ctrl-C twice expects).
void on_signal(int signo) {
  int none = 0;
  if (!g_signal.compare_exchange_strong(none, signo)) {
    ::signal(signo, SIG_DFL);
    ::raise(signo);
  }
}

}  // namespace

void install_interrupt_handlers() {
  struct sigaction sa {};
  sa.sa_handler = on_signal;
  sigemptyset(&sa.sa_mask);
  // SA_RESTART: the libraries' blocking calls (Aravis, V4L2, reads) go on; the loops notice the
  // flag within one step's timeout.
  sa.sa_flags = SA_RESTART;
  ::sigaction(SIGINT, &sa, nullptr);
  ::sigaction(SIGTERM, &sa, nullptr);
}

bool interrupt_requested() { return g_signal.load() != 0; }

int interrupt_exit_code() {
  const int signo = g_signal.load();
  return signo != 0 ? 128 + signo : 0;
}

}  // namespace posecal::cli
