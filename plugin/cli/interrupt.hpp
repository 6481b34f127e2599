// SIGINT and SIGTERM in the command line: the first signal asks every running calibration to
// stop gracefully (each command interrupts its sessions through posecal_session_interrupt,
// saves what was calibrated so far marked "interrupted" and exits with 128 + the signal's
// number: 130 for SIGINT, 143 for SIGTERM); a second signal ends the process at once.
#pragma once

namespace posecal::cli {

// Installs the handlers (once per process; main() calls it).
void install_interrupt_handlers();
// True once SIGINT or SIGTERM has arrived.
bool interrupt_requested();
// 128 + the first signal's number; 0 if none arrived.
int interrupt_exit_code();

}  // namespace posecal::cli
