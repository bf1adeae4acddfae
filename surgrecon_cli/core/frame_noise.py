"""The localisation error a frame's tracked pixels actually carry, measured from their
over-determined evidence (no constants fitted to a simulator).

The Cramér-Rao bound of locating a patch (core/noise.py) is a floor: on real images
(compression, demosaicing, specular highlights, interlacing, focus) the error is several
times larger. A point found by >= 2 cameras in a frame is re-triangulated from its tracked
pixels; its residuals leave 2n − 3 degrees of freedom (two views: the error across the
epipolar line), which measure the frame's true per-view pixel error σ_k
(`pixel_noise_from_residuals`). What σ_k² carries beyond the variance the noise model
predicts for those views (pixel noise + tracking bound + the pose error a view's residuals
can see) is added to every tracked pixel's localisation variance. Pure numpy; no I/O.
"""

from __future__ import annotations

import numpy as np

from .cameras import CameraModel, undistort_pixels
from .noise import NoiseModel, pixel_noise_from_residuals
from .triangulate import Observations, reprojection_residuals, triangulate

MIN_POINTS = 20  # ours: fewer points seen twice measure no frame noise (excess 0)


def tracked_observations(found: np.ndarray, pixels: np.ndarray,
                         models: list[CameraModel]) -> Observations:
    """Observations of the pixels (M, C, 2) px found (M, C) bool; points numbered by row."""
    rows, cams = np.nonzero(found)
    px = pixels[rows, cams]
    normalized = np.zeros_like(px)
    for c in np.unique(cams):
        normalized[cams == c] = undistort_pixels(px[cams == c], models[c])
    return Observations(rows, cams, px, normalized, np.zeros((len(rows), 3), np.uint8))


def tracking_excess_px2(found: np.ndarray, pixels: np.ndarray, localisation: np.ndarray,
                        models: list[CameraModel], poses: np.ndarray,
                        noise: NoiseModel) -> tuple[float, float]:
    """(excess variance px², measured σ_k px) of a frame's tracked pixels: found (N, C)
    bool, pixels (N, C, 2) px, localisation (N, C) px² the tracking bound of each found
    pixel, poses (C, 4, 4) (module docstring). (0, NaN) with fewer than MIN_POINTS points
    found by >= 2 cameras."""
    idx = np.flatnonzero(found.sum(1) >= 2)
    if len(idx) < MIN_POINTS:
        return 0.0, float("nan")
    obs = tracked_observations(found[idx], pixels[idx], models)
    tri = triangulate(obs, poses, models, len(idx))
    residual, depth = reprojection_residuals(tri.points, obs, poses, models)
    measured = pixel_noise_from_residuals(residual, obs.point)
    focal = np.array([m.K[0, 0] for m in models])[obs.camera]
    predicted = noise.tracked_view_variance_px2(
        depth, focal, localisation[idx[obs.point], obs.camera],
        pose=~noise.on_shared_body(obs.camera))
    predicted = predicted[np.isfinite(predicted) & (depth > 0)]
    if not np.isfinite(measured) or predicted.size == 0:
        return 0.0, float("nan")
    return max(0.0, measured**2 - float(np.median(predicted))), measured
