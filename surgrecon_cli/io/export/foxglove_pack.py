"""Foxglove protobuf messages (package `foxglove-schemas-protobuf`) built from numpy arrays.

Per-point data never goes through a Python loop: a point cloud's `data` is one numpy
structured array's bytes (`packed_points`), and the points of an image annotation are
encoded to protobuf wire format with numpy and parsed once (`points_annotation`).
Stamps are int nanoseconds since the epoch; poses (4, 4) child-to-parent (camera-to-world).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from foxglove_schemas_protobuf.Color_pb2 import Color
from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from foxglove_schemas_protobuf.PointsAnnotation_pb2 import PointsAnnotation
from foxglove_schemas_protobuf.Pose_pb2 import Pose
from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
from foxglove_schemas_protobuf.Vector3_pb2 import Vector3
from google.protobuf.timestamp_pb2 import Timestamp

from ...core.geometry.poses import matrix_to_quat

# numpy little-endian type -> Foxglove numeric type
_NUMERIC = {
    "u1": PackedElementField.UINT8, "i1": PackedElementField.INT8,
    "<u2": PackedElementField.UINT16, "<i2": PackedElementField.INT16,
    "<u4": PackedElementField.UINT32, "<i4": PackedElementField.INT32,
    "<f4": PackedElementField.FLOAT32, "<f8": PackedElementField.FLOAT64,
}
NUMPY_TYPES = {code: np.dtype(name) for name, code in _NUMERIC.items()}
"""Foxglove numeric type -> numpy dtype (little-endian), for readers of the data."""

# A Point2 as the element of PointsAnnotation.points (field 3): tag, length, then
# x (field 1, double) and y (field 2, double), 20 bytes.
_POINT2 = np.dtype([("tag", "u1"), ("size", "u1"), ("x_tag", "u1"), ("x", "<f8"),
                    ("y_tag", "u1"), ("y", "<f8")])
_POINTS_FIELD_TAG = (3 << 3) | 2
_X_TAG, _Y_TAG = (1 << 3) | 1, (2 << 3) | 1


def timestamp(stamp_ns: int) -> Timestamp:
    stamp_ns = int(stamp_ns)
    return Timestamp(seconds=stamp_ns // 1_000_000_000, nanos=stamp_ns % 1_000_000_000)


def stamp_ns(ts: Timestamp) -> int:
    """Inverse of `timestamp`."""
    return int(ts.seconds) * 1_000_000_000 + int(ts.nanos)


def color(rgba: Sequence[float]) -> Color:
    """A colour from (r, g, b, a), each 0..1."""
    r, g, b, a = (float(v) for v in rgba)
    return Color(r=r, g=g, b=b, a=a)


def pose(matrix: np.ndarray | None = None) -> Pose:
    """A Pose from a rigid transform (4, 4) (identity if None)."""
    if matrix is None:
        return Pose(position=Vector3(), orientation=Quaternion(w=1.0))
    return Pose(position=vector3(np.asarray(matrix, float)[:3, 3]), orientation=quaternion(matrix))


def vector3(v: Sequence[float] | np.ndarray) -> Vector3:
    x, y, z = (float(c) for c in v)
    return Vector3(x=x, y=y, z=z)


def quaternion(matrix: np.ndarray) -> Quaternion:
    q = matrix_to_quat(np.asarray(matrix, float)[:3, :3])
    return Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3]))


def packed_points(columns: Sequence[tuple[str, str, np.ndarray]]
                  ) -> tuple[list[PackedElementField], int, bytes]:
    """Fields, stride (bytes) and data of points packed one after another.

    columns: (name, numpy type code as in `_NUMERIC`, values (N,)) in field order; the values
    are cast to the type (a float32 column given float32 values keeps their bits)."""
    dtype = np.dtype([(name, code) for name, code, _ in columns])
    n = len(columns[0][2]) if columns else 0
    table = np.empty(n, dtype=dtype)
    fields = []
    for name, code, values in columns:
        table[name] = values
        offset = dtype.fields[name][1] if dtype.fields else 0
        fields.append(PackedElementField(name=name, offset=int(offset), type=_NUMERIC[code]))
    return fields, dtype.itemsize, table.tobytes()


def point_cloud(stamp: int, frame_id: str,
                columns: Sequence[tuple[str, str, np.ndarray]]) -> PointCloud:
    """A foxglove.PointCloud of the `columns` (see `packed_points`) in `frame_id`."""
    fields, stride, data = packed_points(columns)
    return PointCloud(timestamp=timestamp(stamp), frame_id=frame_id, pose=pose(),
                      point_stride=stride, fields=fields, data=data)


def unpack_points(cloud: PointCloud) -> dict[str, np.ndarray]:
    """The fields of a decoded foxglove.PointCloud as {name: (N,) array}."""
    dtype = np.dtype({"names": [f.name for f in cloud.fields],
                      "formats": [NUMPY_TYPES[f.type] for f in cloud.fields],
                      "offsets": [f.offset for f in cloud.fields],
                      "itemsize": cloud.point_stride})
    table = np.frombuffer(cloud.data, dtype=dtype)
    return {name: table[name].copy() for name in dtype.names or ()}


def points_annotation(stamp: int, uv: np.ndarray, fill: Sequence[float],
                      outline: Sequence[float], size: float) -> PointsAnnotation:
    """A POINTS annotation of pixels uv (M, 2), one colour for all, `size` px across."""
    uv = np.asarray(uv, float).reshape(-1, 2)
    wire = np.empty(len(uv), dtype=_POINT2)
    wire["tag"], wire["size"] = _POINTS_FIELD_TAG, _POINT2.itemsize - 2
    wire["x_tag"], wire["y_tag"] = _X_TAG, _Y_TAG
    wire["x"], wire["y"] = uv[:, 0], uv[:, 1]
    message = PointsAnnotation.FromString(wire.tobytes())
    message.timestamp.CopyFrom(timestamp(stamp))
    message.type = PointsAnnotation.POINTS
    message.fill_color.CopyFrom(color(fill))
    message.outline_color.CopyFrom(color(outline))
    message.thickness = float(size)
    return message
