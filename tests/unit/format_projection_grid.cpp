// Helper of the mrcal round-trip test (test_mrcal_roundtrip.py): posecal's own projection over a
// grid that covers the whole image, for comparison with mrcal.project on the same rays.
//
//   format_projection_grid --write FILE.cameramodel   writes a strongly distorted opencv5 model
//   format_projection_grid --read FILE                reads a model file (any format)
//
// Prints "# W H", then one line "x y z u v" per grid point: the ray (x, y, 1) through pixel
// (i (W-1)/64, j (H-1)/48), i = 0..64, j = 0..48 (unprojected by posecal), and posecal's
// projection (u, v) of that ray.
#include <cstdio>
#include <cstring>
#include <exception>

#include "io/model_file.hpp"
#include "lens/camera_model.hpp"

int main(int argc, char** argv) {
  if (argc != 3 || (std::strcmp(argv[1], "--write") != 0 && std::strcmp(argv[1], "--read") != 0)) {
    std::fprintf(stderr, "usage: %s --write FILE.cameramodel | --read FILE\n", argv[0]);
    return 2;
  }
  try {
    posecal::CameraModel model;
    if (std::strcmp(argv[1], "--write") == 0) {
      model = posecal::CameraModel::opencv5(1280, 720, 1000.25, 1010.75, 650.5, 350.25,
                                            {-0.25, 0.12, 0.001, -0.002, -0.02});
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
