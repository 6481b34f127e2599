#include "session_config.hpp"

#include "common/error.hpp"

namespace posecal::abi {

namespace {

// A JSON value as the table's value type, by its JSON type (the table checks the kind).
SessionKeyValue key_value(const std::string& key, const nlohmann::json& v) {
  if (v.is_null()) return std::monostate{};  // unsets an optional key; refused by the others
  if (v.is_boolean()) return v.get<bool>();
  if (v.is_number_integer()) return v.get<long long>();
  if (v.is_number()) return v.get<double>();
  if (v.is_string()) return v.get<std::string>();
  if (v.is_array()) {
    std::vector<std::string> list;
    for (const auto& e : v) {
      if (!e.is_string()) {
        throw Error(ErrorCode::kInvalidArgument, "'" + key + "' must be an array of strings");
      }
      list.push_back(e.get<std::string>());
    }
    return list;
  }
  throw Error(ErrorCode::kInvalidArgument, "'" + key + "' has a value of the wrong type (" + v.type_name() + ")");
}

}  // namespace

std::vector<std::string> session_config_keys() {
  std::vector<std::string> keys;
  for (const SessionKeyInfo& k : session_keys()) keys.emplace_back(k.key);
  return keys;
}

SessionOptions session_options_from_json(const nlohmann::json& config) {
  SessionOptions o;
  try {
    for (const SessionKeyInfo& k : session_keys()) {
      if (config.contains(k.key)) set_session_key(&o, k.key, key_value(k.key, config.at(k.key)));
    }
  } catch (const Error& e) {
    throw Error(e.code(), std::string("session config: ") + e.what());
  }
  std::string why;
  if (!o.is_valid(&why)) throw Error(ErrorCode::kInvalidArgument, "session config: " + why);
  return o;
}

}  // namespace posecal::abi
