#include "quality_gate.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>

#include "common/error.hpp"
#include "common/regular_file.hpp"

namespace posecal::abi {

namespace {

[[noreturn]] void bad_spec(const std::string& path, const std::string& what) {
  throw Error(ErrorCode::kInvalidArgument, "quality spec '" + path + "': " + what);
}

double positive(const std::string& path, const nlohmann::json& j, const std::string& key) {
  const auto& v = j.at(key);
  if (!v.is_number() || !std::isfinite(v.get<double>()) || v.get<double>() <= 0)
    bad_spec(path, "'" + key + "' must be a positive number");
  return v.get<double>();
}

std::string figure(double v) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "%.4g", v);
  return buf;
}

ParameterLimit parameter_limit(const std::string& path, const std::string& name,
                               const nlohmann::json& j) {
  const std::string where = "parameters." + name;
  if (!j.is_object()) bad_spec(path, "'" + where + "' must be an object {\"nominal\", \"tolerance\"}");
  ParameterLimit p;
  for (const auto& item : j.items()) {
    const std::string& k = item.key();
    if (k == "nominal") {
      if (!item.value().is_number() || !std::isfinite(item.value().get<double>()))
        bad_spec(path, "'" + where + ".nominal' must be a number");
      p.nominal = item.value().get<double>();
    } else if (k == "tolerance") {
      p.tolerance = positive(path, j, k);
    } else if (k == "tolerance_abs") {
      p.tolerance_abs = positive(path, j, k);
    } else {
      bad_spec(path, "unknown key '" + where + "." + k + "' (known: nominal, tolerance, tolerance_abs)");
    }
  }
  if (!j.contains("nominal")) bad_spec(path, "'" + where + "' needs 'nominal'");
  if (!p.tolerance && !p.tolerance_abs)
    bad_spec(path, "'" + where + "' needs 'tolerance' (relative) or 'tolerance_abs'");
  return p;
}

}  // namespace

QualitySpec read_quality_spec(const std::string& path,
                              const std::vector<std::string>& parameter_names) {
  return parse_quality_spec(read_regular_file(path, static_cast<size_t>(kMaxSpecFileBytes),
                                              "quality spec", ErrorCode::kNotFound),
                            path, parameter_names);
}

QualitySpec parse_quality_spec(const std::string& text, const std::string& path,
                               const std::vector<std::string>& parameter_names) {
  if (text.size() > static_cast<size_t>(kMaxSpecFileBytes))
    bad_spec(path, "larger than the limit of " + std::to_string(kMaxSpecFileBytes) + " bytes");
  nlohmann::json j;
  try {
    j = nlohmann::json::parse(text);
  } catch (const nlohmann::json::exception& e) {
    // parse_error, and out_of_range for a number beyond a double (found by fuzz_quality_spec).
    bad_spec(path, std::string("not valid JSON: ") + e.what());
  }
  if (!j.is_object()) bad_spec(path, "must be a JSON object");
  QualitySpec spec;
  spec.path = path;
  for (const auto& item : j.items()) {
    const std::string& k = item.key();
    if (k == "max_expected_error_px") {
      spec.max_expected_error_px = positive(path, j, k);
    } else if (k == "max_eps_res_px") {
      spec.max_eps_res_px = positive(path, j, k);
    } else if (k == "max_seconds") {
      spec.max_seconds = positive(path, j, k);
    } else if (k == "max_keyframes") {
      if (!item.value().is_number_integer() || item.value().get<long long>() < 2 ||
          item.value().get<long long>() > 100000)
        bad_spec(path, "'max_keyframes' must be an integer in [2, 100000]");
      spec.max_keyframes = static_cast<int>(item.value().get<long long>());
    } else if (k == "require_converged") {
      if (!item.value().is_boolean()) bad_spec(path, "'require_converged' must be true or false");
      spec.require_converged = item.value().get<bool>();
    } else if (k == "parameters") {
      if (!item.value().is_object()) bad_spec(path, "'parameters' must be an object");
      for (const auto& p : item.value().items()) {
        if (std::find(parameter_names.begin(), parameter_names.end(), p.key()) ==
            parameter_names.end()) {
          std::string list;
          for (const auto& n : parameter_names) list += (list.empty() ? "" : " ") + n;
          bad_spec(path, "'parameters." + p.key() + "': the lens model has no such parameter (" +
                             list + ")");
        }
        spec.parameters[p.key()] = parameter_limit(path, p.key(), p.value());
      }
    } else {
      bad_spec(path, "unknown key '" + k +
                         "' (known: max_expected_error_px, max_eps_res_px, parameters, "
                         "max_keyframes, max_seconds, require_converged)");
    }
  }
  return spec;
}

nlohmann::json quality_verdict(const QualitySpec& spec, const nlohmann::json& result,
                               int keyframes, double seconds) {
  std::vector<std::string> reasons;
  // A figure of the result; NaN where it is missing or not a number (JSON null).
  const auto value = [&](const std::string& key) {
    const auto it = result.find(key);
    return it != result.end() && it->is_number() ? it->get<double>() : std::nan("");
  };
  if (result.value("interrupted", false)) reasons.push_back("the calibration was interrupted");
  if (spec.require_converged && !result.value("converged", false))
    reasons.push_back("the calibration did not converge");
  const auto at_most = [&](const char* name, double v, const std::optional<double>& limit,
                           const char* unit) {
    if (!limit) return;
    if (!std::isfinite(v)) {
      reasons.push_back(std::string(name) + " is unknown (limit " + figure(*limit) + unit + ")");
    } else if (v > *limit) {
      reasons.push_back(std::string(name) + " " + figure(v) + unit + " > " + figure(*limit) +
                        unit);
    }
  };
  at_most("expected_error_px", value("expected_error_px"), spec.max_expected_error_px, " px");
  at_most("eps_res", value("eps_res"), spec.max_eps_res_px, " px");
  at_most("seconds", seconds, spec.max_seconds, " s");
  if (spec.max_keyframes && keyframes > *spec.max_keyframes) {
    reasons.push_back("keyframes " + std::to_string(keyframes) + " > " +
                      std::to_string(*spec.max_keyframes));
  }
  for (const auto& [name, limit] : spec.parameters) {
    const double v = value(name);
    const double off = std::fabs(v - limit.nominal);
    if (!std::isfinite(v)) {
      reasons.push_back(name + " is unknown");
      continue;
    }
    if (limit.tolerance && off > *limit.tolerance * std::fabs(limit.nominal)) {
      reasons.push_back(name + " " + figure(v) + " is " + figure(off) + " from nominal " +
                        figure(limit.nominal) + ", more than " +
                        figure(100 * *limit.tolerance) + "%");
    }
    if (limit.tolerance_abs && off > *limit.tolerance_abs) {
      reasons.push_back(name + " " + figure(v) + " is " + figure(off) + " from nominal " +
                        figure(limit.nominal) + ", more than " + figure(*limit.tolerance_abs));
    }
  }
  return {{"verdict", reasons.empty() ? "pass" : "fail"},
          {"verdict_reasons", reasons},
          {"spec", spec.path}};
}

}  // namespace posecal::abi
