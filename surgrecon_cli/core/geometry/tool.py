"""Surgical tool removal from robot kinematics (Su et al. 2019, section II.C).

A tool is modelled as capsules: a shaft cylinder of `shaft_radius_m` from the kinematic
frame along its `shaft_axis` (default +z) for `shaft_length_m`, with a rounded tip; and,
when `jaw_length_m` > 0, a jaw/wrist part beyond the frame (the other way along the axis):
from `jaw_offset_m` to `jaw_offset_m + jaw_length_m`, `jaw_width_m` wide (a capsule of
radius width/2 around that segment, so it errs by half a width past each end). A pixel is
masked when its viewing ray passes within radius + margin of a capsule's axis (margin given
in px, turned into metres at the ray's depth); a 3D point is dropped when it lies closer
than radius + margin to one.

Several tools (every arm of a dVRK): the functions that mask or drop take the tools' poses
stacked (K, 4, 4) with one config each (a sequence of K), or one pose (4, 4) and its config;
a tool whose pose is not finite (unknown at that frame) masks nothing.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from ...config import ToolConfig
from .cameras import CameraModel, pixel_rays
from .poses import point_to_segment_distance

Capsule = tuple[np.ndarray, np.ndarray, float]
"""Axis ends a, b (3,) in the world and radius (m)."""
ToolPoses = np.ndarray
"""One tool's pose (4, 4) or several tools' poses (K, 4, 4), in the world."""
ToolConfigs = ToolConfig | Sequence[ToolConfig]
_AXES = {"x": 0, "y": 1, "z": 2}


def tool_list(cfgs: ToolConfigs) -> list[ToolConfig]:
    """The tools' configs as a list (one config or a sequence of them)."""
    return [cfgs] if isinstance(cfgs, ToolConfig) else list(cfgs)


def tool_name(index: int) -> str:
    """How outputs name tool `index` in `Config.tool_configs()` order: `tool` for the `[tool]`,
    `tool_K` for the K-th `[[tools]]` table (K from 1)."""
    return "tool" if index == 0 else f"tool_{index}"


def shaft_axis(tool_pose: np.ndarray, cfg: ToolConfig) -> np.ndarray:
    """Unit direction (3,) from the kinematic frame up the shaft (`cfg.shaft_axis`)."""
    sign = -1.0 if cfg.shaft_axis.startswith("-") else 1.0
    return sign * tool_pose[:3, _AXES[cfg.shaft_axis[-1]]]


def shaft_segment(tool_pose: np.ndarray, cfg: ToolConfig) -> tuple[np.ndarray, np.ndarray]:
    """Ends (3,) of the capsule's axis in the world, from the tool-tip pose (4, 4): from the
    centre of the rounded end (one radius up the shaft, so the surface touches the tip) to
    `shaft_length_m` from the tip."""
    tip, axis = tool_pose[:3, 3], shaft_axis(tool_pose, cfg)
    return tip + axis * cfg.shaft_radius_m, tip + axis * max(cfg.shaft_length_m, cfg.shaft_radius_m)


def working_end(tool_pose: np.ndarray, cfg: ToolConfig) -> tuple[np.ndarray, float]:
    """Where the tool meets the tissue: a pose (4, 4) at the tool's far end (the tip, or the
    end of the jaw/wrist part when it has one) with +z up the shaft, and that part's radius
    (m). For a shaft along +z without a jaw this is the tool pose itself."""
    k = _AXES[cfg.shaft_axis[-1]]
    up = shaft_axis(tool_pose, cfg)
    x = tool_pose[:3, (k + 1) % 3]
    end = np.array(tool_pose, dtype=float)
    end[:3, :3] = np.column_stack([x, np.cross(up, x), up])
    if cfg.jaw_length_m > 0:
        end[:3, 3] -= up * (cfg.jaw_offset_m + cfg.jaw_length_m)
        return end, cfg.jaw_width_m / 2
    return end, cfg.shaft_radius_m


def tool_capsules(tool_poses: ToolPoses, cfgs: ToolConfigs) -> list[Capsule]:
    """Every capsule (shaft, jaw) of the tools whose pose is finite."""
    poses = np.asarray(tool_poses, float).reshape(-1, 4, 4)
    configs = tool_list(cfgs)
    if len(configs) != len(poses):
        raise ValueError(f"{len(poses)} tool poses but {len(configs)} tool configs")
    out: list[Capsule] = []
    for pose, cfg in zip(poses, configs, strict=True):
        if not np.isfinite(pose).all():
            continue
        a, b = shaft_segment(pose, cfg)
        out.append((a, b, cfg.shaft_radius_m))
        if cfg.jaw_length_m > 0:
            tip, axis = pose[:3, 3], shaft_axis(pose, cfg)
            out.append((tip - axis * cfg.jaw_offset_m,
                        tip - axis * (cfg.jaw_offset_m + cfg.jaw_length_m), cfg.jaw_width_m / 2))
    return out


def camera_tool_poses(tool_poses: ToolPoses, cfgs: ToolConfigs, cameras: Sequence[str]
                      ) -> np.ndarray | None:
    """Each camera's view of the tools (C, K, 4, 4): the tools' world poses (K, 4, 4) (or one
    (4, 4)) moved by their `camera_offsets` entry for that camera (a hand-eye error measured
    per camera, e.g. with `tool_fit`), unmoved for a camera without one; None when no tool
    has any. Raises ValueError for an entry naming a camera not in `cameras`."""
    configs = tool_list(cfgs)
    if not any(c.camera_offsets for c in configs):
        return None
    poses = np.asarray(tool_poses, float).reshape(-1, 4, 4)
    out = np.repeat(poses[None], len(cameras), axis=0)
    index = {name: c for c, name in enumerate(cameras)}
    for k, cfg in enumerate(configs):
        for entry in cfg.camera_offsets:
            name, *xyz = entry.split()
            if name not in index:
                raise ValueError(f"tool.camera_offsets names camera {name!r}; the log's cameras "
                                 f"are {', '.join(cameras)}")
            out[index[name], k, :3, 3] += np.array(xyz, float)
    return out


def flatten_camera_tools(tool_poses: np.ndarray, cfgs: ToolConfigs
                         ) -> tuple[np.ndarray, list[ToolConfig]]:
    """Per-camera tool poses (C, K, 4, 4) -> every camera's view of every tool as tools of
    their own (C K, 4, 4) with their configs, for 3D tests that must clear all of them; shared
    poses ((K, 4, 4) or (4, 4)) pass through."""
    configs = tool_list(cfgs)
    poses = np.asarray(tool_poses, float)
    if poses.ndim < 4:
        return poses.reshape(-1, 4, 4), configs
    return poses.reshape(-1, 4, 4), configs * poses.shape[0]


def _margins(cfgs: ToolConfigs, attribute: str) -> float:
    """The largest margin of the tools (one margin per mask/cut)."""
    configs = tool_list(cfgs)
    return max((float(getattr(c, attribute)) for c in configs), default=0.0)


def push_out_of_tool(points: np.ndarray, tool_pose: ToolPoses, cfg: ToolConfigs
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Tissue cannot be inside a tool: points (N, 3) m inside a tool's shaft capsule are
    moved along its axis, towards the tip, onto the capsule's surface (where the tool
    presses the tissue), tool after tool. Returns inside (N,) bool (inside any) and the
    pushed points (N, 3)."""
    poses = np.asarray(tool_pose, float).reshape(-1, 4, 4)
    configs = tool_list(cfg)
    inside = np.zeros(len(points), bool)
    pushed = np.array(points, dtype=float)
    for pose, config in zip(poses, configs, strict=True):
        inside_k, pushed = _push_out_of_shaft(pushed, pose, config)
        inside |= inside_k
    return inside, pushed


def _push_out_of_shaft(points: np.ndarray, tool_pose: np.ndarray, cfg: ToolConfig
                       ) -> tuple[np.ndarray, np.ndarray]:
    """`push_out_of_tool` for one tool's shaft."""
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
    tool_pose: ToolPoses,
    cfg: ToolConfigs,
) -> np.ndarray:
    """(N,) bool: pixels (N, 2) whose rays hit a tool capsule inflated by the px margin (rays
    at pixel accuracy: OpenCV's undistortion without the Newton polish)."""
    capsules = tool_capsules(tool_pose, cfg)
    out = np.zeros(len(pixels), bool)
    if not capsules or len(pixels) == 0:
        return out
    origin, dirs = pixel_rays(pixels, camera, cam_to_world, polish=False)
    margin_px = _margins(cfg, "mask_margin_px")
    for a, b, radius in capsules:
        dist, s = ray_segment_distance(origin, dirs, a, b)
        out |= dist <= radius + margin_px * s / camera.K[0, 0]
    return out


def tool_image_mask(camera: CameraModel, cam_to_world: np.ndarray, tool_pose: ToolPoses,
                    cfg: ToolConfigs, step: int = 4) -> np.ndarray:
    """(H, W) bool mask of the tool in one image.

    Rays are cast every `step` px and the coarse mask is dilated by `step` px, so the mask
    errs on the side of removing a few more tissue pixels at the tool's silhouette (cheap:
    the exact ray test costs an undistortion per pixel).
    """
    if not tool_capsules(tool_pose, cfg):
        return np.zeros((camera.height, camera.width), bool)
    us, vs = np.arange(0, camera.width, step), np.arange(0, camera.height, step)
    u, v = np.meshgrid(us, vs)
    pixels = np.stack([u.ravel(), v.ravel()], 1).astype(float)
    coarse = tool_pixel_mask(pixels, camera, cam_to_world, tool_pose, cfg).reshape(u.shape)
    full = np.repeat(np.repeat(coarse, step, axis=0), step, axis=1)[: camera.height, : camera.width]
    kernel = np.ones((2 * step + 1, 2 * step + 1), np.uint8)
    return cv2.dilate(full.astype(np.uint8), kernel).astype(bool)


def points_near_tool(points: np.ndarray, tool_pose: ToolPoses, cfg: ToolConfigs) -> np.ndarray:
    """(N,) bool: 3D points (N, 3) closer than radius + margin to a capsule's axis."""
    out = np.zeros(len(points), bool)
    if len(points) == 0:
        return out
    margin = _margins(cfg, "margin_m")
    for a, b, radius in tool_capsules(tool_pose, cfg):
        out |= point_to_segment_distance(points, a, b) <= radius + margin
    return out
