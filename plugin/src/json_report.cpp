#include "json_report.hpp"

#include <cmath>
#include <optional>

#include "abi_common.hpp"
#include "calib/expected_error.hpp"
#include "common/error.hpp"
#include "io/model_file.hpp"
#include "io/result_file.hpp"

namespace posecal::abi {

nlohmann::json device_json(const DeviceInfo& d) {
  return {{"uri", d.uri},
          {"backend", d.backend},
          {"id", d.id},
          {"vendor", d.vendor},
          {"model", d.model},
          {"serial", d.serial},
          {"transport", d.transport}};
}

namespace {

// The leading n x n block of `m` as a list of rows.
nlohmann::json rows_json(const Eigen::MatrixXd& m, int n) {
  nlohmann::json out = nlohmann::json::array();
  for (int a = 0; a < n; ++a) {
    nlohmann::json row = nlohmann::json::array();
    for (int b = 0; b < n; ++b) row.push_back(number(m(a, b)));
    out.push_back(row);
  }
  return out;
}

}  // namespace

nlohmann::json calibration_json(const CalibrationResult& r) {
  nlohmann::json j;
  const auto& names = r.model.param_names();
  nlohmann::json std_scaled, std_unit, iod, fixed;
  for (size_t i = 0; i < names.size(); ++i) {
    j[names[i]] = number(r.model.params()[i]);
    std_scaled[names[i]] = number(r.std_scaled[i]);
    std_unit[names[i]] = number(r.std_unit[i]);
    iod[names[i]] = number(r.index_of_dispersion[i]);
    fixed[names[i]] = static_cast<bool>(r.fixed[i]);
  }
  j["model"] = lens_model_name(r.model.lens_model());
  j["image_width"] = r.model.width();
  j["image_height"] = r.model.height();
  j["std"] = std_scaled;
  j["std_unit"] = std_unit;
  j["index_of_dispersion"] = iod;
  j["fixed"] = fixed;
  // Parameters the keyframes did not determine, held at their value (CalibrationResult::held).
  j["held"] = r.held;
  if (!r.held.empty()) j["held_reason"] = r.held_reason;
  j["rms"] = number(r.rms_px);
  j["eps_res"] = number(r.rms_px);
  j["residual_sigma"] = number(std::sqrt(r.residual_variance));
  nlohmann::json per_frame = nlohmann::json::array();
  for (double v : r.frame_rms_px) per_frame.push_back(number(v));
  j["per_frame_rms"] = per_frame;
  j["points"] = r.num_points;
  j["iterations"] = r.iterations;
  j["solver_converged"] = r.solver_converged();
  j["solver_termination"] = solver_termination_name(r.termination);
  const int n = static_cast<int>(names.size());
  j["covariance"] = rows_json(r.covariance_scaled(), n);
  j["covariance_order"] = names;
  // With coefficients held: the covariance with them free under their prior, scaled likewise
  // (CalibrationResult::held_covariance); the expected error is taken over it.
  if (r.has_held_covariance()) {
    j["held_covariance"] = rows_json(r.held_covariance_scaled(), n);
  }
  const ExpectedError e = expected_error(r);
  j["expected_error_px"] = number(e.rms_px);
  j["expected_error_unit_px"] = number(e.rms_unit_px);
  j["expected_error_mean_px"] = number(e.mean_px);
  j["expected_error_p90_px"] = number(e.p90_px);
  j["expected_error_limited_by"] =
      e.limiting_param >= 0 ? nlohmann::json(names[e.limiting_param]) : nlohmann::json(nullptr);
  // Not 0: the estimate folds inside the image and the figures leave those points out.
  j["expected_error_points_without_ray"] = e.grid_points - e.points;
  return j;
}

nlohmann::json lens_choice_json(const CalibrationEngine& engine) {
  nlohmann::json cands = nlohmann::json::array();
  for (const LensCandidate& c : engine.lens_candidates()) {
    nlohmann::json j{{"model", lens_model_name(c.model)}, {"fitted", c.fitted}};
    if (!c.fitted) {
      j["failure"] = c.failure;
    } else {
      j["rms"] = number(c.rms_px);
      j["free_intrinsics"] = c.free_intrinsics;
      j["residuals"] = c.residuals;
      j["bic"] = number(c.bic);
      j["expected_error_px"] = number(c.expected_error_px);
      j["held"] = c.held;
    }
    cands.push_back(j);
  }
  return {{"chosen", lens_model_name(engine.estimate().lens_model())},
          {"criterion",
           "BIC = N ln(SSR/N) + k ln N over the keyframes' corners (N residuals, k free "
           "intrinsics); the engine moves to a model that leads the current one by more than " +
               std::to_string(static_cast<int>(kLensSwitchMargin)) + " (" +
               std::to_string(static_cast<int>(kFamilySwitchMargin)) +
               " between the pinhole and the fisheye family, which the bootstrap chooses by the "
               "better fit)"},
          {"candidates", cands}};
}

void save_calibration(const std::string& path, const CalibrationResult& r, const char* format,
                      CalibrationFileExtras extras) {
  std::optional<ModelFormat> f;
  if (format != nullptr && *format != '\0') {
    f = model_format_from_name(format);
    if (!f) {
      std::string names;
      for (const ModelFormat m : model_formats()) {
        names += std::string(names.empty() ? "" : ", ") + model_format_name(m);
      }
      throw Error(ErrorCode::kInvalidArgument,
                  std::string("unknown format '") + format + "': use one of " + names);
    }
  }
  put_result_figures(r, &extras);
  write_camera_model(path, r.model, extras, f);
}

}  // namespace posecal::abi
