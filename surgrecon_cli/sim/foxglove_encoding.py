"""Records -> Foxglove messages (protobuf objects or JSON bytes) and their schemas.

One dict layout per record in Foxglove field naming (timestamp as (sec, nsec), bytes as bytes)
feeds both encodings. JSON follows Foxglove's conventions: timestamp {"sec", "nsec"}, bytes as
base64 strings, `jsonschema` schemas with the same names as the protobuf ones. Joint states
are `foxglove.JointStates` in protobuf; in JSON they are the generic `surgrecon.JointStates`
({"timestamp", "name": [...], "position": [...]}), the shape many non-Foxglove tools write.
"""

from __future__ import annotations

import base64
import json
from typing import Any

import numpy as np
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.CompressedVideo_pb2 import CompressedVideo
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.JointStates_pb2 import JointStates
from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from google.protobuf.descriptor import Descriptor, FieldDescriptor

from ..io.logs.records import CameraInfoRecord, ImageRecord, JointStateRecord, PoseRecord, Record

PROTO_CLASSES: dict[str, Any] = {
    cls.DESCRIPTOR.full_name: cls
    for cls in (CompressedImage, RawImage, CameraCalibration, PoseInFrame, FrameTransforms,
                JointStates, CompressedVideo)
}
JSON_JOINT_STATES = "surgrecon.JointStates"


def foxglove_message(record: Record, json_mode: bool) -> tuple[str, dict[str, Any]]:
    """(schema name, message dict) of a record; the timestamp is a (sec, nsec) tuple."""
    ts = divmod(int(record.stamp_ns), 1_000_000_000)
    if isinstance(record, ImageRecord):
        if record.format in ("h264", "h265"):
            return "foxglove.CompressedVideo", {
                "timestamp": ts, "frame_id": record.frame_id, "data": record.data,
                "format": record.format,
            }
        if record.format in ("jpeg", "png"):
            return "foxglove.CompressedImage", {
                "timestamp": ts, "frame_id": record.frame_id, "data": record.data,
                "format": record.format,
            }
        return "foxglove.RawImage", {
            "timestamp": ts, "frame_id": record.frame_id, "width": record.width,
            "height": record.height, "encoding": record.format, "step": record.step,
            "data": record.data,
        }
    if isinstance(record, CameraInfoRecord):
        K = np.asarray(record.K, float).reshape(3, 3)
        R, P = record.written_rectification()
        return "foxglove.CameraCalibration", {
            "timestamp": ts, "frame_id": record.frame_id, "width": record.width,
            "height": record.height, "distortion_model": record.distortion_model,
            "D": [float(x) for x in np.asarray(record.D, float).ravel()],
            "K": [float(x) for x in K.ravel()],
            "R": [float(x) for x in R.ravel()],
            "P": [float(x) for x in P.ravel()],
        }
    if isinstance(record, PoseRecord):
        p = dict(zip("xyz", (float(x) for x in record.position), strict=True))
        q = dict(zip("xyzw", (float(x) for x in record.orientation), strict=True))
        if not record.child_frame_id:
            return "foxglove.PoseInFrame", {
                "timestamp": ts, "frame_id": record.frame_id,
                "pose": {"position": p, "orientation": q},
            }
        return "foxglove.FrameTransforms", {"transforms": [{
            "timestamp": ts, "parent_frame_id": record.frame_id,
            "child_frame_id": record.child_frame_id, "translation": p, "rotation": q,
        }]}
    if isinstance(record, JointStateRecord):
        names = list(record.names)
        positions = [float(x) for x in record.positions]
        if json_mode:
            return JSON_JOINT_STATES, {"timestamp": ts, "name": names, "position": positions}
        return "foxglove.JointStates", {"timestamp": ts, "joints": [
            {"name": n, "position": v} for n, v in zip(names, positions, strict=True)
        ]}
    raise TypeError(f"cannot encode {type(record).__name__}")


def _convert_times(obj: Any, json_mode: bool) -> Any:
    if isinstance(obj, dict):
        out = {}
        for key, value in obj.items():
            if key == "timestamp":
                sec, nsec = value
                out[key] = ({"sec": sec, "nsec": nsec} if json_mode
                            else {"seconds": sec, "nanos": nsec})
            else:
                out[key] = _convert_times(value, json_mode)
        return out
    if isinstance(obj, list):
        return [_convert_times(v, json_mode) for v in obj]
    if json_mode and isinstance(obj, bytes):
        return base64.b64encode(obj).decode("ascii")
    return obj


def to_protobuf(schema_name: str, message: dict[str, Any]) -> bytes:
    """Serialise a message dict with the `foxglove_schemas_protobuf` class of that name."""
    return PROTO_CLASSES[schema_name](**_convert_times(message, False)).SerializeToString()


def to_json(message: dict[str, Any]) -> bytes:
    """Foxglove JSON encoding of a message dict (compact, key order kept: deterministic)."""
    return json.dumps(_convert_times(message, True), separators=(",", ":")).encode()


def json_schema(schema_name: str) -> bytes:
    """A JSON Schema for a JSON channel: derived from the protobuf descriptor of that name."""
    if schema_name == JSON_JOINT_STATES:
        schema: dict[str, Any] = {
            "title": schema_name, "type": "object",
            "properties": {
                "timestamp": _TIME_SCHEMA,
                "name": {"type": "array", "items": {"type": "string"}},
                "position": {"type": "array", "items": {"type": "number"}},
            },
        }
    else:
        schema = {"title": schema_name, **_descriptor_schema(PROTO_CLASSES[schema_name].DESCRIPTOR)}
    return json.dumps(schema, separators=(",", ":")).encode()


_TIME_SCHEMA = {"type": "object", "properties": {"sec": {"type": "integer", "minimum": 0},
                                                 "nsec": {"type": "integer", "minimum": 0}}}


def _descriptor_schema(desc: Descriptor) -> dict[str, Any]:
    if desc.full_name == "google.protobuf.Timestamp":
        return dict(_TIME_SCHEMA)
    props = {}
    for f in desc.fields:
        if f.type == FieldDescriptor.TYPE_MESSAGE:
            item: dict[str, Any] = _descriptor_schema(f.message_type)
        elif f.type == FieldDescriptor.TYPE_BYTES:
            item = {"type": "string", "contentEncoding": "base64"}
        elif f.type == FieldDescriptor.TYPE_STRING:
            item = {"type": "string"}
        elif f.type in (FieldDescriptor.TYPE_DOUBLE, FieldDescriptor.TYPE_FLOAT):
            item = {"type": "number"}
        elif f.type == FieldDescriptor.TYPE_BOOL:
            item = {"type": "boolean"}
        else:
            item = {"type": "integer"}
        is_repeated = getattr(f, "is_repeated", None)
        repeated = is_repeated if isinstance(is_repeated, bool) else (
            f.label == FieldDescriptor.LABEL_REPEATED)
        props[f.name] = {"type": "array", "items": item} if repeated else item
    return {"type": "object", "properties": props}
