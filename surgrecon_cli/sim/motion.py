"""Ground-truth motion of the simulated cavity (see sim/scene.py for the scene): breathing,
the tool's indentation, the rigid-scene and camera-sweep variants, as functions of time."""

from __future__ import annotations

import numpy as np

from ..core.geometry.poses import make_pose, matrix_to_quat
from .scene import SimConfig, TissueMesh, smoothstep


class Motion:
    """Ground-truth motion of tissue, tool and cameras as functions of time (s)."""

    def __init__(self, cfg: SimConfig, mesh: TissueMesh):
        self.cfg = cfg
        self.mesh = mesh
        rng = np.random.default_rng(cfg.seed + 202)
        duration = cfg.frames / cfg.frame_rate
        # Tool: approaches from above and to the side; axis u points from the tip up the shaft.
        axis = np.array([-0.35, 0.25, 1.0])
        self.tool_axis = axis / np.linalg.norm(axis)
        contact = np.asarray(cfg.contact_xy, float)
        self.contact_rest = np.array([*contact, 0.0])
        nearest = np.argmin(((mesh.vertices[:, :2] - contact) ** 2).sum(1))
        self.contact_rest[2] = mesh.vertices[nearest, 2]
        self.t_contact = 0.1 * duration
        self.t_full = 0.35 * duration
        self.t_release = 0.75 * duration
        direction = np.array([0.35, 0.15, 1.0])
        self.breath_direction = direction / np.linalg.norm(direction)
        self.contact_breath = float(self.breath_weight(self.contact_rest[0]))
        # Cameras: a ring, each drifting slowly and independently (a few mm, a few degrees).
        n = cfg.cameras
        angles = np.linspace(0, 2 * np.pi, n, endpoint=False) + rng.uniform(-0.2, 0.2, n)
        self.cam_base = np.column_stack(
            [
                cfg.camera_ring_radius * np.cos(angles),
                cfg.camera_ring_radius * np.sin(angles),
                cfg.camera_height + rng.uniform(-0.005, 0.005, n),
            ]
        )
        self.cam_look = np.column_stack([rng.uniform(-0.012, 0.012, (n, 2)), np.zeros(n)])
        if cfg.separated and n >= 2:
            # Last camera looks at empty space far from the dome: shares no view.
            self.cam_base[-1] = [0.35, 0.35, cfg.camera_height]
            self.cam_look[-1] = [0.45, 0.45, 0.0]
        self.cam_roll = rng.uniform(-np.pi, np.pi, n)
        self.drift_amp = rng.uniform(0.001, 0.003, (n, 6))
        self.drift_freq = rng.uniform(0.1, 0.3, (n, 6))
        self.drift_phase = rng.uniform(0, 2 * np.pi, (n, 6))
        # Variants draw from their own generators, so that the default scene stays the same.
        self.stereo_offset: np.ndarray | None = None
        if cfg.stereo_baseline > 0:
            self._place_stereo_head(np.random.default_rng(cfg.seed + 505))
        # The rigid scene's rotation axis and translation direction, unit (3,); zero otherwise.
        self.rigid_axis, self.rigid_direction = np.zeros(3), np.zeros(3)
        if cfg.rigid_scene:
            r = np.random.default_rng(cfg.seed + 606)
            axis = r.normal(size=3)
            self.rigid_axis = axis / np.linalg.norm(axis)
            direction = r.normal(size=3)
            self.rigid_direction = direction / np.linalg.norm(direction)
        if cfg.rig_sweep_deg > 0:
            self._plan_rig_sweep(np.random.default_rng(cfg.seed + 808))
        self.sweep_axes: np.ndarray | None = None
        if cfg.sweep_deg > 0:
            self._plan_sweep(np.random.default_rng(cfg.seed + 707))

    def _place_stereo_head(self, rng: np.random.Generator) -> None:
        """Cameras 0 and 1 become one stereo head looking obliquely at the dome."""
        cfg = self.cfg
        look = np.array([-0.012, 0.005]) + rng.uniform(-0.003, 0.003, 2)
        nearest = np.argmin(((self.mesh.vertices[:, :2] - look) ** 2).sum(1))
        look3 = np.array([*look, self.mesh.vertices[nearest, 2]])
        azimuth = np.radians(300.0 + rng.uniform(-25.0, 25.0))  # away from the tool shaft
        elevation = np.radians(cfg.stereo_elevation_deg)
        direction = np.array(
            [
                np.cos(elevation) * np.cos(azimuth),
                np.cos(elevation) * np.sin(azimuth),
                np.sin(elevation),
            ]
        )
        self.cam_base[0] = look3 + cfg.stereo_distance * direction
        self.cam_look[0] = look3
        self.cam_base[1] = self.cam_base[0]  # unused: camera 1 follows camera 0
        self.cam_look[1] = self.cam_look[0]
        self.stereo_offset = np.eye(4)
        self.stereo_offset[0, 3] = cfg.stereo_baseline

    def _plan_sweep(self, rng: np.random.Generator) -> None:
        """Pan axes (n, 3), fixed in the world through each camera's centre, and per-camera
        amounts: every view slides towards the same horizontal world direction."""
        heading = rng.uniform(0, 2 * np.pi)
        towards = np.array([np.cos(heading), np.sin(heading), 0.0])
        self.sweep_amount = np.radians(self.cfg.sweep_deg) * rng.uniform(
            0.75, 1.0, self.cfg.cameras
        )
        axes = []
        for cam in range(self.cfg.cameras):
            z = self._drifting_pose(cam, 0.0)[:3, 2]
            axis = np.cross(z, towards)  # rotating z about z x d turns it towards d
            axes.append(axis / np.linalg.norm(axis))
        self.sweep_axes = np.array(axes)

    def _plan_rig_sweep(self, rng: np.random.Generator) -> None:
        """The untracked sweep: cameras hold still (their logged pose is the rig's), the
        tissue turns about a pivot on camera 0's axis, half-way to the tissue, about camera
        0's y axis tilted up to 30 deg towards its x axis, at a rate drawn per seed."""
        self.drift_amp = np.zeros_like(self.drift_amp)
        pose = self._drifting_pose(0, 0.0)
        self.rig_pivot = pose[:3, 3] + 0.5 * self.cfg.stereo_distance * pose[:3, 2]
        tilt = np.radians(rng.uniform(-30.0, 30.0))
        self.rig_axis = np.cos(tilt) * pose[:3, 1] + np.sin(tilt) * pose[:3, 0]
        self.rig_rate = np.radians(self.cfg.rig_sweep_deg) * rng.uniform(2 / 3, 4 / 3)

    def rigid_motion(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Rigid scene: tissue rotation (3, 3) about the dome's base centre and translation (3,)
        at time t (identity at t <= 0, full at the last frame); with an untracked rig sweep,
        the rotation about the pivot at a constant rate."""
        cfg = self.cfg
        if cfg.rig_sweep_deg > 0:
            R = _rotation(self.rig_axis * self.rig_rate * t * cfg.frame_rate)
            return R, self.rig_pivot - R @ self.rig_pivot
        s = float(smoothstep(np.asarray(t / cfg.duration)))
        R = _rotation(self.rigid_axis * np.radians(cfg.rigid_rotation_deg) * s)
        return R, s * cfg.rigid_translation * self.rigid_direction

    # ---- tissue -------------------------------------------------------------------------
    def breathing(self, t: float) -> float:
        """Breathing shift amplitude (m) at time t; 0 at t = 0 (always 0 in a rigid scene)."""
        cfg = self.cfg
        if cfg.rigid_scene:
            return 0.0
        return cfg.breath_amplitude * 0.5 * (1 - np.cos(2 * np.pi * t / cfg.breath_period))

    def breath_weight(self, x: np.ndarray) -> np.ndarray:
        """Share (same shape as x) of the breathing shift a rest position at x (m) takes."""
        return smoothstep((x - self.cfg.breath_edge) / self.cfg.breath_width + 0.5)

    def indentation(self, t: float) -> float:
        """Indentation depth (m) at time t: ramps in, holds, partly releases (0 if rigid)."""
        cfg = self.cfg
        if cfg.rigid_scene:
            return 0.0
        duration = cfg.frames / cfg.frame_rate
        if t <= self.t_contact:
            return 0.0
        if t <= self.t_full:
            return cfg.indent_depth * smoothstep(
                (t - self.t_contact) / (self.t_full - self.t_contact)
            )
        if t <= self.t_release:
            return cfg.indent_depth
        span = max(duration - self.t_release, 1e-6)
        if cfg.release >= 1:  # all released within half the time left; the tool then lifts off
            return cfg.indent_depth * (1 - smoothstep((t - self.t_release) / (0.5 * span)))
        s = smoothstep((t - self.t_release) / span)
        return cfg.indent_depth * (1 - cfg.release * s)

    def lift(self, t: float) -> float:
        """How far (m) the tool has lifted off after a full release (`release` >= 1), else 0."""
        cfg = self.cfg
        if cfg.release < 1:
            return 0.0
        span = max(cfg.frames / cfg.frame_rate - self.t_release, 1e-6)
        return 0.012 * float(smoothstep((t - self.t_release - 0.5 * span) / (0.5 * span)))

    def tissue_vertices(self, t: float) -> np.ndarray:
        """Tissue vertex positions (V, 3) m at time t."""
        cfg = self.cfg
        rest = self.mesh.vertices
        if cfg.rigid_scene:
            R, shift = self.rigid_motion(t)
            return rest @ R.T + shift
        weight = self.breath_weight(rest[:, 0])
        moved = rest + (self.breathing(t) * weight)[:, None] * self.breath_direction
        d2 = ((rest - self.contact_rest) ** 2).sum(1)
        dent = self.indentation(t) * np.exp(-d2 / (2 * cfg.indent_sigma**2))
        moved = moved - dent[:, None] * self.tool_axis
        if cfg.swell_amplitude > 0 and cfg.breath_amplitude > 0:
            s2 = ((rest[:, :2] - np.asarray(cfg.swell_xy)) ** 2).sum(1)
            phase = self.breathing(t) / cfg.breath_amplitude
            moved[:, 2] += cfg.swell_amplitude * phase * np.exp(-s2 / (2 * cfg.swell_sigma**2))
        return moved

    # ---- tool ---------------------------------------------------------------------------
    def tool_tip(self, t: float) -> np.ndarray:
        """Tool tip position (3,) m: hovers above the contact point, then follows the dent
        (`tool_clearance` above it; lifting off after a full release). In a rigid scene it
        only hovers, descending slowly to `rigid_tool_hover`."""
        if self.cfg.rigid_scene:
            s = float(smoothstep(np.asarray(t / self.cfg.duration)))
            hover = self.cfg.rigid_tool_hover + 0.010 * (1 - s)
            return self.contact_rest + hover * self.tool_axis
        hover = 0.012 * (1 - smoothstep(t / max(self.t_contact, 1e-6)))
        hover = hover + self.lift(t) + self.cfg.tool_clearance
        tip = self.contact_rest + (hover - self.indentation(t)) * self.tool_axis
        # the tissue at the contact point breathes (not in the default scene): the tip follows
        return tip + self.breathing(t) * self.contact_breath * self.breath_direction

    def tool_pose(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Tool tip pose in the world: position (3,), quaternion (4,); its +z is the shaft."""
        z = self.tool_axis
        x = np.cross([0.0, 1.0, 0.0], z)
        x /= np.linalg.norm(x)
        R = np.column_stack([x, np.cross(z, x), z])
        return self.tool_tip(t), matrix_to_quat(R)

    def joint_positions(self, t: float) -> np.ndarray:
        """Seven plausible joint values (rad, m) of a Raven-II-like arm following the tip."""
        tip = self.tool_tip(t)
        return np.array(
            [
                0.3 + 5 * tip[0],
                -0.2 + 5 * tip[1],
                0.35 - 3 * tip[2],
                0.1 * np.sin(t),
                0.05 * np.cos(t),
                0.2,
                0.2,
            ]
        )

    # ---- cameras ------------------------------------------------------------------------
    def camera_pose(self, cam: int, t: float) -> np.ndarray:
        """True camera-to-world pose (4, 4) (optical frame) of camera `cam` at time t."""
        if self.stereo_offset is not None and cam == 1:
            return self.camera_pose(0, t) @ self.stereo_offset
        T = self._drifting_pose(cam, t)
        if self.sweep_axes is not None:
            s = float(smoothstep(np.asarray(t / self.cfg.duration)))
            pan = _rotation(self.sweep_axes[cam] * self.sweep_amount[cam] * s)
            T[:3, :3] = pan @ T[:3, :3]
        return T

    def _drifting_pose(self, cam: int, t: float) -> np.ndarray:
        """Camera pose before any sweep: its base pose with a slow independent wobble."""
        a, f, p = self.drift_amp[cam], self.drift_freq[cam], self.drift_phase[cam]
        wobble = a * np.sin(2 * np.pi * f * t + p)
        position = self.cam_base[cam] + wobble[:3]
        look = self.cam_look[cam] + wobble[3:]
        z = look - position
        z /= np.linalg.norm(z)
        if self.stereo_offset is not None and cam == 0:
            x = np.cross(z, [0.0, 0.0, 1.0])  # the head's baseline (x) stays horizontal
        else:
            ref = np.array([np.cos(self.cam_roll[cam]), np.sin(self.cam_roll[cam]), 0.0])
            x = np.cross(z, ref)
        x /= np.linalg.norm(x)
        R = np.column_stack([x, np.cross(z, x), z])
        return make_pose(position, matrix_to_quat(R))


def _rotation(rotvec: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) of a rotation vector (3,) (Rodrigues' formula)."""
    angle = float(np.linalg.norm(rotvec))
    if angle < 1e-15:
        return np.eye(3)
    k = rotvec / angle
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * (K @ K)
