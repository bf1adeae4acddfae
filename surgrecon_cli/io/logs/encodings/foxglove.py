"""Foxglove schemas, `protobuf` (decoded by `mcap_protobuf`) or `json` messages.

The same converters read both: JSON objects are wrapped so that fields read like protobuf
attributes; the differences (timestamp `sec/nsec` vs `seconds/nanos`, bytes as base64
strings, missing fields) are absorbed by `_time`, `_bytes` and defaults.
"""

from __future__ import annotations

import base64
import json
from collections.abc import Callable
from typing import Any

import numpy as np
from mcap.records import Schema
from mcap_protobuf.decoder import DecoderFactory

from ....core.geometry.distortion import distortion_model_name
from ..records import CameraInfoRecord, ImageRecord, JointStateRecord, PoseRecord, Record
from ..video import CODECS as VIDEO_FORMATS
from .base import rectification, stamp_ns


class ProtobufDeserializer:
    """Protobuf bytes -> message objects (classes built from the schema's descriptor set)."""

    message_encoding = "protobuf"

    def __init__(self) -> None:
        self._factory = DecoderFactory()

    def for_schema(self, schema: Schema | None) -> Callable[[bytes], Any]:
        decoder = self._factory.decoder_for(self.message_encoding, schema)
        if decoder is None:
            raise ValueError("protobuf messages need a protobuf schema")
        return decoder


class _Obj:
    """Attribute view of a JSON object; a missing field reads as None."""

    __slots__ = ("_d",)

    def __init__(self, d: dict[str, Any]) -> None:
        self._d = d

    def __getattr__(self, name: str) -> Any:
        value = self._d.get(name)
        if isinstance(value, dict):
            return _Obj(value)
        if isinstance(value, list):
            return [_Obj(v) if isinstance(v, dict) else v for v in value]
        return value


class JsonDeserializer:
    """JSON bytes -> attribute views; the schema is not needed to decode."""

    message_encoding = "json"

    def for_schema(self, schema: Schema | None) -> Callable[[bytes], Any]:
        def decode(data: bytes) -> Any:
            obj = json.loads(data)
            if not isinstance(obj, dict):
                raise ValueError("JSON message is not an object")
            return _Obj(obj)

        return decode


def _time(ts: Any) -> int:
    if ts is None:
        return 0
    if isinstance(ts, _Obj):
        return stamp_ns(ts.sec, ts.nsec)
    return stamp_ns(ts.seconds, ts.nanos)


def _bytes(data: Any) -> bytes:
    if data is None:
        return b""
    if isinstance(data, str):
        return base64.b64decode(data, validate=True)
    return bytes(data)


def _floats(values: Any) -> np.ndarray:
    return np.asarray([] if values is None else list(values), dtype=float)


def _vec(v: Any, names: str, default: tuple[float, ...]) -> np.ndarray:
    if v is None:
        return np.array(default, dtype=float)
    return np.array([getattr(v, n) or 0.0 for n in names], dtype=float)


def compressed_image(msg: Any) -> list[Record]:
    return [ImageRecord(_time(msg.timestamp), msg.frame_id or "", str(msg.format or "").lower(),
                        _bytes(msg.data))]


def compressed_video(msg: Any) -> list[Record]:
    """One frame of a video stream, still encoded: `io/logs/video.py` decodes it, per topic."""
    fmt = str(msg.format or "").lower()
    if fmt not in VIDEO_FORMATS:
        raise ValueError(f"CompressedVideo format {fmt!r} is not supported "
                         f"(supported: {', '.join(VIDEO_FORMATS)})")
    return [ImageRecord(_time(msg.timestamp), msg.frame_id or "", fmt, _bytes(msg.data))]


def raw_image(msg: Any) -> list[Record]:
    return [ImageRecord(_time(msg.timestamp), msg.frame_id or "", str(msg.encoding or ""),
                        _bytes(msg.data), int(msg.width or 0), int(msg.height or 0),
                        int(msg.step or 0))]


def camera_calibration(msg: Any) -> list[Record]:
    """CameraCalibration (no binning or ROI fields); the distortion model name is checked and
    canonical as for ROS CameraInfo."""
    K = _floats(msg.K)
    D = _floats(msg.D)
    R, P = rectification(msg.R, msg.P)
    return [CameraInfoRecord(
        _time(msg.timestamp), msg.frame_id or "", int(msg.width or 0), int(msg.height or 0),
        K.reshape(3, 3) if K.size == 9 else K, D,
        distortion_model_name(str(msg.distortion_model or ""), D),
        R=R, P=P,
    )]


def pose_in_frame(msg: Any) -> list[Record]:
    pose = msg.pose
    position = pose.position if pose is not None else None
    orientation = pose.orientation if pose is not None else None
    return [PoseRecord(_time(msg.timestamp), msg.frame_id or "", "",
                       _vec(position, "xyz", (0, 0, 0)),
                       _vec(orientation, "xyzw", (0, 0, 0, 1)))]


def _transform(t: Any) -> PoseRecord:
    return PoseRecord(_time(t.timestamp), t.parent_frame_id or "", t.child_frame_id or "",
                      _vec(t.translation, "xyz", (0, 0, 0)),
                      _vec(t.rotation, "xyzw", (0, 0, 0, 1)))


def frame_transform(msg: Any) -> list[Record]:
    return [_transform(msg)]


def frame_transforms(msg: Any) -> list[Record]:
    return [_transform(t) for t in (msg.transforms or [])]


def joint_states(msg: Any) -> list[Record]:
    joints = list(msg.joints or [])
    names = tuple(str(j.name or f"joint_{i}") for i, j in enumerate(joints))
    positions = np.array([np.nan if j.position is None else j.position for j in joints], float)
    return [JointStateRecord(_time(msg.timestamp), names, positions)]


def json_joint_states(msg: Any) -> list[Record]:
    """Any JSON object with `name` and `position` arrays (and optionally a `timestamp`)."""
    positions = _floats(msg.position)
    names = tuple(str(n) for n in (msg.name or [])) or tuple(
        f"joint_{i}" for i in range(len(positions)))
    if len(names) != len(positions):
        raise ValueError(f"{len(names)} joint names but {len(positions)} positions")
    return [JointStateRecord(_time(msg.timestamp), names, positions)]
