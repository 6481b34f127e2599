// The lens-model table: every lens model posecal knows is listed once, in POSECAL_LENS_MODELS, and
// everything else (the LensModel enum, names, parameter counts and groups, the projection used by
// the solver, the derivatives used by pose selection, unprojection) expands from it, as mrcal's
// MRCAL_LENSMODEL_*_LIST drives its lens models.
//
// A model is a struct in namespace posecal::lens (see opencv5.hpp) with
//   kName                 its name in files and JSON ("opencv5")
//   kNumDistortion        number of distortion coefficients; the pinhole fx fy cx cy come first
//   kDistortionNames      their names, in parameter order
//   kOpenCVCoefficients   length of OpenCV's distortion vector that holds exactly this model
//                         (0 if the model is not one of OpenCV's distortion vectors)
//   kRayModel             true if the model projects 3-D directions (project_ray, unproject by
//                         angle, valid beyond 90 degrees from the axis: the fisheye); false if
//                         it distorts the plane Z = 1
//   kBaseDistortion       the leading distortion coefficients always estimated; the rest are
//                         held at 0 while the keyframes do not determine them
//   distort<T>(dist, x, y, &xd, &yd)                   templated for Ceres' Jets
//   distort_jacobian(dist, x, y, &xd, &yd, &J_xy)      with d(xd, yd)/d(x, y)
//   project_jacobians(params, p_cam, &u, &v, &Jc, Ji)  with d(u, v)/d(p_cam) and d/d(params)
//   fold_free_radius(dist)                             where the distortion cannot fold (or 0)
// Adding a model: docs/architecture.md, "Adding a lens model".
#pragma once

#include <algorithm>
#include <array>
#include <optional>
#include <string>
#include <vector>

#include "common/error.hpp"
#include "lens/fisheye.hpp"
#include "lens/opencv5.hpp"
#include "lens/opencv_full.hpp"

namespace posecal {

// X(Model) for each model struct of namespace lens.
#define POSECAL_LENS_MODELS(X) X(OpenCV5) X(OpenCV8) X(OpenCV12) X(OpenCV14) X(Fisheye)

enum class LensModel {
#define POSECAL_LENS_ENUM(M) k##M,
  POSECAL_LENS_MODELS(POSECAL_LENS_ENUM)
#undef POSECAL_LENS_ENUM
};

// The pinhole parameters that precede every model's distortion coefficients.
inline constexpr int kNumPinholeParams = 4;
inline constexpr std::array<const char*, kNumPinholeParams> kPinholeNames{"fx", "fy", "cx", "cy"};

// Number of intrinsics (pinhole + distortion) of a model struct.
template <class M>
inline constexpr int kNumParamsOf = kNumPinholeParams + M::kNumDistortion;

// Upper bound on the parameter count of any lens model; sizes fixed arrays.
inline constexpr int kMaxIntrinsics = std::max({
#define POSECAL_LENS_COUNT(M) kNumParamsOf<lens::M>,
    POSECAL_LENS_MODELS(POSECAL_LENS_COUNT)
#undef POSECAL_LENS_COUNT
});

// Intrinsic groups (paper §3.1): C_K = [fx, fy, cx, cy], C_Delta = the distortion coefficients.
enum class ParamGroup { kPinhole, kDistortion };
inline ParamGroup param_group(int param_index) {
  return param_index < kNumPinholeParams ? ParamGroup::kPinhole : ParamGroup::kDistortion;
}

// Calls f(M{}) with the struct of `model` and returns what it returns.
template <class F>
decltype(auto) with_lens_model(LensModel model, F&& f) {
  switch (model) {
#define POSECAL_LENS_CASE(M) \
  case LensModel::k##M:      \
    return f(lens::M{});
    POSECAL_LENS_MODELS(POSECAL_LENS_CASE)
#undef POSECAL_LENS_CASE
  }
  throw Error(ErrorCode::kInternal, "unknown lens model " + std::to_string(static_cast<int>(model)));
}

// Every model, in table order.
const std::vector<LensModel>& lens_models();
const char* lens_model_name(LensModel model);
// The model of a name ("opencv5"), nullopt if there is none.
std::optional<LensModel> lens_model_from_name(const std::string& name);
int num_distortion_params(LensModel model);
inline int num_intrinsics(LensModel model) { return kNumPinholeParams + num_distortion_params(model); }
// Names of all intrinsics, pinhole first.
const std::vector<std::string>& intrinsic_names(LensModel model);
// The parameters after a model's kBaseDistortion (k4..k6, s1..s4, tau_x, tau_y of OpenCV's full
// model; k3 k4 of the fisheye), in its order; empty for opencv5. Pose selection holds them at 0
// while the keyframes do not determine them.
const std::vector<std::string>& extension_parameters(LensModel model);
// Length of OpenCV's pinhole distortion vector that holds exactly the model; 0 for a model that
// is not one (the fisheye: formats must not write its coefficients as such a vector).
int opencv_coefficients(LensModel model);
// True if the model projects 3-D directions and is valid beyond 90 degrees from the axis.
bool is_ray_model(LensModel model);
// The model holding an OpenCV distortion vector of `coefficients` entries exactly, if any.
std::optional<LensModel> lens_model_of_opencv_count(int coefficients);

// Projects a camera-frame point to pixels under model M: pi(P) = K * Delta(P / Z) (paper eq. 1).
// Ray models project the direction itself (lens/fisheye.hpp).
template <class M, typename T>
inline void project_with(const T* params, const T* p_cam, T* uv) {
  T xd, yd;
  if constexpr (M::kRayModel) {
    M::project_ray(params + kNumPinholeParams, p_cam[0], p_cam[1], p_cam[2], &xd, &yd);
  } else {
    const T x = p_cam[0] / p_cam[2];
    const T y = p_cam[1] / p_cam[2];
    M::distort(params + kNumPinholeParams, x, y, &xd, &yd);
  }
  uv[0] = params[0] * xd + params[2];
  uv[1] = params[1] * yd + params[3];
}

// The same for a model chosen at run time.
template <typename T>
inline void project_generic(LensModel model, const T* params, const T* p_cam, T* uv) {
  with_lens_model(model, [&](auto m) { project_with<decltype(m)>(params, p_cam, uv); });
}

// Lens distortion of a normalised point; `dist` points at the distortion coefficients.
template <typename T>
inline void distort_generic(LensModel model, const T* dist, const T& x, const T& y, T* xd, T* yd) {
  with_lens_model(model, [&](auto m) { decltype(m)::distort(dist, x, y, xd, yd); });
}

}  // namespace posecal
