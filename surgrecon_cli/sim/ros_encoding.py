"""ROS 1 / ROS 2 message definitions and record -> message dicts, for the log writer.

ROS 2 messages are serialised to CDR by `mcap_ros2`; ROS 1 messages by `ros1_serialize`, a
small encoder driven by the same `.msg` text that is written into the MCAP schema, so the
bytes and the schema cannot disagree. Times in the ROS 1 dicts are (secs, nsecs) tuples.
"""

from __future__ import annotations

import struct
from typing import Any

import numpy as np

from ..io.logs.records import CameraInfoRecord, ImageRecord, JointStateRecord, PoseRecord, Record

_COMMON = {
    "sensor_msgs/CompressedImage": "std_msgs/Header header\nstring format\nuint8[] data",
    "sensor_msgs/Image": "std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\n"
    "uint8 is_bigendian\nuint32 step\nuint8[] data",
    "sensor_msgs/RegionOfInterest": "uint32 x_offset\nuint32 y_offset\nuint32 height\n"
    "uint32 width\nbool do_rectify",
    "geometry_msgs/Point": "float64 x\nfloat64 y\nfloat64 z",
    "geometry_msgs/Vector3": "float64 x\nfloat64 y\nfloat64 z",
    "geometry_msgs/Quaternion": "float64 x\nfloat64 y\nfloat64 z\nfloat64 w",
    "geometry_msgs/Pose": "geometry_msgs/Point position\ngeometry_msgs/Quaternion orientation",
    "geometry_msgs/PoseStamped": "std_msgs/Header header\ngeometry_msgs/Pose pose",
    "geometry_msgs/Transform": "geometry_msgs/Vector3 translation\n"
    "geometry_msgs/Quaternion rotation",
    "geometry_msgs/TransformStamped": "std_msgs/Header header\nstring child_frame_id\n"
    "geometry_msgs/Transform transform",
    "tf2_msgs/TFMessage": "geometry_msgs/TransformStamped[] transforms",
    "sensor_msgs/JointState": "std_msgs/Header header\nstring[] name\nfloat64[] position\n"
    "float64[] velocity\nfloat64[] effort",
}
_CAMERA_INFO = (
    "std_msgs/Header header\nuint32 height\nuint32 width\nstring distortion_model\n"
    "float64[] {d}\nfloat64[9] {k}\nfloat64[9] {r}\nfloat64[12] {p}\nuint32 binning_x\n"
    "uint32 binning_y\nsensor_msgs/RegionOfInterest roi"
)
MSGS_ROS1 = {
    **_COMMON,
    "std_msgs/Header": "uint32 seq\ntime stamp\nstring frame_id",
    "sensor_msgs/CameraInfo": _CAMERA_INFO.format(d="D", k="K", r="R", p="P"),
}
MSGS_ROS2 = {
    **_COMMON,
    "builtin_interfaces/Time": "int32 sec\nuint32 nanosec",
    "std_msgs/Header": "builtin_interfaces/Time stamp\nstring frame_id",
    "sensor_msgs/CameraInfo": _CAMERA_INFO.format(d="d", k="k", r="r", p="p"),
}
_SEPARATOR = "=" * 80
_PRIMITIVES = {
    "bool": "?", "int8": "b", "uint8": "B", "byte": "B", "char": "B", "int16": "h",
    "uint16": "H", "int32": "i", "uint32": "I", "int64": "q", "uint64": "Q", "float32": "f",
    "float64": "d",
}


def _fields(text: str) -> list[tuple[str, str]]:
    """(type, name) of each field line of a .msg text (comments and constants skipped)."""
    out = []
    for line in text.splitlines():
        line = line.split("#", 1)[0].strip()
        if line and "=" not in line:
            ftype, name = line.split()[:2]
            out.append((ftype, name))
    return out


def _base(ftype: str) -> str:
    return ftype.split("[", 1)[0]


def full_text(type_name: str, msgs: dict[str, str]) -> str:
    """Concatenated message definition (main text, then each dependency once, depth first)."""
    seen: list[str] = []

    def visit(name: str) -> None:
        for ftype, _ in _fields(msgs[name]):
            dep = _base(ftype)
            if dep in msgs and dep not in seen:
                seen.append(dep)
                visit(dep)

    visit(type_name)
    parts = [msgs[type_name]] + [f"{_SEPARATOR}\nMSG: {dep}\n{msgs[dep]}" for dep in seen]
    return "\n".join(parts) + "\n"


def ros1_serialize(type_name: str, msg: dict[str, Any], msgs: dict[str, str] = MSGS_ROS1) -> bytes:
    """Serialise a message dict to ROS 1 wire format (little-endian, no padding)."""
    out: list[bytes] = []
    _write_struct(type_name, msg, msgs, out)
    return b"".join(out)


def _write_struct(
    type_name: str, msg: dict[str, Any], msgs: dict[str, str], out: list[bytes]
) -> None:
    for ftype, name in _fields(msgs[type_name]):
        value = msg.get(name)
        base = _base(ftype)
        if "[" not in ftype:
            _write_value(base, value, msgs, out)
            continue
        size_text = ftype[ftype.index("[") + 1 : -1]
        items = [] if value is None else value
        if not size_text:
            out.append(struct.pack("<I", len(items)))
        elif len(items) != int(size_text):
            raise ValueError(f"{type_name}.{name}: expected {size_text} values, got {len(items)}")
        if base in ("uint8", "byte", "char") and isinstance(items, bytes | bytearray):
            out.append(bytes(items))
        elif base in _PRIMITIVES:
            out.append(struct.pack(f"<{len(items)}{_PRIMITIVES[base]}", *items))
        else:
            for item in items:
                _write_value(base, item, msgs, out)


def _write_value(base: str, value: Any, msgs: dict[str, str], out: list[bytes]) -> None:
    if base in _PRIMITIVES:
        out.append(struct.pack(f"<{_PRIMITIVES[base]}", value or 0))
    elif base == "string":
        data = (value or "").encode()
        out.append(struct.pack("<I", len(data)) + data)
    elif base in ("time", "duration"):
        secs, nsecs = value or (0, 0)
        out.append(struct.pack("<II" if base == "time" else "<ii", secs, nsecs))
    else:
        _write_struct(base, value or {}, msgs, out)


def ros_message(record: Record, ros1: bool, seq: int = 0) -> tuple[str, dict[str, Any]]:
    """(type name without /msg/, message dict) of a record in ROS 1 or ROS 2 field naming."""
    sec, nsec = divmod(int(record.stamp_ns), 1_000_000_000)
    stamp: Any = (sec, nsec) if ros1 else {"sec": sec, "nanosec": nsec}

    def header(frame_id: str) -> dict[str, Any]:
        h: dict[str, Any] = {"stamp": stamp, "frame_id": frame_id}
        if ros1:
            h["seq"] = seq
        return h

    if isinstance(record, ImageRecord):
        if record.format in ("jpeg", "png"):
            return "sensor_msgs/CompressedImage", {
                "header": header(record.frame_id), "format": record.format, "data": record.data,
            }
        return "sensor_msgs/Image", {
            "header": header(record.frame_id), "height": record.height, "width": record.width,
            "encoding": record.format, "is_bigendian": int(record.big_endian),
            "step": record.step,
            "data": record.data,
        }
    if isinstance(record, CameraInfoRecord):
        K = np.asarray(record.K, float).reshape(3, 3)
        R, P = record.written_rectification()
        names = ("D", "K", "R", "P") if ros1 else ("d", "k", "r", "p")
        values = (np.asarray(record.D, float).ravel(), K.ravel(), R.ravel(), P.ravel())
        return "sensor_msgs/CameraInfo", {
            "header": header(record.frame_id), "height": record.height, "width": record.width,
            "distortion_model": record.distortion_model,
            **{n: [float(x) for x in v] for n, v in zip(names, values, strict=True)},
            "binning_x": int(record.binning_x), "binning_y": int(record.binning_y),
            "roi": dict(zip(("x_offset", "y_offset", "width", "height"),
                            (int(v) for v in record.roi[:4]), strict=True),
                        do_rectify=bool(record.roi[4])),
        }
    if isinstance(record, PoseRecord):
        p = [float(x) for x in record.position]
        q = [float(x) for x in record.orientation]
        if not record.child_frame_id:
            return "geometry_msgs/PoseStamped", {
                "header": header(record.frame_id),
                "pose": {"position": dict(zip("xyz", p, strict=True)),
                         "orientation": dict(zip("xyzw", q, strict=True))},
            }
        return "tf2_msgs/TFMessage", {"transforms": [{
            "header": header(record.frame_id), "child_frame_id": record.child_frame_id,
            "transform": {"translation": dict(zip("xyz", p, strict=True)),
                          "rotation": dict(zip("xyzw", q, strict=True))},
        }]}
    if isinstance(record, JointStateRecord):
        return "sensor_msgs/JointState", {
            "header": header(""), "name": list(record.names),
            "position": [float(x) for x in record.positions], "velocity": [], "effort": [],
        }
    raise TypeError(f"cannot encode {type(record).__name__}")
