// Kalibr's camchain YAML (docs/formats.md): posecal writes one camera, cam0, as pinhole-radtan
// (intrinsics [fu fv pu pv], distortion_coeffs [k1 k2 r1 r2], the same pixel convention as
// OpenCV's) or, for the fisheye, pinhole-equidistant (cv::fisheye's k1..k4), and reads cam0 of a
// camchain. radtan has no k3: a model with k3 != 0 is refused.
#include <cctype>

#include "io/model_file_internal.hpp"

namespace posecal::model_io {

std::string compose_kalibr(const std::string& path, const CameraModel& model) {
  const std::vector<double> d = model.distortion_coefficients();
  const bool fisheye = model.lens_model() == LensModel::kFisheye;
  if (!fisheye && model.lens_model() != LensModel::kOpenCV5) {
    cannot_hold(path, ModelFormat::kKalibr, model, "has no Kalibr distortion model");
  }
  for (size_t i = 4; !fisheye && i < d.size(); ++i) {
    if (d[i] != 0) {
      cannot_hold(path, ModelFormat::kKalibr, model,
                  "has " + model.param_names()[4 + i] + " = " + number_text(d[i]) +
                      ", which Kalibr's radtan distortion (k1 k2 r1 r2) cannot hold");
    }
  }
  return "cam0:\n  camera_model: pinhole\n  intrinsics: " +
         number_list({model.fx(), model.fy(), model.cx(), model.cy()}) +
         "\n  distortion_model: " + (fisheye ? "equidistant" : "radtan") +
         "\n  distortion_coeffs: " + number_list({d[0], d[1], d[2], d[3]}) + "\n  resolution: [" +
         std::to_string(model.width()) + ", " + std::to_string(model.height()) + "]\n";
}

ModelFile parse_kalibr(const std::string& path, std::string_view text) {
  const TextNode root = parse_yaml_subset(path, text);
  const Fields f(path);
  for (const auto& [key, value] : root.entries) {
    if (key.size() < 4 || key.compare(0, 3, "cam") != 0 ||
        key.find_first_not_of("0123456789", 3) != std::string::npos) {
      f.fail(value, "unknown key '" + key + "'", "(a camchain has cam0, cam1, ...)");
    }
  }
  const TextNode& cam = f.need(root, "cam0", "");
  if (cam.kind != TextNode::Kind::kMap) f.fail(cam, "'cam0'", "is not a map");
  f.only_keys(cam,
              {"camera_model", "intrinsics", "distortion_model", "distortion_coeffs", "resolution",
               "rostopic", "cam_overlaps", "T_cam_imu", "T_cn_cnm1", "timeshift_cam_imu"},
              "cam0.");
  const TextNode& camera_model = f.need(cam, "camera_model", "cam0.");
  if (f.string(camera_model, "'cam0.camera_model'") != "pinhole") {
    f.fail(camera_model, "'cam0.camera_model' '" + camera_model.scalar + "'",
           "is not read: posecal's lens models are pinhole ones");
  }
  const std::vector<double> in =
      f.numbers(f.need(cam, "intrinsics", "cam0."), "'cam0.intrinsics'", 4, 4);
  const TextNode& distortion = f.need(cam, "distortion_model", "cam0.");
  const std::string dist_name = f.string(distortion, "'cam0.distortion_model'");
  const bool fisheye = dist_name == "equidistant";
  const size_t n = dist_name == "none" ? 0 : 4;
  if (dist_name != "radtan" && dist_name != "none" && !fisheye) {
    f.fail(distortion, "'cam0.distortion_model' '" + dist_name + "'",
           "is not read: posecal's lens models hold radtan, equidistant (and none)");
  }
  std::vector<double> dist =
      f.numbers(f.need(cam, "distortion_coeffs", "cam0."), "'cam0.distortion_coeffs'", n, n);
  if (!fisheye) dist.resize(5, 0.0);
  const TextNode& resolution = f.need(cam, "resolution", "cam0.");
  f.numbers(resolution, "'cam0.resolution'", 2, 2);
  const int w = f.integer(resolution.items[0], "'cam0.resolution'", 1, CameraModel::kMaxImageSide);
  const int h = f.integer(resolution.items[1], "'cam0.resolution'", 1, CameraModel::kMaxImageSide);
  if (const TextNode* topic = f.find(cam, "rostopic")) f.string(*topic, "'cam0.rostopic'");
  ModelFile file;
  file.format = ModelFormat::kKalibr;
  const std::vector<double> K{in[0], 0, in[2], 0, in[1], in[3], 0, 0, 1};
  file.model = fisheye ? model_from_opencv_fisheye(path, w, h, K, dist, "'cam0.distortion_coeffs'")
                       : model_from_opencv(path, w, h, K, dist, "'cam0.distortion_coeffs'");
  return file;
}

}  // namespace posecal::model_io
