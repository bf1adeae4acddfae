"""Pinhole cameras with lens distortion, OpenCV/ROS conventions.

Distortion models: core/geometry/distortion.py.

Poses are camera-to-world (4, 4) in the optical frame: x right, y down, z forward.
Pixels are (u, v) with the origin at the top-left pixel's centre. Normalised coordinates are
(x/z, y/z), dimensionless; pixels are K applied to the *distorted* normalised coordinates.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...errors import GeometryError
from .distortion import (
    DISTORTION_MODELS,
    distort_normalized,
    distortion_jacobian,
    distortion_model_name,
    reduce_intrinsics,
    undistort_normalized,
)
from .poses import invert_pose


@dataclass(frozen=True)
class CameraModel:
    """Intrinsics of one camera: K (3, 3) in px, distortion coefficients `dist` of `model`
    ((5,) plumb_bob, (8,) rational_polynomial, (4,) equidistant; fewer are padded with
    zeros), image size in px."""

    K: np.ndarray
    dist: np.ndarray
    width: int
    height: int
    model: str = "plumb_bob"

    def __post_init__(self) -> None:
        if self.model not in DISTORTION_MODELS:
            raise GeometryError(f"distortion model {self.model!r} is not supported; supported: "
                                f"{', '.join(DISTORTION_MODELS)}")
        n = DISTORTION_MODELS[self.model]
        K = np.asarray(self.K, float).reshape(3, 3)
        d = np.asarray(self.dist, float).ravel()
        if d.size > n and np.any(d[n:] != 0):
            raise GeometryError(f"{self.model} distortion has {n} coefficients, got {d.size} "
                                f"with non-zero ones after the {n}th: {d.tolist()}")
        dist = np.zeros(n)
        dist[: min(n, d.size)] = d[:n]
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
            "model": self.model,
        }

    @classmethod
    def from_dict(cls, d: dict) -> CameraModel:
        """Inverse of `to_dict`; dicts written before models were recorded are plumb_bob."""
        return cls(np.asarray(d["K"]), np.asarray(d["dist"]), int(d["width"]), int(d["height"]),
                   str(d.get("model", "plumb_bob")))

    def same_as(self, other: CameraModel) -> bool:
        """Same model, image size and (to float tolerance) K and coefficients."""
        return (self.model == other.model and (self.width, self.height) == (other.width,
                                                                            other.height)
                and np.allclose(self.K, other.K) and np.allclose(self.dist, other.dist))

    @classmethod
    def from_camera_info(
        cls,
        K: np.ndarray,
        D: np.ndarray,
        distortion_model: str,
        width: int,
        height: int,
        binning_x: int = 0,
        binning_y: int = 0,
        roi: tuple[int, int, int, int, bool] = (0, 0, 0, 0, False),
    ) -> CameraModel:
        """The model of the images a `sensor_msgs/CameraInfo` describes.

        K (3, 3) px and width/height px are the full-resolution calibration; D its
        coefficients; roi = (x_offset, y_offset, width, height, do_rectify) in full-resolution
        px. Binning and ROI are applied as ROS `image_geometry.PinholeCameraModel` does
        (`fromCameraInfo`, `reducedResolution`), for the raw (distorted) images:

        - binning 0 means 1 (no binning); an all-zero ROI means the full image;
        - the principal point moves by the ROI offset, then the x row of K (fx, cx) is
          divided by binning_x and the y row (fy, cy) by binning_y
          (u_image = (u_full - x_offset) / binning_x, likewise v). image_geometry leaves a
          skew K[0, 1] unscaled; here it is scaled with its row so that the mapping stays
          exact (ROS calibrations have zero skew). The half-pixel shift between the pixel
          centres of binned and unbinned images is ignored, as in image_geometry;
        - the image is roi.width // binning_x by roi.height // binning_y px;
        - D is unchanged: distortion acts on normalised coordinates, before K;
        - do_rectify only asks for a rectified ROI (the bounding box of the undistorted raw
          ROI) for *rectified* images; raw images cover the raw ROI, so it changes nothing
          here.

        Raises GeometryError (one line) for an unsupported distortion model, an ROI outside
        the full image, or invalid intrinsics.
        """
        D = np.asarray(D, float).ravel()
        model = distortion_model_name(distortion_model, D)
        Kr, w, h = reduce_intrinsics(np.asarray(K, float).reshape(3, 3), int(width), int(height),
                                     binning_x, binning_y, roi)
        return cls(Kr, D, w, h, model)


def world_to_camera(points: np.ndarray, cam_to_world: np.ndarray) -> np.ndarray:
    """World points (N, 3) -> camera-frame points (N, 3) (metres)."""
    T = invert_pose(cam_to_world)
    return points @ T[:3, :3].T + T[:3, 3]


def project(
    points: np.ndarray, cam_to_world: np.ndarray, camera: CameraModel, distort: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """Project world points (N, 3) m into a camera. Returns pixels (N, 2) and depth z (N,) m;
    distort=False gives the undistorted (pinhole) pixels.

    Points with z <= 0 get NaN pixels.
    """
    pc = world_to_camera(np.asarray(points, float), cam_to_world)
    z = pc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        xy = pc[:, :2] / z[:, None]
    xy[z <= 1e-9] = np.nan
    if distort:
        xy = distort_normalized(xy, camera.dist, camera.model)
    uv = xy @ camera.K[:2, :2].T + camera.K[:2, 2]
    return uv, z


def projection_jacobian(
    points: np.ndarray, cam_to_world: np.ndarray, camera: CameraModel, distort: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """∂ pixel / ∂ world point (N, 2, 3) px/m of `project` at points (N, 3) m, analytic
    (lens distortion included unless distort=False), and the depths z (N,) m. NaN rows for
    points with z <= 0."""
    T = invert_pose(cam_to_world)
    pc = np.asarray(points, float) @ T[:3, :3].T + T[:3, 3]
    z = pc[:, 2]
    inv_z = np.where(z > 1e-9, 1.0 / np.where(z > 1e-9, z, 1.0), np.nan)
    xy = pc[:, :2] * inv_z[:, None]
    dxy = np.zeros((len(pc), 2, 3))  # ∂ normalised / ∂ camera-frame point
    dxy[:, 0, 0] = dxy[:, 1, 1] = inv_z
    dxy[:, :, 2] = -xy * inv_z[:, None]
    if distort:
        dxy = np.einsum("nab,nbc->nac", distortion_jacobian(xy, camera.dist, camera.model), dxy)
    J = np.einsum("ab,nbc,cd->nad", camera.K[:2, :2], dxy, T[:3, :3])
    return J, z


def distortion_jacobians(normalized: np.ndarray, cameras: np.ndarray,
                         models: list[CameraModel]) -> np.ndarray:
    """∂ distorted / ∂ undistorted normalised coordinates (M, 2, 2) of observations at
    undistorted normalised coordinates (M, 2) in cameras (M,) (indices into `models`);
    identity where the coordinates are not finite. Multiplying a pinhole Jacobian by it
    (times the focal length) gives the pixel Jacobian of any model."""
    xy = np.asarray(normalized, float).reshape(-1, 2)
    cameras = np.asarray(cameras, int)
    J = np.broadcast_to(np.eye(2), (len(xy), 2, 2)).copy()
    finite = np.isfinite(xy).all(1)
    for c in np.unique(cameras[finite]):
        sel = finite & (cameras == c)
        J[sel] = distortion_jacobian(xy[sel], models[c].dist, models[c].model)
    return J


def view_distortion_jacobians(points: np.ndarray, cameras: np.ndarray, poses: np.ndarray,
                              models: list[CameraModel]) -> np.ndarray:
    """`distortion_jacobians` where world points (M, 3) m project in cameras (M,) with
    camera-to-world poses (C, 4, 4) (identity for points behind their camera)."""
    points = np.asarray(points, float).reshape(-1, 3)
    cameras = np.asarray(cameras, int)
    T = invert_pose(np.asarray(poses, float))[cameras]
    pc = np.einsum("mij,mj->mi", T[:, :3, :3], points) + T[:, :3, 3]
    z = pc[:, 2]
    xy = np.full((len(pc), 2), np.nan)
    front = z > 1e-9
    xy[front] = pc[front, :2] / z[front, None]
    return distortion_jacobians(xy, cameras, models)


def in_image(uv: np.ndarray, camera: CameraModel, border: float = 0.0) -> np.ndarray:
    """(N,) bool: pixel inside the image, `border` px away from its edges."""
    with np.errstate(invalid="ignore"):
        return (
            (uv[:, 0] >= border)
            & (uv[:, 1] >= border)
            & (uv[:, 0] <= camera.width - 1 - border)
            & (uv[:, 1] <= camera.height - 1 - border)
        )


def undistort_pixels(uv: np.ndarray, camera: CameraModel, polish: bool = True) -> np.ndarray:
    """Distorted pixels (N, 2) -> normalised undistorted coordinates (N, 2), the inverse of
    `project` (see `undistort_normalized`, also for `polish`)."""
    uv = np.asarray(uv, float).reshape(-1, 2)
    if len(uv) == 0:
        return np.zeros((0, 2))
    xy_d = (uv - camera.K[:2, 2]) @ np.linalg.inv(camera.K[:2, :2]).T
    return undistort_normalized(xy_d, camera.dist, camera.model, polish)


def pixel_rays(
    uv: np.ndarray, camera: CameraModel, cam_to_world: np.ndarray, polish: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """Rays through distorted pixels (N, 2): origin (3,) and unit directions (N, 3) in world
    (`polish`: see `undistort_normalized`)."""
    xy = undistort_pixels(uv, camera, polish)
    d = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
    d = d @ cam_to_world[:3, :3].T
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return cam_to_world[:3, 3].copy(), d


def projection_matrix(cam_to_world: np.ndarray) -> np.ndarray:
    """3x4 normalised projection matrix [R | t] (world -> camera) for undistorted coords."""
    return invert_pose(cam_to_world)[:3, :]
