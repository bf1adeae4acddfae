"""Write records into an MCAP log, in any encoding surgrecon reads.

record          ROS (ros2: pkg/msg/Type; ros1: pkg/Type)      Foxglove (protobuf or json)
image jpeg/png  sensor_msgs/CompressedImage                   foxglove.CompressedImage
image raw       sensor_msgs/Image                             foxglove.RawImage
image h264/h265 (not in ROS encodings)                        foxglove.CompressedVideo
camera info     sensor_msgs/CameraInfo (ROS 1: D K R P)       foxglove.CameraCalibration
pose            geometry_msgs/PoseStamped                     foxglove.PoseInFrame
pose + child    tf2_msgs/TFMessage                            foxglove.FrameTransforms
joint states    sensor_msgs/JointState                        foxglove.JointStates (protobuf),
                                                              surgrecon.JointStates (json)

Deterministic: no wall clock anywhere (log and publish time = the given log time, per-topic
sequence numbers), fixed chunk size and zstd compression, so the same records give the same
bytes. The file is written atomically (temporary name, then rename), leaving the page cache
as it goes (`io.run.atomic.CacheDropping`).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from pathlib import Path
from typing import IO, Any, cast

from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from mcap_protobuf.schema import register_schema
from mcap_ros2.writer import Writer as Ros2Writer

from .. import __version__
from ..io.logs.records import Record
from ..io.run.atomic import CacheDropping, atomic_open
from .foxglove_encoding import PROTO_CLASSES, foxglove_message, json_schema, to_json, to_protobuf
from .ros_encoding import MSGS_ROS1, MSGS_ROS2, full_text, ros1_serialize, ros_message

ENCODINGS = ("ros2", "ros1", "foxglove-protobuf", "foxglove-json")
DEFAULT_CHUNK_SIZE = 1 << 20
_LIBRARY = f"surgrecon/{__version__}"


class _Sink:
    """One MCAP writer; subclasses turn a record into (schema, encoding, bytes)."""

    profile = ""
    message_encoding = ""

    def __init__(self, stream: IO[bytes], chunk_size: int, compression: CompressionType) -> None:
        self.writer = McapWriter(stream, chunk_size=chunk_size, compression=compression)
        self.writer.start(profile=self.profile, library=_LIBRARY)
        self.schemas: dict[str, int] = {}
        self.channels: dict[str, tuple[int, str]] = {}
        self.sequence: dict[str, int] = {}

    def encode(self, record: Record, seq: int) -> tuple[str, bytes]:
        raise NotImplementedError

    def register(self, schema_name: str) -> int:
        raise NotImplementedError

    def channel_encoding(self, schema_name: str) -> str:
        return self.message_encoding

    def write(self, topic: str, log_time_ns: int, record: Record) -> None:
        seq = self.sequence.get(topic, 0)
        self.sequence[topic] = seq + 1
        schema_name, data = self.encode(record, seq)
        if topic not in self.channels:
            if schema_name not in self.schemas:
                self.schemas[schema_name] = self.register(schema_name)
            channel_id = self.writer.register_channel(
                topic=topic, message_encoding=self.channel_encoding(schema_name),
                schema_id=self.schemas[schema_name],
            )
            self.channels[topic] = (channel_id, schema_name)
        channel_id, channel_schema = self.channels[topic]
        if channel_schema != schema_name:
            raise ValueError(
                f"topic {topic}: has schema {channel_schema}, cannot write {schema_name}")
        self.writer.add_message(channel_id=channel_id, log_time=log_time_ns, data=data,
                                publish_time=log_time_ns, sequence=seq)

    def finish(self) -> None:
        self.writer.finish()


class _Ros1Sink(_Sink):
    profile = "ros1"
    message_encoding = "ros1"

    def encode(self, record: Record, seq: int) -> tuple[str, bytes]:
        name, msg = ros_message(record, ros1=True, seq=seq)
        return name, ros1_serialize(name, msg, MSGS_ROS1)

    def register(self, schema_name: str) -> int:
        return self.writer.register_schema(
            schema_name, "ros1msg", full_text(schema_name, MSGS_ROS1).encode())


class _Ros2Sink:
    """ROS 2 through `mcap_ros2`'s writer (CDR serialisation from the message definitions)."""

    def __init__(self, stream: IO[bytes], chunk_size: int, compression: CompressionType) -> None:
        self.writer = Ros2Writer(stream, chunk_size=chunk_size, compression=compression)
        self.schemas: dict[str, Any] = {}
        self.sequence: dict[str, int] = {}
        self.topic_types: dict[str, str] = {}

    def write(self, topic: str, log_time_ns: int, record: Record) -> None:
        seq = self.sequence.get(topic, 0)
        self.sequence[topic] = seq + 1
        short, msg = ros_message(record, ros1=False)
        if self.topic_types.setdefault(topic, short) != short:
            raise ValueError(
                f"topic {topic}: has type {self.topic_types[topic]}, cannot write {short}")
        pkg, name = short.split("/")
        full = f"{pkg}/msg/{name}"
        if full not in self.schemas:
            self.schemas[full] = self.writer.register_msgdef(full, full_text(short, MSGS_ROS2))
        self.writer.write_message(topic, self.schemas[full], msg, log_time=log_time_ns,
                                  publish_time=log_time_ns, sequence=seq)

    def finish(self) -> None:
        self.writer.finish()


class _ProtobufSink(_Sink):
    message_encoding = "protobuf"

    def encode(self, record: Record, seq: int) -> tuple[str, bytes]:
        name, msg = foxglove_message(record, json_mode=False)
        return name, to_protobuf(name, msg)

    def register(self, schema_name: str) -> int:
        return register_schema(self.writer, PROTO_CLASSES[schema_name])


class _JsonSink(_Sink):
    message_encoding = "json"

    def encode(self, record: Record, seq: int) -> tuple[str, bytes]:
        name, msg = foxglove_message(record, json_mode=True)
        return name, to_json(msg)

    def register(self, schema_name: str) -> int:
        return self.writer.register_schema(schema_name, "jsonschema", json_schema(schema_name))


_SINKS: dict[str, Callable[[IO[bytes], int, CompressionType], Any]] = {
    "ros2": _Ros2Sink,
    "ros1": _Ros1Sink,
    "foxglove-protobuf": _ProtobufSink,
    "foxglove-json": _JsonSink,
}


def write_log(
    path: Path,
    messages: Iterable[tuple[str, int, Record]],
    encoding: str,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
    compression: CompressionType = CompressionType.ZSTD,
) -> None:
    """Write `(topic, log_time_ns, record)` messages, in log-time order, to an MCAP file.

    encoding: one of `ENCODINGS` ("ros2", "ros1", "foxglove-protobuf", "foxglove-json").
    chunk_size: uncompressed bytes per chunk (fixed, for reproducible output).
    compression: of the chunks (zstd; none for data compressed already, e.g. JPEG images).
    Raises ValueError on an unknown encoding, decreasing log times or a topic whose record
    type changes. Nothing is left under `path` if writing fails.
    """
    if encoding not in _SINKS:
        raise ValueError(f"unknown log encoding {encoding!r} (known: {', '.join(ENCODINGS)})")
    with atomic_open(Path(path), "wb") as handle:
        stream = CacheDropping(handle)
        try:
            sink = _SINKS[encoding](cast(IO[bytes], stream), chunk_size, compression)
            last = None
            for topic, log_time_ns, record in messages:
                if last is not None and log_time_ns < last:
                    raise ValueError(f"log times must not decrease: {topic} at {log_time_ns} "
                                     f"ns after {last} ns")
                last = log_time_ns
                sink.write(topic, int(log_time_ns), record)
            sink.finish()
        finally:
            stream.close()
