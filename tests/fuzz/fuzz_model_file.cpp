// libFuzzer target: camera-model files, read_camera_model (core/io/model_file.cpp), which reads
// every format by content: OpenCV YAML / JSON / XML through cv::FileStorage, ROS camera_info and
// Kalibr camchain YAML and mrcal's Python literal through posecal's own parser (text_tree.cpp),
// HALCON's camera parameters (halcon_campar.cpp). The input is written to a temporary file per run (the reader takes a path).
//
// Besides "no crash, no sanitizer report, only posecal::Error thrown": a model that reads is
// valid, and writing it in every format and reading it back gives the same model (the
// calibration files posecal writes are read by `evaluate` and by sim://?model=FILE); only Kalibr
// (radtan has no k3) and HALCON (a fit with a limit) may refuse it.
#include <unistd.h>

#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <string>
#include <vector>

#include "common/error.hpp"
#include "io/model_file.hpp"

namespace {

std::string temp_path(const std::string& suffix) {
  const char* dir = std::getenv("TMPDIR");
  return std::string(dir && *dir ? dir : "/tmp") + "/posecal_fuzz_model_" +
         std::to_string(::getpid()) + suffix;
}

// The files of this process, removed at exit: the input, and the output in each format.
struct TempFiles {
  std::string in = temp_path(".yml");
  std::vector<std::string> out;
  TempFiles() {
    for (const posecal::ModelFormat f : posecal::model_formats()) {
      out.push_back(temp_path(std::string("_out_") + posecal::model_format_name(f) +
                              posecal::model_format_extension(f)));
    }
  }
  ~TempFiles() {
    std::remove(in.c_str());
    for (const std::string& o : out) std::remove(o.c_str());
  }
};

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  static const TempFiles files;
  const std::string& in = files.in;
  FILE* f = std::fopen(in.c_str(), "wb");
  if (f == nullptr) std::abort();
  if (size > 0 && std::fwrite(data, 1, size, f) != size) std::abort();
  std::fclose(f);

  posecal::CameraModel model;
  try {
    model = posecal::read_camera_model(in);
  } catch (const posecal::Error&) {
    return 0;
  }
  if (!model.is_valid()) std::abort();
  for (size_t i = 0; i < posecal::model_formats().size(); ++i) {
    const posecal::ModelFormat format = posecal::model_formats()[i];
    // Kalibr may refuse the model (k3), HALCON too (its fit's limit).
    const bool may_refuse =
        format == posecal::ModelFormat::kKalibr || format == posecal::ModelFormat::kHalcon;
    try {
      posecal::write_camera_model(files.out[i], model, {}, format);
    } catch (const posecal::Error&) {
      if (may_refuse) continue;
      std::abort();
    }
    // Must not throw. HALCON's file is a fit (halcon_campar.cpp): not the same parameters.
    const posecal::CameraModel again = posecal::read_camera_model(files.out[i]);
    if (format == posecal::ModelFormat::kHalcon) {
      if (!again.is_valid() || again.width() != model.width()) std::abort();
      continue;
    }
    if (again.width() != model.width() || again.height() != model.height() ||
        again.lens_model() != model.lens_model() || again.params() != model.params()) {
      std::abort();
    }
  }
  return 0;
}
