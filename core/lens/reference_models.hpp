// Camera models built in, so that the project reads no file outside its own tree at run time.
#pragma once

#include "lens/camera_model.hpp"

namespace posecal {

// The Logitech C525 calibration of the paper's experiments (1280x720; data/c525_reference.yml is
// the same).
CameraModel c525_reference_model();

}  // namespace posecal
