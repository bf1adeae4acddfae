"""Surgical tool removal from robot kinematics (Su et al. 2019, section II.C).

The tool is modelled as a capsule: a shaft cylinder of `shaft_radius_m` from the tip along
the tool frame's +z axis for `shaft_length_m`, with a rounded tip. A pixel is masked when its
viewing ray passes within radius + margin of the shaft axis (margin given in px, turned
into metres at the ray's depth); a 3D point is dropped when it lies closer than
radius + margin to the axis.
"""

from __future__ import annotations

import cv2
import numpy as np

from ..config import ToolConfig
from .cameras import CameraModel, pixel_rays
from .geometry import point_to_segment_distance


def shaft_segment(tool_pose: np.ndarray, cfg: ToolConfig) -> tuple[np.ndarray, np.ndarray]:
    """Ends (3,) of the capsule's axis in the world, from the tool-tip pose (4, 4): from the
    centre of the rounded end (one radius up the shaft, so the surface touches the tip) to
    `shaft_length_m` from the tip."""
    tip, axis = tool_pose[:3, 3], tool_pose[:3, 2]
    return tip + axis * cfg.shaft_radius_m, tip + axis * max(cfg.shaft_length_m, cfg.shaft_radius_m)


def push_out_of_tool(points: np.ndarray, tool_pose: np.ndarray, cfg: ToolConfig
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Tissue cannot be inside the tool: points (N, 3) m inside the capsule are moved along
    the shaft axis, towards the tip, onto the capsule's surface (where the tool presses
    the tissue). Returns inside (N,) bool and the pushed points (N, 3)."""
    pushed = np.array(points, dtype=float)
    if not np.isfinite(tool_pose).all() or len(points) == 0:
        return np.zeros(len(points), bool), pushed
    a, b = shaft_segment(tool_pose, cfg)
    axis = (b - a) / np.linalg.norm(b - a)
    rel = pushed - a
    along = rel @ axis
    radial2 = (rel**2).sum(1) - along**2
    inside = (radial2 < cfg.shaft_radius_m**2) & (along <= np.linalg.norm(b - a))
    surface = -np.sqrt(np.maximum(cfg.shaft_radius_m**2 - radial2, 0.0))  # rounded end, below a
    inside &= along > surface
    pushed[inside] -= ((along - surface)[inside] + 1e-6)[:, None] * axis  # 1 µm clear
    return inside, pushed


def ray_segment_distance(origin: np.ndarray, dirs: np.ndarray, a: np.ndarray, b: np.ndarray):
    """Closest distance (N,) between rays origin + s*dirs (s >= 0, dirs unit (N, 3)) and the
    segment a-b, with the ray parameter s (N,) at the closest approach."""
    u = b - a
    w0 = origin - a
    uu = float(u @ u)
    du = dirs @ u
    dw = dirs @ w0
    uw = float(u @ w0)
    denom = uu - du**2  # |d|=1
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(denom > 1e-12, (du * uw - uu * dw) / denom, 0.0)
    s = np.maximum(s, 0.0)
    t = ((s * du + uw) / uu).clip(0.0, 1.0)
    # Re-optimise s for the clamped t.
    s = np.maximum(((a + t[:, None] * u - origin) * dirs).sum(1), 0.0)
    diff = origin + s[:, None] * dirs - (a + t[:, None] * u)
    return np.linalg.norm(diff, axis=1), s


def tool_pixel_mask(
    pixels: np.ndarray,
    camera: CameraModel,
    cam_to_world: np.ndarray,
    tool_pose: np.ndarray,
    cfg: ToolConfig,
) -> np.ndarray:
    """(N,) bool: pixels (N, 2) whose rays hit the tool capsule inflated by the px margin."""
    if not np.isfinite(tool_pose).all() or len(pixels) == 0:
        return np.zeros(len(pixels), bool)
    a, b = shaft_segment(tool_pose, cfg)
    origin, dirs = pixel_rays(pixels, camera, cam_to_world)
    dist, s = ray_segment_distance(origin, dirs, a, b)
    margin = cfg.mask_margin_px * s / camera.K[0, 0]
    return dist <= cfg.shaft_radius_m + margin


def tool_image_mask(camera: CameraModel, cam_to_world: np.ndarray, tool_pose: np.ndarray,
                    cfg: ToolConfig, step: int = 4) -> np.ndarray:
    """(H, W) bool mask of the tool in one image.

    Rays are cast every `step` px and the coarse mask is dilated by `step` px, so the mask
    errs on the side of removing a few more tissue pixels at the tool's silhouette (cheap:
    the exact ray test costs an undistortion per pixel).
    """
    if not np.isfinite(tool_pose).all():
        return np.zeros((camera.height, camera.width), bool)
    us, vs = np.arange(0, camera.width, step), np.arange(0, camera.height, step)
    u, v = np.meshgrid(us, vs)
    pixels = np.stack([u.ravel(), v.ravel()], 1).astype(float)
    coarse = tool_pixel_mask(pixels, camera, cam_to_world, tool_pose, cfg).reshape(u.shape)
    full = np.repeat(np.repeat(coarse, step, axis=0), step, axis=1)[: camera.height, : camera.width]
    kernel = np.ones((2 * step + 1, 2 * step + 1), np.uint8)
    return cv2.dilate(full.astype(np.uint8), kernel).astype(bool)


def points_near_tool(points: np.ndarray, tool_pose: np.ndarray, cfg: ToolConfig) -> np.ndarray:
    """(N,) bool: 3D points (N, 3) closer than radius + margin to the shaft axis."""
    if not np.isfinite(tool_pose).all() or len(points) == 0:
        return np.zeros(len(points), bool)
    a, b = shaft_segment(tool_pose, cfg)
    return point_to_segment_distance(points, a, b) <= cfg.shaft_radius_m + cfg.margin_m
