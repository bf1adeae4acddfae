"""Small rendered scenes for the template/target tests (no MCAP round trip needed)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from surgrecon_cli.core.geometry.cameras import CameraModel
from surgrecon_cli.core.geometry.poses import make_pose, quat_to_matrix
from surgrecon_cli.sim.render import Renderer, tool_mesh
from surgrecon_cli.sim.scene import SimConfig, vertex_normals
from surgrecon_cli.sim.simulate import LogBuilder, _noisy_pose


@dataclass
class RenderedFrames:
    """Images (F, C) of a scene, true and tracker-noisy poses, the tool pose, true surfaces."""

    images: list[list[np.ndarray]]
    true_poses: np.ndarray  # (F, C, 4, 4)
    poses: np.ndarray  # (F, C, 4, 4) with tracker noise
    tool_poses: np.ndarray  # (F, 4, 4)
    vertices: np.ndarray  # (F, V, 3)
    faces: np.ndarray
    models: list[CameraModel]
    cfg: SimConfig


def render_frames(cfg: SimConfig, frames: list[int]) -> RenderedFrames:
    builder = LogBuilder(cfg)
    motion = builder.motion
    renderer = Renderer(builder.texture, cfg.image_noise, np.random.default_rng(cfg.seed))
    rng = np.random.default_rng(cfg.seed + 9)
    images, true_poses, poses, tools, verts = [], [], [], [], []
    for frame in frames:
        t = builder.frame_times[frame]
        v = motion.tissue_vertices(t)
        normals = vertex_normals(v, builder.mesh.faces)
        tip, quat = motion.tool_pose(t)
        tool = tool_mesh(tip, quat_to_matrix(quat)[:, 2], cfg.tool_radius, cfg.tool_length)
        row, tp, np_ = [], [], []
        for cam in range(cfg.cameras):
            T = motion.camera_pose(cam, builder.image_stamp(frame, cam))
            row.append(
                renderer.render(
                    cam,
                    builder.models[cam],
                    T,
                    v,
                    normals,
                    builder.mesh.faces,
                    builder.mesh.material_xy,
                    tool,
                )
            )
            tp.append(T)
            np_.append(make_pose(*_noisy_pose(T, cfg, rng)))
        images.append(row)
        true_poses.append(tp)
        poses.append(np_)
        tools.append(make_pose(tip, quat))
        verts.append(v)
    return RenderedFrames(
        images,
        np.array(true_poses),
        np.array(poses),
        np.array(tools),
        np.array(verts),
        builder.mesh.faces,
        builder.models,
        cfg,
    )


def tool_pose_along(tip: np.ndarray, axis: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """A tool pose (4, 4) with its tip at `tip` (m) and its z axis along `axis`; x is
    perpendicular to both `reference` and z."""
    z = axis / np.linalg.norm(axis)
    x = np.cross(reference, z)
    x /= np.linalg.norm(x)
    pose = np.eye(4)
    pose[:3, :3] = np.column_stack([x, np.cross(z, x), z])
    pose[:3, 3] = tip
    return pose
