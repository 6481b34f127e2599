#include "lens/reference_models.hpp"

namespace posecal {

CameraModel c525_reference_model() {
  // data/c525_reference.yml: real Logitech C525 calibration, 1280x720, 9 frames.
  return CameraModel::opencv5(
      1280, 720, 1.0687250840763766e+03, 1.0737431805568067e+03, 6.3526070691971165e+02,
      3.5555335970090516e+02,
      {-3.1759579767319194e-03, -2.0593634553884241e-01, -2.8115339213691912e-03,
       -3.8662066741185558e-03, 2.4780625930115230e-01});
}

}  // namespace posecal
