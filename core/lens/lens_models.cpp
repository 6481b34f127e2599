#include "lens/lens_models.hpp"

namespace posecal {

namespace {

struct ModelInfo {
  LensModel model;
  const char* name;
  int opencv_coefficients;
  bool ray_model;
  int base_distortion;
  std::vector<std::string> names;  // all intrinsics, pinhole first
};

template <class M>
ModelInfo info_of(LensModel model) {
  ModelInfo info{model,        M::kName,           M::kOpenCVCoefficients,
                 M::kRayModel, M::kBaseDistortion, {kPinholeNames.begin(), kPinholeNames.end()}};
  for (const char* n : M::kDistortionNames) info.names.emplace_back(n);
  return info;
}

const std::vector<ModelInfo>& table() {
  static const std::vector<ModelInfo> t = {
#define POSECAL_LENS_INFO(M) info_of<lens::M>(LensModel::k##M),
      POSECAL_LENS_MODELS(POSECAL_LENS_INFO)
#undef POSECAL_LENS_INFO
  };
  return t;
}

const ModelInfo& info(LensModel model) {
  for (const ModelInfo& i : table())
    if (i.model == model) return i;
  throw Error(ErrorCode::kInternal, "unknown lens model " + std::to_string(static_cast<int>(model)));
}

}  // namespace

const std::vector<LensModel>& lens_models() {
  static const std::vector<LensModel> all = [] {
    std::vector<LensModel> v;
    for (const ModelInfo& i : table()) v.push_back(i.model);
    return v;
  }();
  return all;
}

const char* lens_model_name(LensModel model) { return info(model).name; }

std::optional<LensModel> lens_model_from_name(const std::string& name) {
  for (const ModelInfo& i : table())
    if (name == i.name) return i.model;
  return std::nullopt;
}

int num_distortion_params(LensModel model) { return static_cast<int>(info(model).names.size()) - kNumPinholeParams; }

const std::vector<std::string>& intrinsic_names(LensModel model) { return info(model).names; }

const std::vector<std::string>& extension_parameters(LensModel model) {
  static const std::vector<std::vector<std::string>> all = [] {
    std::vector<std::vector<std::string>> v;
    for (const ModelInfo& i : table())
      v.emplace_back(i.names.begin() + kNumPinholeParams + i.base_distortion, i.names.end());
    return v;
  }();
  return all.at(static_cast<size_t>(model));
}

bool is_ray_model(LensModel model) { return info(model).ray_model; }

int opencv_coefficients(LensModel model) { return info(model).opencv_coefficients; }

std::optional<LensModel> lens_model_of_opencv_count(int coefficients) {
  for (const ModelInfo& i : table())
    if (i.opencv_coefficients > 0 && i.opencv_coefficients == coefficients) return i.model;
  return std::nullopt;
}

}  // namespace posecal
