"""Writing an MCAP file of protobuf (Foxglove schemas) and JSON channels.

Protobuf schemas are registered as the FileDescriptorSet of the message type and its
dependencies (`mcap_protobuf.schema`, as Foxglove and `mcap-protobuf-support` read them),
JSON channels with a JSON Schema (`jsonschema` encoding). Chunks are zstd-compressed.
Every message is stamped twice with the same time: log and publish time.
"""

from __future__ import annotations

import json
from collections import Counter
from typing import IO, Any

from google.protobuf.message import Message
from mcap.well_known import MessageEncoding, SchemaEncoding
from mcap.writer import CompressionType, Writer
from mcap_protobuf.schema import build_file_descriptor_set

from ... import __version__

_CHUNK_BYTES = 4 << 20


class McapOut:
    """Messages to an open binary stream; `finish()` writes the summary and index."""

    def __init__(self, stream: IO[bytes], profile: str = "") -> None:
        self._writer = Writer(stream, chunk_size=_CHUNK_BYTES, compression=CompressionType.ZSTD)
        self._writer.start(profile=profile, library=f"surgrecon {__version__}")
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, tuple[int, str]] = {}
        self.counts: Counter[str] = Counter()

    def _channel(self, topic: str, schema_name: str, encoding: str, make_schema: Any,
                 message_encoding: str) -> int:
        if topic in self._channels:
            channel, name = self._channels[topic]
            if name != schema_name:
                raise ValueError(f"topic {topic!r} carries {name}, not {schema_name}")
            return channel
        key = f"{encoding}:{schema_name}"
        if key not in self._schemas:
            self._schemas[key] = self._writer.register_schema(
                name=schema_name, encoding=encoding, data=make_schema())
        channel = self._writer.register_channel(topic=topic, message_encoding=message_encoding,
                                                schema_id=self._schemas[key])
        self._channels[topic] = (channel, schema_name)
        return channel

    def _add(self, channel: int, topic: str, data: bytes, stamp_ns: int) -> None:
        self.counts[topic] += 1
        self._writer.add_message(channel_id=channel, log_time=int(stamp_ns), data=data,
                                 publish_time=int(stamp_ns), sequence=self.counts[topic])

    def protobuf(self, topic: str, message: Message, stamp_ns: int) -> None:
        """One protobuf message (e.g. a foxglove.PointCloud) on `topic`."""
        cls = type(message)
        name = cls.DESCRIPTOR.full_name
        channel = self._channel(
            topic, name, SchemaEncoding.Protobuf,
            lambda: build_file_descriptor_set(cls).SerializeToString(),
            MessageEncoding.Protobuf)
        self._add(channel, topic, message.SerializeToString(), stamp_ns)

    def json(self, topic: str, schema_name: str, schema: dict[str, Any], obj: dict[str, Any],
             stamp_ns: int) -> None:
        """One JSON object on `topic`, described by the JSON Schema `schema`."""
        channel = self._channel(topic, schema_name, SchemaEncoding.JSONSchema,
                                lambda: json.dumps(schema).encode("utf-8"), MessageEncoding.JSON)
        self._add(channel, topic, json.dumps(obj, allow_nan=False).encode("utf-8"), stamp_ns)

    def metadata(self, name: str, data: dict[str, str]) -> None:
        self._writer.add_metadata(name, data)

    def finish(self) -> None:
        self._writer.finish()
