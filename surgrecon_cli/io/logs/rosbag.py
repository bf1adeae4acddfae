"""ROS 1 `.bag` files and ROS 2 sqlite3 `.db3` files, read through `rosbags` (pure Python, no
ROS install) and handed on as the MCAP records an MCAP file of the same data holds.

A bag's connections become `Schema` + `Channel` records and its messages `Message` records
carrying the raw serialized bytes (ROS 1 wire format, or CDR), so they are decoded by the
same `ros1` / `cdr` adapters as an MCAP log's (registry.py): one decoding path for every
container. ROS 1 schema names are given in ROS 1 spelling (`sensor_msgs/Image`; rosbags
renames them to ROS 2's), latched ROS 1 topics get MCAP's `latching: 1` metadata and ROS 2
transient-local topics a `durability: transient_local` QoS, as the MCAP recorders write them.
A `.db3` written before rosbag2 stored message definitions gets its definitions generated
from rosbags' type store (standard message types only).

Messages come in log-time order (rosbags sorts them); the log time is the bag's receive time.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import ExitStack
from pathlib import Path
from typing import Any

from mcap.records import Channel, Message, Schema

from ...errors import InputError
from .bounded import TrackedFile

ROS1_SUFFIX, DB3_SUFFIX = ".bag", ".db3"
ROS1_MAGIC = b"#ROSBAG V2.0\n"
SQLITE_MAGIC = b"SQLite format 3\x00"

BagRecord = Schema | Channel | Message


def is_bag(path: Path) -> bool:
    """True for a file that is read as a bag (by its suffix)."""
    return path.suffix in (ROS1_SUFFIX, DB3_SUFFIX)


def check_bag_magic(path: Path) -> None:
    """InputError unless `path` starts as its kind of bag does."""
    magic, kind = ((ROS1_MAGIC, "ROS 1 bag (#ROSBAG V2.0)") if path.suffix == ROS1_SUFFIX
                   else (SQLITE_MAGIC, "sqlite3 database"))
    with open(path, "rb") as f:
        head = f.read(len(magic))
    if head != magic:
        raise InputError(f"{path}: not a {kind}: it does not start with the {kind}'s magic "
                         "bytes; pass a .bag, .db3, .mcap log or a bag folder")


def bag_records(path: Path) -> Iterator[BagRecord]:
    """Every connection of the bag at `path` as Schema + Channel (ids = connection ids), then
    its messages as Message records in log-time order. InputError (one line, naming the
    file) when rosbags cannot read it."""
    from rosbags.rosbag1 import Reader as Reader1
    from rosbags.rosbag2 import Reader as Reader2

    ros1 = path.suffix == ROS1_SUFFIX
    with ExitStack() as stack:
        try:
            reader: Any = Reader1(path) if ros1 else Reader2(path)
            stack.enter_context(reader)
            connections = list(reader.connections)
        except Exception as exc:  # rosbags raises its own errors, sqlite3's and struct's
            raise _unreadable(path, exc) from exc
        store = None
        for conn in connections:
            if not ros1 and not conn.msgdef.data and store is None:
                store = _typestore()
            schema, channel = _channel(conn, ros1, store)
            yield schema
            yield channel
        sequence: dict[int, int] = {}
        messages = reader.messages() if ros1 else reader.messages(connections)
        while True:
            try:
                conn, log_time, data = next(messages)
            except StopIteration:
                return
            except Exception as exc:
                raise _unreadable(path, exc) from exc
            seq = sequence[conn.id] = sequence.get(conn.id, -1) + 1
            yield Message(channel_id=conn.id, sequence=seq, log_time=log_time,
                          publish_time=log_time, data=bytes(data))


def read_along(records: Iterator[BagRecord], tracked: TrackedFile, size: int
               ) -> Iterator[BagRecord]:
    """`records` of a bag, while `tracked` (the same file, `size` bytes) is read in step
    with the message bytes seen: progress for its callback; the hash covers the whole file
    once it is drained."""
    seen = 0
    for record in records:
        if isinstance(record, Message):
            seen += len(record.data)
            if seen > tracked.pos:
                tracked.read(min(seen, size) - tracked.pos)
        yield record


def _unreadable(path: Path, exc: BaseException) -> InputError:
    text = " ".join(str(exc).split()) or type(exc).__name__
    hint = ("(an unindexed ROS 1 bag needs `rosbag reindex`)" if path.suffix == ROS1_SUFFIX
            else "(a rosbag2 sqlite3 file)")
    return InputError(f"{path}: not a readable bag {hint}: {text[:200]}")


def _typestore() -> Any:
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.LATEST)


def _channel(conn: Any, ros1: bool, store: Any) -> tuple[Schema, Channel]:
    """The MCAP schema and channel of a rosbags connection."""
    from rosbags.interfaces import QosDurability

    definition = conn.msgdef.data
    if ros1:
        name, encoding, message_encoding = conn.msgtype.replace("/msg/", "/"), "ros1msg", "ros1"
        metadata = {"latching": "1"} if conn.ext.latching else {}
    else:
        name, encoding, message_encoding = conn.msgtype, "ros2msg", "cdr"
        if conn.msgdef.format.name == "IDL":
            encoding = "ros2idl"
        if not definition and store is not None and conn.msgtype in store.fielddefs:
            definition = store.generate_msgdef(conn.msgtype, ros_version=2)[0]
        latched = any(q.durability == QosDurability.TRANSIENT_LOCAL
                      for q in conn.ext.offered_qos_profiles)
        metadata = {"offered_qos_profiles": "- durability: transient_local"} if latched else {}
    schema = Schema(id=conn.id, name=name, encoding=encoding, data=definition.encode())
    channel = Channel(id=conn.id, schema_id=conn.id, topic=conn.topic,
                      message_encoding=message_encoding, metadata=metadata)
    return schema, channel
