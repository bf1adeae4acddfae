"""What the frame step works on, grouped: the run's template and rig (fixed for a run), one
frame's images and poses, and a set of images with where the template points were seen in
them (the base frame, the template's frame 0). Plain frozen dataclasses on numpy arrays."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...config import TargetConfig
from ..geometry.cameras import CameraModel
from ..geometry.tool import ToolConfigs
from ..noise.model import NoiseModel
from .tracking import TrackingView


@dataclass(frozen=True)
class TemplateData:
    """The frame-0 template: points (N, 3) m, rgb (N, 3) uint8, covariance (N, 3, 3) m² of
    which pose_covariance (N, 3, 3) m² comes from the cameras' pose errors, and pixels
    (N, C, 2) where each point was seen at frame 0 (NaN = not seen)."""

    points: np.ndarray
    rgb: np.ndarray
    covariance: np.ndarray
    pose_covariance: np.ndarray
    pixels: np.ndarray


@dataclass(frozen=True)
class Rig:
    """The run's cameras (C models), its measured noise model, the target cloud's config and
    every tool's geometry (`Config.tool_configs()`)."""

    models: list[CameraModel]
    noise: NoiseModel
    cfg: TargetConfig
    tools: ToolConfigs


@dataclass(frozen=True)
class FrameInput:
    """One frame: its index, per camera its image prepared for tracking (core/tracking.
    tracking_view; None where unusable), camera-to-world poses (C, 4, 4) (NaN where
    unusable), every tool's pose (K, 4, 4) (NaN = unknown) and, when new features are to be
    triangulated into its target, its RGB images (H, W, 3) uint8 (else None);
    `camera_tool_pose` (C, K, 4, 4): each camera's view of the tools (`tool.camera_offsets`),
    None = every camera sees them at `tool_pose`; `previous`: the frame before it when that
    is not the base (None: none or not given), tracked through (core/target/track_points)."""

    index: int
    views: list[TrackingView | None]
    poses: np.ndarray
    tool_pose: np.ndarray
    images: list[np.ndarray | None] | None = None
    camera_tool_pose: np.ndarray | None = None
    previous: FrameInput | None = None

    @property
    def seen_tools(self) -> np.ndarray:
        """The tools as the cameras see them, for masks and tool-point removal: (C, K, 4, 4)
        per camera, or the shared (K, 4, 4)."""
        return self.tool_pose if self.camera_tool_pose is None else self.camera_tool_pose


@dataclass(frozen=True)
class Sighting:
    """Images the points are tracked from: per camera a tracking view (None = unusable),
    the poses (C, 4, 4) they were taken from and where each point was seen (N, C, 2) px
    (NaN = not seen)."""

    views: list[TrackingView | None]
    poses: np.ndarray
    pixels: np.ndarray
