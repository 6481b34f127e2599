// A record's calibration recomputed from its stored keyframes (records_resolve.hpp).
#include "records_resolve.hpp"

#include <nlohmann/json.hpp>

#include "abi_common.hpp"
#include "session/journal.hpp"
#include "session_config.hpp"

namespace posecal::abi {

nlohmann::json prior_json(const IntrinsicsPrior& prior,
                          const std::vector<std::string>& param_names) {
  nlohmann::json mean = nlohmann::json::object(), cov = nlohmann::json::array();
  for (size_t i = 0; i < param_names.size() && i < prior.mean.size(); ++i)
    mean[param_names[i]] = prior.mean[i];
  for (Eigen::Index a = 0; a < prior.covariance.rows(); ++a) {
    nlohmann::json row = nlohmann::json::array();
    for (Eigen::Index b = 0; b < prior.covariance.cols(); ++b)
      row.push_back(prior.covariance(a, b));
    cov.push_back(row);
  }
  return {{"names", prior.names},
          {"mean", mean},
          {"covariance", cov},
          {"noise_px", prior.noise_px},
          {"image_width", prior.image_size.width},
          {"image_height", prior.image_size.height}};
}

std::optional<IntrinsicsPrior> prior_from_json(const nlohmann::json& result, LensModel lens) {
  if (!result.is_object() || !result.contains("prior") || !result["prior"].is_object())
    return std::nullopt;
  const nlohmann::json& p = result["prior"];
  if (!p.value("used", false)) return std::nullopt;
  auto bad = [](const std::string& what) {
    throw Error(ErrorCode::kInvalidArgument, "the record's prior: " + what);
  };
  IntrinsicsPrior out;
  try {
    out.names = p.at("names").get<std::vector<std::string>>();
    for (const std::string& n : intrinsic_names(lens))
      out.mean.push_back(p.at("mean").at(n).get<double>());
    const nlohmann::json& c = p.at("covariance");
    const auto m = static_cast<Eigen::Index>(out.names.size());
    if (!c.is_array() || static_cast<Eigen::Index>(c.size()) != m)
      bad("the covariance is not " + std::to_string(m) + " rows");
    out.covariance.resize(m, m);
    for (Eigen::Index a = 0; a < m; ++a) {
      if (!c[a].is_array() || static_cast<Eigen::Index>(c[a].size()) != m)
        bad("a covariance row is not " + std::to_string(m) + " values");
      for (Eigen::Index b = 0; b < m; ++b) out.covariance(a, b) = c[a][b].get<double>();
    }
    out.noise_px = p.at("noise_px").get<double>();
    out.image_size = cv::Size(p.at("image_width").get<int>(), p.at("image_height").get<int>());
  } catch (const nlohmann::json::exception& e) {
    bad(e.what());
  }
  return out;
}

Resolved resolve(const RunRecord& r) {
  const std::string& run = r.summary.identity.run_id;
  const nlohmann::json config = parse_options(r.summary.identity.config.c_str(),
                                              session_config_keys(), "recorded session config");
  SessionOptions options = session_options_from_json(config);
  // A session with the fleet prior: the prior it had (its result keeps it), not today's fleet.
  const nlohmann::json result = nlohmann::json::parse(r.result, nullptr, false);
  options.engine.calibration.prior = prior_from_json(result, options.engine.calibration.lens_model);
  if (options.engine.calibration.prior && result["prior"].contains("accuracy_px") &&
      result["prior"]["accuracy_px"].is_number()) {
    options.engine.accuracy_px = result["prior"]["accuracy_px"].get<double>();
  }
  const size_t needed = options.engine.calibration.prior ? 1 : 2;
  if (r.keyframes.size() < needed || r.image_width <= 0 || r.image_height <= 0) {
    throw Error(ErrorCode::kState, "run " + run + " has " + std::to_string(r.keyframes.size()) +
                                       " keyframes: a calibration needs " +
                                       (needed == 1 ? "one" : "two"));
  }
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
