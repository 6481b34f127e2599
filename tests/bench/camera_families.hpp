// The benchmark's camera families (docs/benchmarks.md, "worlds"): the reference camera of each,
// which bench_pose_selection samples around per seed and detector_bias renders through, and the
// board each is calibrated with.
#pragma once

#include <cmath>
#include <string>
#include <vector>

#include "board/board.hpp"
#include "common/error.hpp"
#include "lens/camera_model.hpp"
#include "lens/reference_models.hpp"

namespace posecal {

inline CameraModel reference_camera(const std::string& name) {
  if (name == "c525") return c525_reference_model();
  if (name == "industrial") {
    // 2448x2048 machine-vision camera, 8 mm lens on a 3.45 um sensor, strong barrel distortion.
    return CameraModel::opencv5(2448, 2048, 2320, 2320, 1223.5, 1023.5,
                                {-0.30, 0.12, 0.0005, -0.0004, -0.02});
  }
  if (name == "tele") {
    // Long focal length, low distortion (50 mm lens on a 1/1.8" 1600x1200 sensor).
    return CameraModel::opencv5(1600, 1200, 11300, 11300, 799.5, 599.5,
                                {-0.02, 0.05, 0.0, 0.0, 0.0});
  }
  if (name == "longfocal") {
    // 1920x1200, 25 mm lens on 5.86 um pixels (f ~ 4270 px; the f ~ 4000-4200).
    return CameraModel::opencv5(1920, 1200, 4100, 4100, 962.0, 597.0,
                                {-0.05, 0.3, 0.0002, -0.0003, 0.0});
  }
  if (name == "vga") {
    // 640x480 webcam with pincushion distortion (k1 > 0).
    return CameraModel::opencv5(640, 480, 610, 612, 322.0, 238.5,
                                {0.12, -0.25, 0.001, -0.0015, 0.1});
  }
  // Lens models beyond OpenCV's five coefficients (issue 14); the engine calibrates each camera's
  // own model and OpenCV's baselines use the same one.
  if (name == "fisheye185") {
    // 1280x1024, 185 degrees across the image circle (Kannala-Brandt, cv::fisheye's k1..k4).
    return CameraModel(1280, 1024, LensModel::kFisheye,
                       {317.1, 317.8, 641.5, 509.3, 0.008, -0.0012, 0.0002, -0.00001});
  }
  if (name == "fisheye150") {
    // 1280x1024, 150 degrees across the width.
    return CameraModel(1280, 1024, LensModel::kFisheye,
                       {489.0, 489.5, 641.5, 509.3, 0.012, -0.0021, 0.00031, -0.00002});
  }
  if (name == "wide") {
    // 2448x2048, about 110 degrees across the width, OpenCV's rational model (opencv8).
    return CameraModel(
        2448, 2048, LensModel::kOpenCV8,
        {1224, 1226, 1230.5, 1020.2, 1.5, 0.3, 0.0005, -0.0003, 0.01, 1.85, 0.6, 0.05});
  }
  if (name == "tilted") {
    // The C525's lens on a sensor tilted 0.5 degrees about x and 0.3 about y (opencv14).
    const CameraModel c = c525_reference_model();
    std::vector<double> p(c.params().begin(), c.params().end());
    p.resize(18, 0.0);
    p[16] = 0.5 * M_PI / 180, p[17] = 0.3 * M_PI / 180;
    return CameraModel(c.width(), c.height(), LensModel::kOpenCV14, p);
  }
  throw Error(
      ErrorCode::kInvalidArgument,
      "unknown camera '" + name +
          "' (c525, industrial, tele, longfocal, vga, fisheye185, fisheye150, wide, tilted)");
}

inline BoardSpec board_for(const std::string& camera) {
  // A board that fills a useful part of the view at a workable distance.
  if (camera == "tele") return BoardSpec::parse("charuco:9x6:0.028:0.0182:DICT_4X4_50");
  return BoardSpec{};
}

}  // namespace posecal
