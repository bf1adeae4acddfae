"""Transform channels (`/tf`, `/tf_static`) of an MCAP log -> `core.sync.tf_tree.TransformSamples`.

A channel carries transforms when its (message encoding, schema) decodes to the `transforms`
kind in `registry.DECODERS`: ROS 2 `tf2_msgs/msg/TFMessage` (cdr), ROS 1 `tf2_msgs/TFMessage`
or `tf/tfMessage` (ros1), Foxglove `foxglove.FrameTransform` / `foxglove.FrameTransforms`
(protobuf or json). One message may hold several transforms.

A channel is static (latched, valid for the whole log) when its topic's last name is
`tf_static` (the ROS and Foxglove convention), or when the recorder marked it latched: ROS 2
`offered_qos_profiles` with transient-local durability, ROS 1 `latching: 1`.

Stamps are the transforms' own (`header.stamp`, Foxglove `timestamp`), or the message's log
time when that is zero or `time_source` is "log_time" (as `reader.LogReader` does).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mcap.records import Channel, Message, Schema

from ...core.sync.tf_samples import SampleCollector, TransformSamples, frame_id_problem
from ...errors import InputError
from .encodings.registry import DESERIALIZERS, find_decoder
from .scan import ALL, SKIP, LogScan, scan_mcap

_TRANSIENT_LOCAL = re.compile(r"durability:\s*(1|transient_local)\b", re.IGNORECASE)


def is_transform_schema(message_encoding: str, schema_name: str) -> bool:
    """True when channels of this encoding and schema carry transforms."""
    return find_decoder(message_encoding, schema_name, ("transforms",)) is not None


def is_static_channel(topic: str, metadata: dict[str, str] | None = None) -> bool:
    """True for a latched transform channel (see the module docstring)."""
    if topic.rstrip("/").rsplit("/", 1)[-1] == "tf_static":
        return True
    meta = metadata or {}
    if str(meta.get("latching", "")).strip() in ("1", "true", "True"):
        return True
    return bool(_TRANSIENT_LOCAL.search(meta.get("offered_qos_profiles", "")))


@dataclass(frozen=True)
class TransformLog:
    """The transforms of a log: `samples` of every transform channel; per transform topic:
    `topics` {topic: static?}, `counts` {topic: transforms}, `child_frames` {topic: sorted
    child frame names}; and the `scan` (channels, damage)."""

    samples: TransformSamples
    topics: dict[str, bool]
    counts: dict[str, int]
    child_frames: dict[str, tuple[str, ...]]
    scan: LogScan


class TransformCollector:
    """Decodes transform messages of several channels into growing sample lists.

    `select(channel, schema)` is a `scan.Select` (ALL for transform channels); `add(channel,
    schema, message)` decodes one message (InputError naming topic and log time if it does
    not decode); `samples()` returns everything collected.
    """

    def __init__(self, path: Path, use_log_time: bool = False) -> None:
        self.path = Path(path)
        self.use_log_time = use_log_time
        self._deserializers: dict[str, Any] = {}
        self._decode: dict[int, Any] = {}
        self._static: dict[int, bool] = {}
        self.topics: dict[str, bool] = {}
        self.counts: dict[str, int] = {}
        self.child_frames: dict[str, set[str]] = {}
        self._samples = SampleCollector()

    def select(self, channel: Channel, schema: Schema | None) -> str:
        name = schema.name if schema else ""
        return ALL if is_transform_schema(channel.message_encoding, name) else SKIP

    def _open(self, channel: Channel, schema: Schema | None) -> Any:
        enc = channel.message_encoding
        decoder = find_decoder(enc, schema.name if schema else "", ("transforms",))
        if decoder is None:
            raise ValueError(f"{channel.topic} does not carry transforms")
        try:
            if enc not in self._deserializers:
                self._deserializers[enc] = DESERIALIZERS[enc]()
            deserialize = self._deserializers[enc].for_schema(schema)
        except Exception as exc:  # third-party schema parsers raise anything
            raise InputError(f"{self.path}: schema {schema.name if schema else ''!r} of topic "
                             f"{channel.topic} cannot be parsed ({exc})") from exc
        static = is_static_channel(channel.topic, channel.metadata)
        self.topics[channel.topic] = static
        self.counts.setdefault(channel.topic, 0)
        self.child_frames.setdefault(channel.topic, set())
        return deserialize, decoder.convert, static

    def add(self, channel: Channel, schema: Schema | None, message: Message) -> None:
        if channel.id not in self._decode:
            self._decode[channel.id] = self._open(channel, schema)
        deserialize, convert, static = self._decode[channel.id]
        try:
            records = convert(deserialize(message.data))
        except Exception as exc:  # third-party decoders raise anything on malformed bytes
            raise InputError(
                f"{self.path}: message on {channel.topic} at log time "
                f"{message.log_time / 1e9:.6f} s does not decode as "
                f"{schema.name if schema else 'transforms'} ({exc})") from exc
        for r in records:
            why = frame_id_problem(r.frame_id) or frame_id_problem(r.child_frame_id)
            if why is not None:
                raise InputError(f"{self.path}: transform on {channel.topic} at log time "
                                 f"{message.log_time / 1e9:.6f} s has {why}")
            stamp = r.stamp_ns
            self._samples.add(r.frame_id, r.child_frame_id, static,
                              message.log_time if self.use_log_time or stamp <= 0 else stamp,
                              (*r.position, *r.orientation))
            self.child_frames[channel.topic].add(r.child_frame_id)
        self.counts[channel.topic] += len(records)

    def result(self, scan: LogScan) -> TransformLog:
        """Everything collected, with the scan it came from."""
        for ch in scan.channels:  # channels without messages are listed too
            if is_transform_schema(ch.message_encoding, ch.schema_name):
                self.topics.setdefault(ch.topic, is_static_channel(ch.topic, ch.metadata))
                self.counts.setdefault(ch.topic, 0)
                self.child_frames.setdefault(ch.topic, set())
        return TransformLog(self.samples(), dict(self.topics), dict(self.counts),
                            {t: tuple(sorted(f)) for t, f in self.child_frames.items()}, scan)

    def samples(self) -> TransformSamples:
        return self._samples.samples()


def read_transforms(path: Path, time_source: str = "header",
                    allow_truncated: bool = False) -> TransformLog:
    """Every transform of every transform channel of the log at `path` (static ones flagged).

    Reads only the chunks that hold transform messages when the log has intact indexes,
    streams it otherwise. Raises InputError when the file is not MCAP, when a message does
    not decode, and on damage unless `allow_truncated` (then the transforms before it are
    returned and `scan.damage` says where it is).
    """
    collector = TransformCollector(path, use_log_time=time_source == "log_time")
    scan = scan_mcap(Path(path), collector.select, collector.add)
    if scan.damage and not allow_truncated:
        raise InputError(f"{path}: damaged log: {scan.damage}; re-copy or repair the log, or pass "
                         "--allow-truncated to use the data before the damage")
    return collector.result(scan)
