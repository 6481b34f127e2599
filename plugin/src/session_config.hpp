// The session config of posecal_session_open: the JSON object read key by key through the one table
// of session keys (core/session/session_keys.def).
#pragma once

#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "session/session_options.hpp"

namespace posecal::abi {

// The keys posecal_session_open accepts.
std::vector<std::string> session_config_keys();

// Options from a parsed config object (only its table keys; parse_options has refused others).
// Throws Error(kInvalidArgument) "session config: ..." naming the key.
SessionOptions session_options_from_json(const nlohmann::json& config);

}  // namespace posecal::abi
