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
    e.g. 'rgb8', 'bgr8', 'mono8', 'bayer_rggb8', 'yuv422', with width/height/step in px/bytes;
    big_endian: 16-bit samples are big-endian, ROS `is_bigendian`)."""

    stamp_ns: int
    frame_id: str
    format: str
    data: bytes
    width: int = 0
    height: int = 0
    step: int = 0
    big_endian: bool = False


@dataclass(frozen=True)
class CameraInfoRecord:
    """Intrinsics as recorded: K (3, 3) px and width/height px of the full-resolution sensor,
    D distortion coefficients of `distortion_model` (plumb_bob: k1 k2 p1 p2 k3;
    rational_polynomial: k1 k2 p1 p2 k3 k4 k5 k6; equidistant: k1 k2 k3 k4), ROS binning
    (0 = 1) and roi = (x_offset, y_offset, width, height, do_rectify) in full-resolution px
    (all zero = full image). `core.geometry.cameras.CameraModel.from_camera_info` turns these into
    the model of the published images. R (3, 3) and P (3, 4): the stereo rectification and
    projection (P[0, 3] = Tx = −fx′·B, metres), None where the message has none."""

    stamp_ns: int
    frame_id: str
    width: int
    height: int
    K: np.ndarray
    D: np.ndarray
    distortion_model: str = "plumb_bob"
    binning_x: int = 0
    binning_y: int = 0
    roi: tuple[int, int, int, int, bool] = (0, 0, 0, 0, False)
    R: np.ndarray | None = None
    P: np.ndarray | None = None

    def written_rectification(self) -> tuple[np.ndarray, np.ndarray]:
        """R (3, 3) and P (3, 4) as a CameraInfo message carries them: the recorded ones,
        else those of an unrectified monocular camera (identity, [K | 0])."""
        if self.R is not None and self.P is not None:
            return np.asarray(self.R, float), np.asarray(self.P, float)
        K = np.asarray(self.K, float).reshape(3, 3)
        return np.eye(3), np.hstack([K, np.zeros((3, 1))])


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
