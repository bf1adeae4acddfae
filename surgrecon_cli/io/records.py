"""Encoding-neutral message records.

Readers decode every supported schema (ROS 1, ROS 2, Foxglove protobuf/json) into these;
the simulator's log writer encodes these into any of them. Stamps are int nanoseconds.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ImageRecord:
    """One camera image: compressed (`format` 'jpeg'/'png') or raw (`format` = ROS encoding,
    e.g. 'rgb8', 'bgr8', 'mono8', with width/height/step)."""

    stamp_ns: int
    frame_id: str
    format: str
    data: bytes
    width: int = 0
    height: int = 0
    step: int = 0


@dataclass(frozen=True)
class CameraInfoRecord:
    """Intrinsics: K (3, 3) px, D distortion coefficients (plumb_bob: k1 k2 p1 p2 k3)."""

    stamp_ns: int
    frame_id: str
    width: int
    height: int
    K: np.ndarray
    D: np.ndarray
    distortion_model: str = "plumb_bob"


@dataclass(frozen=True)
class PoseRecord:
    """A pose of `child_frame_id` in `frame_id`: position (3,) m, orientation (4,) x y z w.

    For a PoseStamped/PoseInFrame the child frame is empty (the topic says whose pose it is).
    """

    stamp_ns: int
    frame_id: str
    child_frame_id: str
    position: np.ndarray
    orientation: np.ndarray


@dataclass(frozen=True)
class JointStateRecord:
    """Robot joint states: names and positions (rad or m)."""

    stamp_ns: int
    names: tuple[str, ...]
    positions: np.ndarray


Record = ImageRecord | CameraInfoRecord | PoseRecord | JointStateRecord
