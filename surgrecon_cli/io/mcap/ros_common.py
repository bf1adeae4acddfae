"""Converters shared by ROS 1 and ROS 2 messages (same types; stamps and CameraInfo field
names differ: ROS 1 `secs/nsecs` and `D K`, ROS 2 `sec/nanosec` and `d k`)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..records import CameraInfoRecord, ImageRecord, JointStateRecord, PoseRecord, Record


@dataclass(frozen=True)
class RosFlavor:
    """stamp(header) -> ns; names of the CameraInfo distortion and matrix fields."""

    stamp: Callable[[Any], int]
    d: str
    k: str


def compressed_image(msg: Any, ros: RosFlavor) -> list[Record]:
    return [ImageRecord(ros.stamp(msg.header), msg.header.frame_id, str(msg.format).lower(),
                        bytes(msg.data))]


def raw_image(msg: Any, ros: RosFlavor) -> list[Record]:
    return [ImageRecord(ros.stamp(msg.header), msg.header.frame_id, str(msg.encoding),
                        bytes(msg.data), int(msg.width), int(msg.height), int(msg.step))]


def camera_info(msg: Any, ros: RosFlavor) -> list[Record]:
    K = np.asarray(getattr(msg, ros.k), dtype=float)
    return [CameraInfoRecord(
        ros.stamp(msg.header), msg.header.frame_id, int(msg.width), int(msg.height),
        K.reshape(3, 3) if K.size == 9 else K, np.asarray(getattr(msg, ros.d), dtype=float),
        str(msg.distortion_model),
    )]


def _xyz(v: Any) -> np.ndarray:
    return np.array([v.x, v.y, v.z], dtype=float)


def _xyzw(q: Any) -> np.ndarray:
    return np.array([q.x, q.y, q.z, q.w], dtype=float)


def pose_stamped(msg: Any, ros: RosFlavor) -> list[Record]:
    return [PoseRecord(ros.stamp(msg.header), msg.header.frame_id, "",
                       _xyz(msg.pose.position), _xyzw(msg.pose.orientation))]


def tf_message(msg: Any, ros: RosFlavor) -> list[Record]:
    return [
        PoseRecord(ros.stamp(t.header), t.header.frame_id, t.child_frame_id,
                   _xyz(t.transform.translation), _xyzw(t.transform.rotation))
        for t in msg.transforms
    ]


def joint_state(msg: Any, ros: RosFlavor) -> list[Record]:
    positions = np.asarray(msg.position, dtype=float)
    names = tuple(str(n) for n in msg.name) or tuple(f"joint_{i}" for i in range(len(positions)))
    return [JointStateRecord(ros.stamp(msg.header), names, positions)]
