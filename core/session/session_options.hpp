// The options of a calibration session and their keys (session_keys.def): what
// posecal_session_open's config sets, read and written by key so that the C ABI's parser, the
// CLI's flags and the documentation come from one table.
#pragma once

#include <optional>
#include <string>
#include <variant>
#include <vector>

#include "select/engine.hpp"

namespace posecal {

struct SessionOptions {
  EngineOptions engine;
  bool lock_settings = true;  // lock exposure, gain and focus before the first frame
  std::string journal;        // the session journal's path ("" = none; session/journal.hpp)
  bool journal_images = false;
  bool resume = true;         // resume an existing journal (false: set it aside, start afresh)
  std::string spec;           // a quality specification's path ("" = none; plugin/src/quality_gate)
  std::string records;        // the calibration record store ("" = none; records/record_store)
  std::string records_spool;
  double fleet_outlier_probability = 0.001;  // records/fleet.hpp
  // "prior": "fleet": start from the fleet's mean and weigh the calibration with its spread
  // (records/fleet.hpp, fleet_prior; plugin/src/session_abi.cpp builds it from `records`).
  bool fleet_prior = false;
  std::string run_id;         // the record's run id ("" = a new UUID)
  std::string station_id, operator_id, lens_id;  // recorded with the run
  bool is_valid(std::string* error) const { return engine.is_valid(error); }
};

enum class SessionKeyKind { kNumber, kInteger, kOptionalNumber, kBool, kChoice, kText, kTextList };

struct SessionKeyInfo {
  const char* key;
  SessionKeyKind kind;
  double lo, hi;             // kNumber, kInteger, kOptionalNumber: the inclusive range
  const char* choices;       // kChoice: "a|b|..."
  const char* default_text;  // as the JSON value is written (kChoice: the name)
  const char* cli_alias;     // an older CLI flag name, "" if none ("!name": sets a Bool false)
  const char* doc;
};
// Every key, in the table's order.
const std::vector<SessionKeyInfo>& session_keys();
// The key's description; nullptr for an unknown key.
const SessionKeyInfo* find_session_key(const std::string& key);

// A key's value: kNumber double, kInteger long long, kOptionalNumber double or std::monostate
// (unset), kBool bool, kChoice and kText string, kTextList vector of strings.
using SessionKeyValue =
    std::variant<double, long long, bool, std::string, std::vector<std::string>, std::monostate>;

// Sets the key. Throws Error(kInvalidArgument) naming the key for an unknown key, a value of the
// wrong kind, out of range, not one of the choices, or a board spec that does not parse.
void set_session_key(SessionOptions* options, const std::string& key, const SessionKeyValue& value);
// The key's current value.
SessionKeyValue get_session_key(const SessionOptions& options, const std::string& key);

}  // namespace posecal
