"""The localisation error a frame's tracked pixels actually carry, measured from their
over-determined evidence (no constants fitted to a simulator).

The Cramér-Rao bound of locating a patch (core/noise/model.py) is a floor: on real images
(compression, demosaicing, specular highlights, interlacing, focus) the error is several
times larger. A point found by >= 2 cameras in a frame is re-triangulated from its tracked
pixels; its residuals leave 2n − 3 degrees of freedom (two views: the error across the
epipolar line), which measure the frame's true per-view pixel error σ_k
(`pixel_noise_from_residuals`). What σ_k² carries beyond the variance the noise model
predicts for those views (pixel noise + tracking bound + the pose error a view's residuals
can see) is added to every tracked pixel's localisation variance. Pure numpy; no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry.cameras import CameraModel, undistort_pixels, view_distortion_jacobians
from ..geometry.triangulate import Observations, Triangulation, triangulate
from .model import (
    NoiseModel,
    body_pose_covariance,
    pixel_noise_from_residuals,
    point_covariances,
    projection_jacobians,
)

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


@dataclass(frozen=True)
class MultiView:
    """A frame's points found by >= 2 cameras, re-triangulated from their tracked pixels
    without any gate: their rows idx (K,) among the frame's points, their observations
    (points numbered 0..K-1 in the order of idx) and their triangulation."""

    idx: np.ndarray
    obs: Observations
    tri: Triangulation

    def of_rows(self, rows: np.ndarray) -> tuple[Observations, Triangulation]:
        """Observations and triangulation of the points `rows` (ascending, a subset of idx),
        numbered 0..len(rows)-1: what triangulating them alone gives."""
        keep = np.isin(self.idx, rows)
        return self.obs.renumbered(keep), self.tri.of_points(keep, self.obs.point)


def triangulate_found(found: np.ndarray, pixels: np.ndarray, models: list[CameraModel],
                      poses: np.ndarray) -> MultiView:
    """The points found (N, C) bool by >= 2 cameras, triangulated from their pixels
    (N, C, 2) px at camera poses (C, 4, 4): once per frame, for the frame's noise
    (`tracking_excess_px2`) and the target's reprojection check (core/target/cloud.py)."""
    idx = np.flatnonzero(found.sum(1) >= 2)
    obs = tracked_observations(found[idx], pixels[idx], models)
    return MultiView(idx, obs, triangulate(obs, poses, models, len(idx)))


def tracking_excess_px2(multi: MultiView, localisation: np.ndarray, models: list[CameraModel],
                        noise: NoiseModel) -> tuple[float, float]:
    """(excess variance px², measured σ_k px) of a frame's tracked pixels: multi the points
    found by >= 2 cameras (`triangulate_found`), localisation (N, C) px² the tracking bound
    of each found pixel (module docstring). (0, NaN) with fewer than MIN_POINTS such
    points."""
    idx, obs, tri = multi.idx, multi.obs, multi.tri
    if len(idx) < MIN_POINTS:
        return 0.0, float("nan")
    residual, depth = tri.residual_px, tri.depth
    measured = pixel_noise_from_residuals(residual, obs.point)
    focal = np.array([m.K[0, 0] for m in models])[obs.camera]
    predicted = noise.tracked_view_variance_px2(
        depth, focal, localisation[idx[obs.point], obs.camera],
        pose=~noise.on_shared_body(obs.camera))
    predicted = predicted[np.isfinite(predicted) & (depth > 0)]
    if not np.isfinite(measured) or predicted.size == 0:
        return 0.0, float("nan")
    return max(0.0, measured**2 - float(np.median(predicted))), measured


def retriangulate(found: np.ndarray, pixels: np.ndarray, models: list[CameraModel],
                  poses: np.ndarray, noise: NoiseModel) -> tuple[np.ndarray, np.ndarray,
                                                                  np.ndarray]:
    """Every point found (N, C) bool by >= 2 cameras, re-triangulated from its tracked pixels
    (N, C, 2) px at camera poses (C, 4, 4), without any gate: positions (N, 3) m and their
    covariances (N, 3, 3) m² from image noise (pixel noise + the frame's tracking noise,
    `noise.tracking_px`) and from the cameras' pose errors (per view, or the rigid error of a
    shared tracker body). NaN for the other points. The classifier's own look at the
    evidence a gate summarised (core/target/cloud.py calls a point static when its frame-0
    position still explains every view separately; its views together may not)."""
    n = len(found)
    found = found & np.isfinite(poses).all((1, 2))[None, :]  # a camera without a pose: unused
    positions = np.full((n, 3), np.nan)
    image_cov = np.full((n, 3, 3), np.nan)
    pose_cov = np.full((n, 3, 3), np.nan)
    multi = triangulate_found(found, pixels, models, poses)
    idx, obs, tri = multi.idx, multi.obs, multi.tri
    if len(idx) == 0:
        return positions, image_cov, pose_cov
    ok = tri.in_front & np.isfinite(tri.points).all(1)
    at = np.nan_to_num(tri.points[obs.point])
    focal = np.array([m.K[0, 0] for m in models])[obs.camera]
    J, z = projection_jacobians(at, poses[obs.camera], focal,
                                view_distortion_jacobians(at, obs.camera, poses, models))
    image = noise.tracked_view_variance_px2(z, focal, np.full(len(z), noise.tracking_px**2),
                                            pose=False)
    independent = image + np.where(noise.on_shared_body(obs.camera), 0.0,
                                   noise.pose_variance_px2(z, focal))
    cov = point_covariances(obs.point, J, image, len(idx))
    body = body_pose_covariance(np.nan_to_num(tri.points), obs.point, obs.camera,
                                poses[:, :3, 3], noise)
    pose = point_covariances(obs.point, J, independent, len(idx)) - cov + body
    positions[idx[ok]] = tri.points[ok]
    image_cov[idx[ok]] = cov[ok]
    pose_cov[idx[ok]] = pose[ok]
    return positions, image_cov, pose_cov
