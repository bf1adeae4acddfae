"""What the frame step works on, grouped: the run's template and rig (fixed for a run), one
frame's images and poses, and a set of images with where the template points were seen in
them (the base frame, the template's frame 0). Plain frozen dataclasses on numpy arrays."""

from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from ...config import TargetConfig
from ..geometry.cameras import CameraModel
from ..geometry.tool import ToolConfigs
from ..noise.frame_noise import PixelNeighbours
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

    @cached_property
    def neighbours(self) -> list[PixelNeighbours]:
        """Per camera, each point's nearest others by frame-0 pixel (core/noise/frame_noise.
        PixelNeighbours), built when first asked for: the tracking noise's fits take their
        neighbours among the points found in a frame from these."""
        return [PixelNeighbours.of(self.pixels[:, c]) for c in range(self.pixels.shape[1])]


class ChainMemo:
    """Where the last `size` frames tracked straight from their base found the points by
    the chain alone (pixels (N, C, 2), NaN = not found; core/target/track_points, before
    re-acquisition from the template), in this process: a frame tracked through its
    previous frame starts from the previous frame's pixels instead of tracking them again
    (the same computation, so the same pixels; a frame not held is tracked). Keyed by the
    frame's index and a digest of the base it was tracked from (`key`); thread-safe."""

    def __init__(self, size: int = 4) -> None:
        self.size = size
        self._items: OrderedDict[tuple[int, str], np.ndarray] = OrderedDict()
        self._lock = threading.Lock()

    @staticmethod
    def key(latest: np.ndarray, base: Sighting, frame: int) -> tuple[int, str]:
        """The key of `frame` tracked from `base` with the points at `latest` (N, 3) m."""
        digest = hashlib.blake2b(digest_size=16)
        for array in (latest, base.pixels, base.poses):
            digest.update(np.ascontiguousarray(array).tobytes())
        return frame, digest.hexdigest()

    def get(self, key: tuple[int, str]) -> np.ndarray | None:
        """The pixels (N, C, 2) held under `key`, or None."""
        with self._lock:
            return self._items.get(key)

    def put(self, key: tuple[int, str], pixels: np.ndarray) -> None:
        """Holds pixels (N, C, 2) under `key` (read-only), dropping the oldest beyond size."""
        pixels.flags.writeable = False
        with self._lock:
            self._items[key] = pixels
            self._items.move_to_end(key)
            while len(self._items) > self.size:
                self._items.popitem(last=False)


class PairMemo:
    """Per pair of cameras (a, b), an array computed once for the run (the template's
    stereo matches, core/target/track_points._stereo_disparity), in this process;
    thread-safe."""

    def __init__(self) -> None:
        self._items: dict[tuple[int, int], np.ndarray] = {}
        self._lock = threading.Lock()

    def get(self, pair: tuple[int, int], compute: Callable[[], np.ndarray]) -> np.ndarray:
        """The array held for `pair`, computed by `compute` (and held, read-only) the first
        time."""
        with self._lock:
            held = self._items.get(pair)
        if held is None:
            held = compute()
            held.flags.writeable = False
            with self._lock:
                held = self._items.setdefault(pair, held)
        return held


@dataclass(frozen=True)
class Rig:
    """The run's cameras (C models), its measured noise model, the target cloud's config,
    every tool's geometry (`Config.tool_configs()`) and, for a run's frame step, the memo
    of its frames' chained tracks (`ChainMemo`; None: nothing held) and of the template's
    stereo matches (`PairMemo`; None: matched again every frame)."""

    models: list[CameraModel]
    noise: NoiseModel
    cfg: TargetConfig
    tools: ToolConfigs
    chains: ChainMemo | None = None
    pair_matches: PairMemo | None = None


@dataclass(frozen=True)
class FrameInput:
    """One frame: its index, per camera its image prepared for tracking (core/tracking.
    tracking_view; None where unusable), camera-to-world poses (C, 4, 4) (NaN where
    unusable), every tool's pose (K, 4, 4) (NaN = unknown) and, when new features are to be
    triangulated into its target, its RGB images (H, W, 3) uint8 (else None);
    `camera_tool_pose` (C, K, 4, 4): each camera's view of the tools (`tool.camera_offsets`),
    None = every camera sees them at `tool_pose`; `previous`: the frame before it when that
    is not the base (None: none or not given), tracked through (core/target/track_points);
    `lock`: whether its tracks are locked to the template's images (track_points' step 3;
    False for a frame one step from its base that is no later frame's base: its tracks
    carry one KLT step's drift, and nothing starts from them)."""

    index: int
    views: list[TrackingView | None]
    poses: np.ndarray
    tool_pose: np.ndarray
    images: list[np.ndarray | None] | None = None
    camera_tool_pose: np.ndarray | None = None
    previous: FrameInput | None = None
    lock: bool = True

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
