// A record's calibration recomputed from its stored keyframes (records_resolve.hpp).
#include "records_resolve.hpp"

#include <nlohmann/json.hpp>

#include "abi_common.hpp"
#include "session/journal.hpp"
#include "session_config.hpp"

namespace posecal::abi {

Resolved resolve(const RunRecord& r) {
  const std::string& run = r.summary.identity.run_id;
  if (r.keyframes.size() < 2 || r.image_width <= 0 || r.image_height <= 0) {
    throw Error(ErrorCode::kState, "run " + run + " has " + std::to_string(r.keyframes.size()) +
                                       " keyframes: a calibration needs two");
  }
  const nlohmann::json config = parse_options(r.summary.identity.config.c_str(),
                                              session_config_keys(), "recorded session config");
  const SessionOptions options = session_options_from_json(config);
  std::vector<KeyframeRecord> keyframes;
  for (const StoredKeyframe& k : r.keyframes) keyframes.push_back(keyframe_from_json(k.record));
  Resolved out;
  out.engine =
      std::make_unique<CalibrationEngine>(cv::Size(r.image_width, r.image_height), options.engine);
  out.identical_to_last_keyframe = out.engine->restore(keyframes);
  if (!out.engine->result()) {
    throw Error(ErrorCode::kDegenerate, "run " + run + ": its keyframes give no calibration");
  }
  return out;
}

}  // namespace posecal::abi
