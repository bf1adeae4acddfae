"""Converters shared by ROS 1 and ROS 2 messages (same types; stamps and CameraInfo field
names differ: ROS 1 `secs/nsecs` and `D K`, ROS 2 `sec/nanosec` and `d k`)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from typing import Any

import numpy as np
from mcap.records import Schema

from ....core.geometry.distortion import distortion_model_name
from ..records import CameraInfoRecord, ImageRecord, JointStateRecord, PoseRecord, Record
from .base import rectification


class FactoryDeserializer:
    """Message bytes -> message objects through an mcap_ros* `DecoderFactory` (one generated
    decoder per schema); `schema_kind` names the schema encoding in errors."""

    def __init__(self, factory: Any, message_encoding: str, schema_kind: str) -> None:
        self._factory = factory()
        self.message_encoding = message_encoding
        self._schema_kind = schema_kind

    def for_schema(self, schema: Schema | None) -> Callable[[bytes], Any]:
        decoder = self._factory.decoder_for(self.message_encoding, schema)
        if decoder is None:
            raise ValueError(f"{self.message_encoding} messages need a {self._schema_kind} schema")
        return decoder


@dataclass(frozen=True)
class RosFlavor:
    """stamp(header) -> ns; names of the CameraInfo distortion and matrix fields."""

    stamp: Callable[[Any], int]
    d: str
    k: str
    r: str
    p: str


def compressed_image(msg: Any, ros: RosFlavor) -> list[Record]:
    return [ImageRecord(ros.stamp(msg.header), msg.header.frame_id, str(msg.format).lower(),
                        bytes(msg.data))]


def raw_image(msg: Any, ros: RosFlavor) -> list[Record]:
    return [ImageRecord(ros.stamp(msg.header), msg.header.frame_id, str(msg.encoding),
                        bytes(msg.data), int(msg.width), int(msg.height), int(msg.step),
                        bool(getattr(msg, "is_bigendian", 0)))]


def camera_info(msg: Any, ros: RosFlavor) -> list[Record]:
    """CameraInfo as recorded (full-resolution K and size, binning, ROI); the distortion
    model name is checked and canonical (`core.geometry.distortion.distortion_model_name`: an
    unknown model with non-zero coefficients raises, naming it)."""
    K = np.asarray(getattr(msg, ros.k), dtype=float)
    D = np.asarray(getattr(msg, ros.d), dtype=float)
    roi = getattr(msg, "roi", None)
    roi_values = (0, 0, 0, 0, False) if roi is None else (
        int(roi.x_offset), int(roi.y_offset), int(roi.width), int(roi.height),
        bool(roi.do_rectify))
    return [CameraInfoRecord(
        ros.stamp(msg.header), msg.header.frame_id, int(msg.width), int(msg.height),
        K.reshape(3, 3) if K.size == 9 else K, D,
        distortion_model_name(str(msg.distortion_model), D),
        int(getattr(msg, "binning_x", 0) or 0), int(getattr(msg, "binning_y", 0) or 0),
        roi_values, *rectification(getattr(msg, ros.r, None), getattr(msg, ros.p, None)),
    )]


def _xyz(v: Any) -> np.ndarray:
    return np.array([v.x, v.y, v.z], dtype=float)


def _xyzw(q: Any) -> np.ndarray:
    return np.array([q.x, q.y, q.z, q.w], dtype=float)


def pose_stamped(msg: Any, ros: RosFlavor) -> list[Record]:
    return [PoseRecord(ros.stamp(msg.header), msg.header.frame_id, "",
                       _xyz(msg.pose.position), _xyzw(msg.pose.orientation))]


def transform_stamped(msg: Any, ros: RosFlavor) -> list[Record]:
    """geometry_msgs/TransformStamped read where a PoseStamped is: the pose of
    `child_frame_id` in `header.frame_id`, both kept in the record."""
    return [PoseRecord(ros.stamp(msg.header), msg.header.frame_id, msg.child_frame_id,
                       _xyz(msg.transform.translation), _xyzw(msg.transform.rotation))]


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


@dataclass(frozen=True)
class RosDecoders:
    """The decoders of one ROS flavour (message -> records)."""

    compressed_image: Callable[[Any], list[Record]]
    raw_image: Callable[[Any], list[Record]]
    camera_info: Callable[[Any], list[Record]]
    pose_stamped: Callable[[Any], list[Record]]
    tf_message: Callable[[Any], list[Record]]
    joint_state: Callable[[Any], list[Record]]


def bind(ros: RosFlavor) -> RosDecoders:
    """All decoders with the flavour's field names and stamp convention bound."""
    return RosDecoders(*(partial(f, ros=ros) for f in (
        compressed_image, raw_image, camera_info, pose_stamped, tf_message, joint_state)))
