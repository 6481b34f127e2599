// Helper of the mrcal round-trip test (test_mrcal_roundtrip.py): posecal's own projection over a
// grid that covers the whole image, for comparison with mrcal.project on the same rays.
//
//   format_projection_grid --write FILE.cameramodel [LENS]  writes a strongly distorted model of
//                                                     LENS (opencv5, the default, opencv8,
//                                                     opencv12)
//   format_projection_grid --read FILE                reads a model file (any format)
//
// Prints "# W H", then one line "x y z u v" per grid point: the ray (x, y, 1) through pixel
// (i (W-1)/64, j (H-1)/48), i = 0..64, j = 0..48 (unprojected by posecal), and posecal's
// projection (u, v) of that ray.
#include <cstdio>
#include <cstring>
#include <exception>
#include <optional>
#include <string>
#include <vector>

#include "io/model_file.hpp"
#include "lens/camera_model.hpp"

int main(int argc, char** argv) {
  const bool write = argc >= 3 && std::strcmp(argv[1], "--write") == 0;
  if (!(write && argc <= 4) && !(argc == 3 && std::strcmp(argv[1], "--read") == 0)) {
    std::fprintf(stderr, "usage: %s --write FILE.cameramodel [LENS] | --read FILE\n", argv[0]);
    return 2;
  }
  try {
    posecal::CameraModel model;
    if (write) {
      const std::string lens_name = argc == 4 ? argv[3] : "opencv5";
      const std::optional<posecal::LensModel> lens = posecal::lens_model_from_name(lens_name);
      if (!lens) {
        std::fprintf(stderr, "unknown lens model %s\n", lens_name.c_str());
        return 2;
      }
      // Barrel from k1..k3 alone for opencv5; a wide-angle rational form (and thin prism) else.
      const std::vector<double> dist =
          *lens == posecal::LensModel::kOpenCV5
              ? std::vector<double>{-0.25, 0.12, 0.001, -0.002, -0.02}
              : std::vector<double>{0.8,  -0.1,  0.001,  -0.002, 0.02,   1.1,   0.05,
                                    0.01, 0.002, -0.001, 0.0015, 0.0005, 0.009, -0.007};
      std::vector<double> params{1000.25, 1010.75, 650.5, 350.25};
      params.insert(params.end(), dist.begin(),
                    dist.begin() + posecal::num_distortion_params(*lens));
      model = posecal::CameraModel(1280, 720, *lens, params);
      posecal::write_camera_model(argv[2], model);
    } else {
      model = posecal::read_camera_model(argv[2]);
    }
    std::printf("# %d %d\n", model.width(), model.height());
    constexpr int kCols = 64, kRows = 48;
    for (int j = 0; j <= kRows; ++j) {
      for (int i = 0; i <= kCols; ++i) {
        const Eigen::Vector2d px((model.width() - 1) * static_cast<double>(i) / kCols,
                                 (model.height() - 1) * static_cast<double>(j) / kRows);
        Eigen::Vector2d xn, uv;
        if (!model.unproject(px, &xn) || !model.project(Eigen::Vector3d(xn.x(), xn.y(), 1), &uv)) {
          std::fprintf(stderr, "pixel (%g, %g) does not unproject\n", px.x(), px.y());
          return 1;
        }
        std::printf("%.17g %.17g 1 %.17g %.17g\n", xn.x(), xn.y(), uv.x(), uv.y());
      }
    }
  } catch (const std::exception& e) {
    std::fprintf(stderr, "%s\n", e.what());
    return 1;
  }
  return 0;
}
