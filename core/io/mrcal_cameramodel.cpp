// mrcal's .cameramodel: a Python dict literal (mrcal reads it with ast.literal_eval) holding
// lensmodel, intrinsics, extrinsics and imagersize (docs/formats.md). posecal's OpenCV-vector
// models are mrcal's LENSMODEL_OPENCV<N> with the same parameters in the same order and the same
// pixel convention; the extrinsics are the identity (posecal calibrates the intrinsics only).
#include <cstdlib>

#include "io/model_file_internal.hpp"

namespace posecal::model_io {

namespace {

// The OpenCV coefficient counts mrcal names LENSMODEL_OPENCV<N>.
bool mrcal_opencv_count(size_t n) { return n == 4 || n == 5 || n == 8 || n == 12; }

}  // namespace

std::string compose_mrcal(const std::string& path, const CameraModel& model) {
  const std::vector<double> d = model.distortion_coefficients();
  if (opencv_coefficients(model.lens_model()) == 0 || !mrcal_opencv_count(d.size())) {
    cannot_hold(path, ModelFormat::kMrcal, model, "has no LENSMODEL_OPENCV<N> equivalent");
  }
  std::vector<double> intrinsics{model.fx(), model.fy(), model.cx(), model.cy()};
  intrinsics.insert(intrinsics.end(), d.begin(), d.end());
  return std::string("# written by posecal: lens model ") + lens_model_name(model.lens_model()) +
         "\n{\n    'lensmodel': 'LENSMODEL_OPENCV" + std::to_string(d.size()) +
         "',\n\n    # intrinsics are fx,fy,cx,cy,distortion0,distortion1,....\n"
         "    'intrinsics': " +
         number_list(intrinsics) +
         ",\n\n    # extrinsics are rt_fromref: the identity (posecal calibrates the intrinsics "
         "only)\n    'extrinsics': [0, 0, 0, 0, 0, 0],\n\n    'imagersize': [" +
         std::to_string(model.width()) + ", " + std::to_string(model.height()) + "],\n}\n";
}

ModelFile parse_mrcal(const std::string& path, std::string_view text) {
  const TextNode root = parse_python_literal(path, text);
  const Fields f(path);
  f.only_keys(root,
              {"lensmodel", "intrinsics", "extrinsics", "imagersize", "valid_intrinsics_region",
               "icam_intrinsics", "optimization_inputs"},
              "");
  const TextNode& lens = f.need(root, "lensmodel", "");
  const std::string name = f.string(lens, "'lensmodel'");
  size_t n_dist = 0;
  const std::string prefix = "LENSMODEL_OPENCV";
  if (name == "LENSMODEL_PINHOLE") {
    n_dist = 0;
  } else if (name.compare(0, prefix.size(), prefix) == 0 && name.size() <= prefix.size() + 2 &&
             mrcal_opencv_count(std::strtoul(name.c_str() + prefix.size(), nullptr, 10)) &&
             name.find_first_not_of("0123456789", prefix.size()) == std::string::npos) {
    n_dist = std::strtoul(name.c_str() + prefix.size(), nullptr, 10);
  } else {
    f.fail(lens, "'lensmodel' '" + name + "'",
           "is not read: posecal reads LENSMODEL_OPENCV4, OPENCV5, OPENCV8, OPENCV12 and PINHOLE");
  }
  const std::vector<double> intrinsics =
      f.numbers(f.need(root, "intrinsics", ""), "'intrinsics'", 4 + n_dist, 4 + n_dist);
  f.numbers(f.need(root, "extrinsics", ""), "'extrinsics'", 6, 6);
  const TextNode& size_node = f.need(root, "imagersize", "");
  f.numbers(size_node, "'imagersize'", 2, 2);
  const int w = f.integer(size_node.items[0], "'imagersize'", 1, CameraModel::kMaxImageSide);
  const int h = f.integer(size_node.items[1], "'imagersize'", 1, CameraModel::kMaxImageSide);
  if (const TextNode* region = f.find(root, "valid_intrinsics_region")) {
    if (region->kind != TextNode::Kind::kSeq) {
      f.fail(*region, "'valid_intrinsics_region'", "is not a list of [x, y] points");
    }
    for (const TextNode& point : region->items) {
      f.numbers(point, "'valid_intrinsics_region'", 2, 2);
    }
  }
  if (const TextNode* icam = f.find(root, "icam_intrinsics")) {
    f.integer(*icam, "'icam_intrinsics'", 0, 1 << 20);
  }
  if (const TextNode* inputs = f.find(root, "optimization_inputs")) {
    if (inputs->kind != TextNode::Kind::kScalar || !inputs->quoted) {
      f.fail(*inputs, "'optimization_inputs'", "is not a bytes string");
    }
  }
  std::vector<double> dist(intrinsics.begin() + 4, intrinsics.end());
  if (dist.empty()) dist.assign(5, 0.0);
  const std::vector<double> K{
      intrinsics[0], 0, intrinsics[2], 0, intrinsics[1], intrinsics[3], 0, 0, 1};
  ModelFile file;
  file.format = ModelFormat::kMrcal;
  file.model = model_from_opencv(path, w, h, K, dist, "'intrinsics'");
  return file;
}

}  // namespace posecal::model_io
