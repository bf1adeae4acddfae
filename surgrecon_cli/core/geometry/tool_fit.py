"""Where the instruments really are in a camera group's images: a move of the tools relative
to the cameras, from the shafts' silhouettes.

Robot kinematics place a tool in the world through a hand-eye calibration per camera (or
camera group); when those calibrations disagree by several mm, one world frame cannot put
the tool model on the instrument in every camera. A laparoscopic instrument's shaft is a
long dark cylinder: in every image of the group it is darker than the tissue on both sides
of it. For candidate moves of the given tools (one move for all of them and every camera of
the group), each shaft's axis is moved, sampled along its length and projected; the contrast
at a sample is the darker of the two strips just outside the instrument's silhouette minus
the strip on it (grey levels). The move that maximises the summed contrast is searched as a
translation on a coarse grid, then refined (Powell), with a rotation when allowed. Along a
single shaft a translation is barely seen: fit tools whose shafts are not parallel together,
or read only the component across the shaft. When the hand-eye errors differ per robot (as
in d-lfd), fit each robot's tool on its own (docs/dlfd.md).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from ...config import ToolConfig
from .cameras import CameraModel, project
from .tool import ToolConfigs, shaft_axis, tool_list

INSIDE = (-0.6, 0.0, 0.6)  # samples across the shaft, in radii from its axis
OUTSIDE = 1.4  # the strips just beside the silhouette, radii from the axis


@dataclass(frozen=True)
class ShaftFit:
    """How a fit looks for the shafts: `radius_m` the instruments' real shaft radius (dVRK:
    4 mm), the shaft sampled at `samples` points from `span_m` up its axis from the kinematic
    frame (m); translations on a grid of `step_m` within `search_m` per axis (m), rotation up
    to `max_turn_deg` per axis (0: none); `tolerance` the share of the best contrast within
    which coarse translations count towards `ToolOffsetFit.spread_m`."""

    radius_m: float = 0.004
    span_m: tuple[float, float] = (0.01, 0.12)
    samples: int = 24
    search_m: float = 0.024
    step_m: float = 0.003
    max_turn_deg: float = 12.0
    tolerance: float = 0.9


@dataclass(frozen=True)
class ToolOffsetFit:
    """A camera group's tool correction: `move` (4, 4), a rigid move in the world to apply
    to every tool's pose (or its inverse to the group's cameras), the summed contrast there
    and with no move (grey levels), and `spread_m` (3,): the half extent per axis of the
    coarse translations whose contrast is within `tolerance` of the best (how well the
    images pin the translation down)."""

    move: np.ndarray
    contrast: float
    contrast_at_zero: float
    spread_m: np.ndarray


def shaft_contrast(gray: np.ndarray, camera: CameraModel, cam_to_world: np.ndarray,
                   tool: tuple[np.ndarray, ToolConfig], offsets: np.ndarray,
                   options: ShaftFit = ShaftFit()) -> np.ndarray:
    """(M,) mean contrast (grey levels) of one tool's shaft in one image for each offset
    (M, 3) m (or rigid move (M, 4, 4)) of the tool (pose (4, 4), geometry): the shaft from
    `options.span_m[0]` to `[1]` up its axis from the kinematic frame, `options.radius_m`
    the instrument's real radius; samples outside the image or behind the camera are left
    out (an offset that leaves fewer than a quarter of them in the image scores zero).
    gray (H, W) float."""
    tool_pose, cfg = tool
    samples = options.samples
    if not np.isfinite(tool_pose).all():
        return np.zeros(len(offsets))
    moves = _as_moves(offsets)
    axis = shaft_axis(tool_pose, cfg)
    along = np.linspace(options.span_m[0], options.span_m[1], samples)
    centre = tool_pose[:3, 3] + along[:, None] * axis  # (S, 3)
    points = np.einsum("mij,sj->msi", moves[:, :3, :3], centre) + moves[:, None, :3, 3]
    axes = np.repeat(moves[:, :3, :3] @ axis, samples, axis=0)  # (M S, 3)
    flat = points.reshape(-1, 3)
    uv, z = project(flat, cam_to_world, camera)
    uv_ahead, _ = project(flat + 0.002 * axes, cam_to_world, camera)
    tangent = uv_ahead - uv
    with np.errstate(invalid="ignore", divide="ignore"):
        tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
        r_px = camera.K[0, 0] * options.radius_m / z
    normal = np.stack([-tangent[:, 1], tangent[:, 0]], 1) * r_px[:, None]
    offsets_r = np.array([*INSIDE, -OUTSIDE, OUTSIDE])
    at = uv[:, None, :] + offsets_r[None, :, None] * normal[:, None, :]  # (N, 5, 2)
    ok = np.isfinite(at).all(axis=(1, 2)) & (z > 0)
    ok &= ((at[..., 0] >= 0) & (at[..., 0] <= camera.width - 1) & (at[..., 1] >= 0)
           & (at[..., 1] <= camera.height - 1)).all(axis=1)
    values = _bilinear(gray, np.where(ok[:, None, None], at, 0.0))  # (N, 5)
    n_in = len(INSIDE)
    contrast = np.minimum(values[:, n_in], values[:, n_in + 1]) - values[:, :n_in].mean(1)
    ok = ok.reshape(len(offsets), samples)
    total = np.where(ok, contrast.reshape(ok.shape), 0.0).sum(1)
    n = ok.sum(1)
    return np.where(n >= samples // 4, total / np.maximum(n, 1), 0.0)


def _as_moves(offsets: np.ndarray) -> np.ndarray:
    """Translations (M, 3) or rigid moves (M, 4, 4) -> moves (M, 4, 4)."""
    offsets = np.asarray(offsets, float)
    if offsets.ndim == 3:
        return offsets
    moves = np.tile(np.eye(4), (len(offsets), 1, 1))
    moves[:, :3, 3] = offsets
    return moves


def _bilinear(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Image (H, W) at pixels uv (..., 2) inside it, bilinear."""
    u = np.clip(uv[..., 0], 0, image.shape[1] - 1.001)
    v = np.clip(uv[..., 1], 0, image.shape[0] - 1.001)
    u0, v0 = u.astype(int), v.astype(int)
    fu, fv = u - u0, v - v0
    top = image[v0, u0] * (1 - fu) + image[v0, u0 + 1] * fu
    bottom = image[v0 + 1, u0] * (1 - fu) + image[v0 + 1, u0 + 1] * fu
    return top * (1 - fv) + bottom * fv


def group_contrast(grays: Sequence[np.ndarray], cameras: Sequence[CameraModel],
                   cam_to_world: np.ndarray, tools: tuple[np.ndarray, ToolConfigs],
                   offsets: np.ndarray, options: ShaftFit = ShaftFit()) -> np.ndarray:
    """(M,) summed `shaft_contrast` over a group's cameras (grays, cameras, cam_to_world
    (C, 4, 4)) and the tools (poses (K, 4, 4), one config each)."""
    poses = np.asarray(tools[0], float).reshape(-1, 4, 4)
    total = np.zeros(len(offsets))
    for gray, camera, pose in zip(grays, cameras, cam_to_world, strict=True):
        for tool, cfg in zip(poses, tool_list(tools[1]), strict=True):
            total += shaft_contrast(gray, camera, pose, (tool, cfg), offsets, options)
    return total


def _grid(half: float, step: float) -> np.ndarray:
    ticks = np.arange(-half, half + step / 2, step)
    return np.stack(np.meshgrid(ticks, ticks, ticks, indexing="ij"), -1).reshape(-1, 3)


def rigid_move(params: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """(4, 4) world move: rotation by the rotation vector params[:3] (degrees) about `centre`
    (3,) m, then translation params[3:] (mm)."""
    R, _ = cv2.Rodrigues(np.radians(np.asarray(params[:3], float)))
    move = np.eye(4)
    move[:3, :3] = R
    move[:3, 3] = centre - R @ centre + np.asarray(params[3:], float) / 1000
    return move


def fit_tool_offset(grays: Sequence[np.ndarray], cameras: Sequence[CameraModel],
                    cam_to_world: np.ndarray, tool_poses: np.ndarray, cfgs: ToolConfigs,
                    options: ShaftFit = ShaftFit()) -> ToolOffsetFit:
    """The rigid move (world) of all tools that best lays their shafts on the dark
    instruments in a camera group's images (module docstring): a grid of translations of
    `options.step_m` within `options.search_m` per axis, then rotation (up to
    `options.max_turn_deg` per axis, about the tools' kinematic points' centroid; none when
    it is 0) and translation refined together (Powell; a result outside those limits falls
    back to the best grid offset). grays: (H, W) per camera, any grey scale (8-bit levels
    for the contrasts' units); tool_poses (K, 4, 4) world, one config each."""
    search_m, step_m = options.search_m, options.step_m
    max_turn_deg, tolerance = options.max_turn_deg, options.tolerance
    from scipy.optimize import minimize

    blurred = [cv2.GaussianBlur(np.asarray(g, np.float32), (3, 3), 0) for g in grays]
    poses = np.asarray(tool_poses, float).reshape(-1, 4, 4)
    finite = np.isfinite(poses).all(axis=(1, 2))
    centre = poses[finite, :3, 3].mean(0) if finite.any() else np.zeros(3)

    def score(moves: np.ndarray) -> np.ndarray:
        return group_contrast(blurred, cameras, cam_to_world, (poses, cfgs), moves, options)

    coarse = _grid(search_m, step_m)
    coarse_score = score(coarse)
    zero = float(score(np.zeros((1, 3)))[0])
    if coarse_score.max() <= 0:
        return ToolOffsetFit(np.eye(4), zero, zero, np.full(3, search_m))
    good = coarse[coarse_score >= tolerance * coarse_score.max()]
    start = np.r_[0.0, 0.0, 0.0, coarse[int(np.argmax(coarse_score))] * 1000]
    limit = 1000 * (search_m + step_m)
    free = slice(0, 6) if max_turn_deg > 0 else slice(3, 6)

    def params(x: np.ndarray) -> np.ndarray:
        full = start.copy()
        full[free] = x
        return full

    result = minimize(lambda x: -score(rigid_move(params(x), centre)[None])[0], start[free],
                      method="Powell", options={"xtol": 0.05, "ftol": 1e-3, "maxfev": 1500})
    x = params(result.x)
    inside = (np.abs(x[:3]) <= max_turn_deg).all() and (np.abs(x[3:]) <= limit).all()
    best = x if inside and -result.fun >= coarse_score.max() else start
    return ToolOffsetFit(move=rigid_move(best, centre), contrast=float(max(-result.fun,
                         coarse_score.max())), contrast_at_zero=zero,
                         spread_m=(good.max(0) - good.min(0)) / 2)
