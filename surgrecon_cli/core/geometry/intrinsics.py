"""Plausibility of a camera's intrinsics, beyond their being finite numbers.

A calibration can be valid arithmetic and still describe no real camera: the image of such a
camera matches nothing, and it silently drops out of the reconstruction. Checked here:

- K is a pinhole matrix: K[2] = (0, 0, 1), fx, fy > 0;
- the principal point lies within the image extended by `PRINCIPAL_POINT_MARGIN` of its
  size on each side (real lenses put it near the centre);
- the lens distortion maps the undistorted plane onto the image monotonically: along rays
  from the principal point towards the midpoints of the image's edges, the distorted radius
  grows strictly with the undistorted one until it reaches the border. Sampled numerically
  (`RAY_SAMPLES` angles from the optical axis up to `MAX_ANGLE_DEG`), for every distortion
  model. The same out to the corners is only worth a warning (`folds_before_corners`).
"""

from __future__ import annotations

import numpy as np

from .cameras import CameraModel
from .distortion import distort_normalized

PRINCIPAL_POINT_MARGIN = 0.5
"""Principal point allowed this fraction of the image size beyond each edge."""
RAY_SAMPLES = 4000
MAX_ANGLE_DEG = 89.5


def implausible_intrinsics(K: np.ndarray, width: int, height: int,
                           camera: CameraModel) -> str | None:
    """Why a calibration cannot be a real camera's, None when it can be.

    K (3, 3) px and `width` x `height` px: the full-resolution calibration (as CameraInfo
    gives it, before binning and ROI); `camera`: the model of the images (its distortion).
    """
    K = np.asarray(K, float).reshape(3, 3)
    if not np.array_equal(K[2], [0.0, 0.0, 1.0]):
        return f"K's last row is {K[2].tolist()}, not [0, 0, 1]"
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        return f"focal lengths fx = {K[0, 0]:g}, fy = {K[1, 1]:g} px are not positive"
    cx, cy = K[0, 2], K[1, 2]
    mx, my = PRINCIPAL_POINT_MARGIN * width, PRINCIPAL_POINT_MARGIN * height
    if not (-mx <= cx <= width + mx and -my <= cy <= height + my):
        return (f"principal point ({cx:.6g}, {cy:.6g}) px is outside the {width}x{height} px "
                f"image by more than {PRINCIPAL_POINT_MARGIN:g} of its size")
    return _non_monotonic(K, camera.dist, camera.model, _border(width, height, corners=False))


def folds_before_corners(K: np.ndarray, width: int, height: int,
                         camera: CameraModel) -> str | None:
    """Why the distortion does not reach the image's corners monotonically, None when it
    does. Not a refusal: corners are often vignetted (a round endoscope image) and left out
    of the calibration, so a polynomial may fold back there; arguments as for
    `implausible_intrinsics`, which must have passed."""
    return _non_monotonic(np.asarray(K, float).reshape(3, 3), camera.dist, camera.model,
                          _border(width, height, corners=True))


def _border(width: int, height: int, corners: bool) -> np.ndarray:
    """Pixels (4, 2): the image's corners, or the midpoints of its edges."""
    if corners:
        return np.array([[0, 0], [width - 1, 0], [0, height - 1], [width - 1, height - 1]],
                        float)
    return np.array([[(width - 1) / 2, 0], [(width - 1) / 2, height - 1],
                     [0, (height - 1) / 2], [width - 1, (height - 1) / 2]], float)


def _non_monotonic(K: np.ndarray, dist: np.ndarray, model: str,
                   pixels: np.ndarray) -> str | None:
    """Why the distortion does not map rays monotonically out to `pixels` (P, 2), or None."""
    border = (pixels - K[:2, 2]) @ np.linalg.inv(K[:2, :2]).T  # distorted normalised
    reach = np.linalg.norm(border, axis=1)  # (P,)
    directions = border / np.where(reach > 0, reach, 1.0)[:, None]
    radius = np.tan(np.radians(np.linspace(0.0, MAX_ANGLE_DEG, RAY_SAMPLES)))  # undistorted
    points = radius[None, :, None] * directions[:, None, :]  # (P, S, 2)
    with np.errstate(all="ignore"):
        distorted = distort_normalized(points.reshape(-1, 2), dist, model).reshape(points.shape)
        along = np.einsum("rsk,rk->rs", distorted, directions)  # distorted radius on the ray
    for ray in range(len(border)):
        if reach[ray] == 0:
            continue
        beyond = np.flatnonzero(~(along[ray] < reach[ray]))  # (NaN counts as beyond)
        end = int(beyond[0]) if len(beyond) else RAY_SAMPLES
        if end == RAY_SAMPLES or not np.isfinite(along[ray, end]) or np.any(
                np.diff(along[ray, :end + 1]) <= 0):
            u, v = pixels[ray]
            return (f"the {model} distortion {np.round(dist, 6).tolist()} is not monotonic "
                    f"out to pixel ({u:g}, {v:g}) of the image: no undistorted ray reaches it "
                    "without folding back")
    return None
