#include "interrupt.hpp"

#include <signal.h>

namespace posecal::cli {

namespace {

volatile sig_atomic_t g_signal = 0;

// Async-signal-safe: a flag the command loops poll between frames, or, the second time, the
// default action (the process ends by the signal, as a user pressing Ctrl-C twice expects).
void on_signal(int signo) {
  if (g_signal != 0) {
    ::signal(signo, SIG_DFL);
    ::raise(signo);
    return;
  }
  g_signal = signo;
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

bool interrupt_requested() { return g_signal != 0; }

int interrupt_exit_code() { return g_signal != 0 ? 128 + g_signal : 0; }

}  // namespace posecal::cli
