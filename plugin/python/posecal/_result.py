"""A calibration result: the library's result JSON as a dict, with numpy views of K, D and the
covariance."""

from __future__ import annotations

from typing import Any, Dict, Tuple

import numpy as np
import numpy.typing as npt

# posecal.h: the intrinsics are the pinhole fx fy cx cy, then the lens model's distortion
# coefficients; "covariance_order" lists them in that order.
_PINHOLE = ("fx", "fy", "cx", "cy")


class Result(Dict[str, Any]):
    """A calibration result (posecal_session_result / posecal_calibration_json): a dict of the
    JSON object, so `result["fx"]`, `result["converged"]` and `json.dumps(result)` work as
    before, plus numpy arrays:

    - `K`: the 3 x 3 camera matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]];
    - `D`: the distortion coefficients, 1-D, in the lens model's order (for "opencv5": k1 k2
      p1 p2 k3, OpenCV's distCoeffs), so `cv2.undistort(image, r.K, r.D)` works;
    - `covariance`: the intrinsics' covariance, square, rows and columns in the order of
      `parameter_names` (fx fy cx cy, then `distortion_names`).

    Each access builds a new array from the dict; changing one changes nothing else.
    """

    @property
    def parameter_names(self) -> Tuple[str, ...]:
        """The intrinsics' names: fx fy cx cy, then the distortion coefficients'."""
        return tuple(self["covariance_order"])

    @property
    def distortion_names(self) -> Tuple[str, ...]:
        """The names of D's entries ("k1", "k2", "p1", "p2", "k3" for "opencv5")."""
        return tuple(n for n in self.parameter_names if n not in _PINHOLE)

    @property
    def K(self) -> npt.NDArray[np.float64]:  # noqa: N802 - the camera matrix is K everywhere
        """The 3 x 3 camera matrix."""
        return np.array([[self["fx"], 0.0, self["cx"]],
                         [0.0, self["fy"], self["cy"]],
                         [0.0, 0.0, 1.0]], dtype=np.float64)

    @property
    def D(self) -> npt.NDArray[np.float64]:  # noqa: N802 - OpenCV's name
        """The distortion coefficients (1-D, float64), in `distortion_names` order."""
        return np.array([self[n] for n in self.distortion_names], dtype=np.float64)

    @property
    def covariance(self) -> npt.NDArray[np.float64]:
        """The intrinsics' covariance (n x n, float64; units of the parameters squared), in
        `parameter_names` order."""
        n = len(self["covariance_order"])
        return np.array(self["covariance"], dtype=np.float64).reshape(n, n)
