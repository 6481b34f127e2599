// libFuzzer target: camera-model files, read_camera_model (core/io/model_file.cpp), which reads
// OpenCV YAML / JSON / XML through cv::FileStorage. The input is written to a temporary file per
// run (the reader takes a path).
//
// Besides "no crash, no sanitizer report, only posecal::Error thrown": a model that reads is
// valid, and writing it and reading it back gives the same model (the calibration files posecal
// writes are read by `evaluate` and by sim://?model=FILE).
#include <unistd.h>

#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <string>

#include "common/error.hpp"
#include "io/model_file.hpp"

namespace {

std::string temp_path(const char* suffix) {
  const char* dir = std::getenv("TMPDIR");
  return std::string(dir && *dir ? dir : "/tmp") + "/posecal_fuzz_model_" +
         std::to_string(::getpid()) + suffix;
}

// The two files of this process, removed at exit.
struct TempFiles {
  std::string in = temp_path(".yml");
  std::string out = temp_path("_out.yml");
  ~TempFiles() {
    std::remove(in.c_str());
    std::remove(out.c_str());
  }
};

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  static const TempFiles files;
  const std::string& in = files.in;
  const std::string& out = files.out;
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
  posecal::write_camera_model(out, model);
  const posecal::CameraModel again = posecal::read_camera_model(out);  // must not throw
  if (again.width() != model.width() || again.height() != model.height() ||
      again.lens_model() != model.lens_model() || again.params() != model.params()) {
    std::abort();
  }
  return 0;
}
