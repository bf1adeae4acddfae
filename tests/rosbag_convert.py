"""Write the messages of a ROS 2 (CDR) MCAP log into a ROS 2 sqlite3 bag (`.db3`, the CDR bytes
and message definitions as they are) and a ROS 1 `.bag` (CDR converted to ROS 1 wire format
by rosbags, with the ROS 1 Noetic message definitions), as recorders would have written them."""

from __future__ import annotations

from pathlib import Path

from mcap.reader import make_reader
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_types_from_msg, get_typestore


def _known(store, name: str, definition: bytes):
    """`store` knowing type `name` (a type missing from it, e.g. tf2_msgs/msg/TFMessage in
    some stores, registered from the first block of the MCAP schema's definition)."""
    if name not in store.fielddefs:
        store.register(get_types_from_msg(definition.decode().split("=" * 10)[0], name))
    return store


def mcap_to_db3(src: Path, dst: Path) -> Path:
    """A rosbag2 sqlite3 bag folder at `dst` (metadata.yaml + one .db3) of `src`'s messages."""
    store = get_typestore(Stores.LATEST)
    with open(src, "rb") as f, Writer2(dst, version=9) as writer:
        conns: dict[int, object] = {}
        for schema, channel, message in make_reader(f).iter_messages(log_time_order=True):
            if channel.id not in conns:
                rihs01 = _known(store, schema.name, schema.data).hash_rihs01(schema.name)
                conns[channel.id] = writer.add_connection(
                    channel.topic, schema.name, msgdef=schema.data.decode(), rihs01=rihs01)
            writer.write(conns[channel.id], message.log_time, message.data)
    return dst


def mcap_to_bag(src: Path, dst: Path) -> Path:
    """A ROS 1 bag at `dst` of `src`'s messages, converted from CDR."""
    ros2, ros1 = get_typestore(Stores.LATEST), get_typestore(Stores.ROS1_NOETIC)
    with open(src, "rb") as f, Writer1(dst) as writer:
        conns: dict[int, object] = {}
        for schema, channel, message in make_reader(f).iter_messages(log_time_order=True):
            if channel.id not in conns:
                _known(ros2, schema.name, schema.data)
                conns[channel.id] = writer.add_connection(
                    channel.topic, schema.name,
                    typestore=_known(ros1, schema.name, schema.data.replace(b"/msg/", b"/")))
            writer.write(conns[channel.id], message.log_time,
                         ros2.cdr_to_ros1(message.data, schema.name))
    return dst
