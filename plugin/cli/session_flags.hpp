// The session-config flags of simulate, calibrate --camera and station: one flag per key of the
// library's table of session keys (core/session/session_keys.def), so a key added there is a
// flag here without another edit.
#pragma once

#include <memory>
#include <string>
#include <vector>

#include "cli_common.hpp"

namespace posecal::cli {

class SessionFlags {
 public:
  // Adds the flags to `cmd` under the help group "session config" (CLI11 binds them to this
  // object: it must outlive the parse).
  explicit SessionFlags(CLI::App* cmd);
  ~SessionFlags();
  SessionFlags(const SessionFlags&) = delete;
  SessionFlags& operator=(const SessionFlags&) = delete;

  // The config for posecal_session_open: only the keys given on the command line, so the
  // library's defaults (and its sim:// adjustments) apply to the rest.
  Json config() const;

 private:
  struct Flag;
  std::vector<std::unique_ptr<Flag>> flags_;  // owned one by one: CLI11 keeps their addresses
};

}  // namespace posecal::cli
