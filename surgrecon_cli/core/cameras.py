"""Pinhole cameras with plumb_bob distortion (k1 k2 p1 p2 k3), OpenCV/ROS conventions.

Poses are camera-to-world (4, 4) in the optical frame: x right, y down, z forward.
Pixels are (u, v) with the origin at the top-left pixel's centre.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..errors import GeometryError
from .geometry import invert_pose


@dataclass(frozen=True)
class CameraModel:
    """Intrinsics of one camera: K (3, 3) in px, distortion (5,) plumb_bob, image size in px."""

    K: np.ndarray
    dist: np.ndarray
    width: int
    height: int

    def __post_init__(self) -> None:
        K = np.asarray(self.K, float).reshape(3, 3)
        dist = np.zeros(5)
        d = np.asarray(self.dist, float).ravel()[:5]
        dist[: d.size] = d
        if not (np.isfinite(K).all() and np.isfinite(dist).all()) or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise GeometryError(f"invalid intrinsics K={K.tolist()} dist={dist.tolist()}")
        if self.width <= 0 or self.height <= 0:
            raise GeometryError(f"invalid image size {self.width}x{self.height}")
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "dist", dist)

    def to_dict(self) -> dict:
        return {
            "K": self.K.tolist(),
            "dist": self.dist.tolist(),
            "width": self.width,
            "height": self.height,
        }

    @classmethod
    def from_dict(cls, d: dict) -> CameraModel:
        return cls(np.asarray(d["K"]), np.asarray(d["dist"]), int(d["width"]), int(d["height"]))


def distort_normalized(xy: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Apply plumb_bob distortion to normalised coordinates (N, 2)."""
    k1, k2, p1, p2, k3 = dist
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([xd, yd], axis=1)


def world_to_camera(points: np.ndarray, cam_to_world: np.ndarray) -> np.ndarray:
    """World points (N, 3) -> camera-frame points (N, 3) (metres)."""
    T = invert_pose(cam_to_world)
    return points @ T[:3, :3].T + T[:3, 3]


def project(
    points: np.ndarray, cam_to_world: np.ndarray, camera: CameraModel, distort: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """Project world points (N, 3) into a camera. Returns pixels (N, 2) and depth z (N,) in m.

    Points with z <= 0 get NaN pixels.
    """
    pc = world_to_camera(np.asarray(points, float), cam_to_world)
    z = pc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        xy = pc[:, :2] / z[:, None]
    xy[z <= 1e-9] = np.nan
    if distort:
        xy = distort_normalized(xy, camera.dist)
    uv = xy @ camera.K[:2, :2].T + camera.K[:2, 2]
    return uv, z


def in_image(uv: np.ndarray, camera: CameraModel, border: float = 0.0) -> np.ndarray:
    """(N,) bool: pixel inside the image, `border` px away from its edges."""
    with np.errstate(invalid="ignore"):
        return (
            (uv[:, 0] >= border)
            & (uv[:, 1] >= border)
            & (uv[:, 0] <= camera.width - 1 - border)
            & (uv[:, 1] <= camera.height - 1 - border)
        )


def undistort_pixels(uv: np.ndarray, camera: CameraModel) -> np.ndarray:
    """Distorted pixels (N, 2) -> normalised undistorted coordinates (N, 2) (iterative)."""
    if len(uv) == 0:
        return np.zeros((0, 2))
    pts = np.ascontiguousarray(uv, dtype=np.float64).reshape(-1, 1, 2)
    out = cv2.undistortPointsIter(
        pts,
        camera.K,
        camera.dist,
        None,
        None,
        (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-10),
    )
    return out.reshape(-1, 2)


def pixel_rays(
    uv: np.ndarray, camera: CameraModel, cam_to_world: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Rays through distorted pixels (N, 2): origin (3,) and unit directions (N, 3) in world."""
    xy = undistort_pixels(uv, camera)
    d = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
    d = d @ cam_to_world[:3, :3].T
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return cam_to_world[:3, 3].copy(), d


def projection_matrix(cam_to_world: np.ndarray) -> np.ndarray:
    """3x4 normalised projection matrix [R | t] (world -> camera) for undistorted coords."""
    return invert_pose(cam_to_world)[:3, :]
