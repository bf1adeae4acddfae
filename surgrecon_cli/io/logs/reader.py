"""Stream an MCAP log once, in file order, as role-tagged records, with bounded memory.

A log is one file or a folder of split files (io/logs/log_input.py), read one after the other.
ROS 1 `.bag` and ROS 2 `.db3` files are read through rosbags as the same records
(`rosbag.bag_records`), so every container goes through one decoding path.

Reads top-level records sequentially (`mcap.stream_reader.StreamReader`, chunk CRCs checked),
so it works on files without a summary or footer (recorder crashed). Damage (truncation,
bad CRC, bad compression, bad record length) raises `InputError` naming the file, the byte
offset where valid data ends and the log time reached; with `allow_truncated` the messages
before the damage are kept and the damage is reported in `LogReader.damage`.
"""

from __future__ import annotations

import hashlib
import logging
import shlex
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path
from typing import Any

import zstandard
from mcap.exceptions import EndOfFile, InvalidMagic, McapError, RecordLengthLimitExceeded
from mcap.records import Channel, McapRecord, Message, Schema
from mcap.stream_reader import CRCValidationError, StreamReader

from ...config import TopicsConfig
from ...errors import InputError, TopicError
from .bounded import BoundedFile, TrackedFile, as_stream, expand_chunks, read_summary
from .encodings.base import SchemaDecoder
from .encodings.registry import DESERIALIZERS, find_decoder, no_images_message, supported
from .log_input import resolve_log
from .records import Record
from .rosbag import bag_records, check_bag_magic, is_bag, read_along
from .stream import STREAM_ERRORS, RecordStream, one_line
from .topics import ROLE_KINDS, TopicRoles

logger = logging.getLogger(__name__)

MCAP_MAGIC = b"\x89MCAP0\r\n"
_MAX_LISTED = 40


@dataclass(frozen=True)
class LogItem:
    """One record in its role: `camera` is the camera id for camera roles, else ""."""

    role: str
    camera: str
    topic: str
    log_time_ns: int
    record: Record


@dataclass
class _ChannelInfo:
    topic: str
    schema_name: str
    encoding: str
    roles: list[tuple[str, str]] = field(default_factory=list)
    decoder: SchemaDecoder | None = None
    deserialize: Callable[[bytes], Any] | None = None


class LogReader:
    """Iterate a log's records in the roles of `topics`; see the module docstring.

    After iteration: `sha256` (of the whole file), `size`, `valid_bytes`, `damage` (None or a
    one-line description), `last_log_time_ns`, `channels` {topic: "schema (encoding)"},
    `message_counts` {topic: n}; `check_roles()` raises `TopicError` for missing roles.
    require_roles: fail before streaming when the summary shows a required role missing;
    extra_tools: the pose topics of `[[tools]]` (role "extra_tool_pose", camera = index).
    """

    def __init__(self, path: Path, topics: TopicsConfig, time_source: str = "header",
                 allow_truncated: bool = False,
                 on_bytes: Callable[[int], None] | None = None,
                 require_roles: bool = True, extra_tools: tuple[str, ...] = ()) -> None:
        self.input = resolve_log(path)
        self.path = self.input.path
        self.file = self.input.files[0]  # the file being read (named in damage messages)
        self.roles = TopicRoles(topics, extra_tools)
        self.use_log_time = time_source == "log_time"
        self.allow_truncated = allow_truncated
        self.on_bytes = on_bytes
        self.require_roles = require_roles
        self.size = self.input.size
        self._offset = 0  # bytes of the files before the current one
        self.sha256 = ""
        self.valid_bytes = 0
        self.damage: str | None = None
        self.salvaged: str | None = None  # damage after the data: every message still read
        self.last_log_time_ns: int | None = None
        self.channels: dict[str, str] = {}
        self.message_counts: dict[str, int] = {}
        self._role_topics: dict[str, set[str]] = {}
        self._deserializers: dict[str, Any] = {}
        self._log_time_stamps: dict[str, int] = {}  # records stamped by log time, per topic
        self.transform_topics: set[str] = set()  # role topics carrying transforms (TF)
        self._image_channels: set[str] = set()  # topics of an image schema, whatever the role

    # -- channels and roles --------------------------------------------------------------
    def _classify(self, topic: str, schema_name: str, encoding: str) -> _ChannelInfo:
        info = _ChannelInfo(topic, schema_name, encoding)
        if find_decoder(encoding, schema_name, ROLE_KINDS["image"]) is not None:
            self._image_channels.add(topic)
        matches = self.roles.match(topic)
        rejected = []
        for m in matches:
            decoder = find_decoder(encoding, schema_name, ROLE_KINDS[m.role])
            if decoder is None:
                rejected.append(m.role)
                continue
            if (m.role == "camera_pose" and decoder.kind == "pose" and not m.camera
                    and not self.roles.config.camera_from_ecm):
                raise TopicError(
                    f"{self.path}: topics.camera_pose = {self.roles.patterns['camera_pose']!r} "
                    f"has no {{camera}} placeholder, so the poses on {topic} ({schema_name}) "
                    "belong to no camera; use a {camera} pattern, transforms with "
                    "topics.camera_frame, or set each camera's pose on it in "
                    "topics.camera_from_ecm (x y z qx qy qz qw per camera)")
            info.decoder = decoder
            info.roles.append((m.role, m.camera))
            if decoder.kind == "transforms":
                self.transform_topics.add(topic)
        if rejected and not info.roles:
            role = rejected[0]
            raise TopicError(
                f"{self.path}: topic {topic} matches topics.{role} = "
                f"{self.roles.patterns[role]!r} but its schema {schema_name!r} ({encoding}) "
                f"cannot be read as {role}; supported: {', '.join(supported(ROLE_KINDS[role]))}")
        return info

    def _missing_roles_error(self, missing: list[str], channels: dict[str, str]) -> InputError:
        if "image" in missing and not self._image_channels and not self.damage:
            return InputError(no_images_message(self.path))
        wanted = ", ".join(f"topics.{r} = {self.roles.patterns[r]!r}" for r in missing)
        if self.damage:
            return InputError(f"{self.path}: no complete frame before the damage "
                              f"({self.damage}); nothing read for {wanted}")
        listed = [f"{t}  {s}" for t, s in sorted(channels.items())]
        if len(listed) > _MAX_LISTED:
            listed = [*listed[:_MAX_LISTED], f"... ({len(listed) - _MAX_LISTED} more)"]
        beside = Path(self.path).with_suffix(".toml")  # what `surgrecon convert` writes
        given = (f"--config {shlex.quote(str(beside))} (written beside the log, e.g. by "
                 "`surgrecon convert`), or " if beside.is_file() else "")
        return TopicError(
            f"{self.path}: no topic for {wanted}; set [topics] in a --config file: {given}"
            f"`surgrecon info {shlex.quote(str(self.path))} --write-config FILE` writes one (a "
            "robot role the log does not record, tool_pose or joint_states, is set to \"\"); "
            f"topics in the log{':' if listed else ': none'}", details=tuple(listed))

    def _early_check(self) -> None:
        """Check roles from the summary sections, when every file has an intact one."""
        channels: dict[str, str] = {}
        found: set[str] = set()
        for path in self.input.files:
            try:
                with open(path, "rb") as f:
                    f.seek(-len(MCAP_MAGIC), 2)
                    if f.read() != MCAP_MAGIC:
                        return
                    summary = read_summary(BoundedFile(f, path.stat().st_size))
            except (*STREAM_ERRORS, OSError):
                return
            if summary is None or not summary[1]:
                return
            for ch in summary[1].values():
                schema = summary[0].get(ch.schema_id)
                name = schema.name if schema else ""
                channels[ch.topic] = f"{name} ({ch.message_encoding})"
                info = self._classify(ch.topic, name, ch.message_encoding)
                found.update(role for role, _ in info.roles)
        missing = [r for r in self.roles.required if r not in found]
        if missing and self.require_roles:
            raise self._missing_roles_error(missing, channels)

    def check_roles(self) -> None:
        """After iteration: every required role has a channel and (transforms) a frame."""
        missing = [r for r in self.roles.required if r not in self._role_topics]
        if missing:
            raise self._missing_roles_error(missing, self.channels)

    # -- streaming -----------------------------------------------------------------------
    def check_magic(self) -> None:
        """InputError unless every file starts with its format's magic bytes."""
        for path in self.input.files:
            if is_bag(path):
                check_bag_magic(path)
                continue
            with open(path, "rb") as f:
                head = f.read(len(MCAP_MAGIC))
            if head != MCAP_MAGIC:
                raise InputError(f"{path}: not an MCAP file (it does not start with the "
                                 "MCAP magic bytes); pass a .mcap log or a bag folder")

    def __iter__(self) -> Iterator[LogItem]:
        self.check_magic()
        self._early_check()
        sha = hashlib.sha256()
        for path in self.input.files:
            self.file = path
            self._deserializers = {}  # schema ids are per file; decoders cache by id
            size = path.stat().st_size
            with open(path, "rb") as raw:
                tracked = TrackedFile(BoundedFile(raw, size), self.on_bytes, sha)
                if self.damage is None and is_bag(path):
                    yield from self._records(read_along(bag_records(path), tracked, size),
                                             partial(getattr, tracked, "pos"), size)
                    self.valid_bytes = self._offset + size
                elif self.damage is None:  # after damage, nothing later is used
                    yield from self._stream(tracked, size)
                tracked.drain()  # the hash covers the whole log, damaged part included
            self._offset += size
        self.sha256 = sha.hexdigest()

    def _stream(self, tracked: TrackedFile, size: int) -> Iterator[LogItem]:
        stream = StreamReader(as_stream(tracked), validate_crcs=True, emit_chunks=True,
                              record_size_limit=size)
        yield from self._records(expand_chunks(stream.records), partial(getattr, tracked, "pos"),
                                 size)

    def _records(self, records: Iterator[McapRecord], pos: Callable[[], int], size: int
                 ) -> Iterator[LogItem]:
        """The role items of one file's records; `pos()` is the bytes read of the file (of
        `size` bytes)."""
        stream = RecordStream(records, pos)
        channels: dict[int, _ChannelInfo] = {}
        for record in stream:
            self.valid_bytes = self._offset + stream.valid
            if isinstance(record, Channel):
                channels[record.id] = self._open_channel(record, stream.schemas)
            else:
                yield from self._message(channels[record.channel_id], record)
        self.valid_bytes = self._offset + (size if stream.footer else stream.valid)
        if stream.unknown_channel is not None:
            self._on_damage(McapError(f"message on unknown channel {stream.unknown_channel}"),
                            stream.data_complete)
        elif stream.error is not None:
            self._on_damage(stream.error, stream.data_complete)

    def _open_channel(self, channel: Channel, schemas: dict[int, Schema]) -> _ChannelInfo:
        schema = schemas.get(channel.schema_id)
        name = schema.name if schema else ""
        self.channels[channel.topic] = f"{name} ({channel.message_encoding})"
        info = self._classify(channel.topic, name, channel.message_encoding)
        for role, _ in info.roles:
            self._role_topics.setdefault(role, set()).add(channel.topic)
        if info.roles:
            factory = DESERIALIZERS.get(channel.message_encoding)
            try:
                if factory is None:
                    raise ValueError(f"no deserializer for {channel.message_encoding}")
                if channel.message_encoding not in self._deserializers:
                    self._deserializers[channel.message_encoding] = factory()
                info.deserialize = self._deserializers[channel.message_encoding].for_schema(schema)
            except Exception as exc:  # third-party schema parsers raise anything
                raise InputError(f"{self.path}: schema {name!r} of topic {channel.topic} cannot "
                                 f"be parsed ({one_line(exc)})") from exc
        return info

    def _message(self, info: _ChannelInfo, message: Message) -> Iterator[LogItem]:
        self.message_counts[info.topic] = self.message_counts.get(info.topic, 0) + 1
        self.last_log_time_ns = message.log_time
        if info.decoder is None or info.deserialize is None or info.topic in self.transform_topics:
            return  # transforms are read into the TF tree (io/logs/transforms.py)
        try:
            records = info.decoder.convert(info.deserialize(message.data))
        except Exception as exc:  # third-party decoders raise anything on malformed bytes
            raise InputError(
                f"{self.path}: message on {info.topic} at log time {message.log_time / 1e9:.6f} s "
                f"does not decode as {info.schema_name} ({one_line(exc)})") from exc
        for record in records:
            if self.use_log_time or record.stamp_ns <= 0:
                self._note_log_time(info.topic, record.stamp_ns)
                record = replace(record, stamp_ns=message.log_time)
            for role, camera in info.roles:
                yield LogItem(role, camera, info.topic, message.log_time, record)

    def role_uses_transforms(self, role: str) -> bool:
        """Whether `role`'s topics carry transforms (its poses then come from the TF tree)."""
        return any(t in self.transform_topics for t in self._role_topics.get(role, ()))

    def _note_log_time(self, topic: str, stamp_ns: int) -> None:
        count = self._log_time_stamps.get(topic, 0)
        self._log_time_stamps[topic] = count + 1
        if count == 0 and not self.use_log_time:
            logger.warning("%s: %s has messages with a %s header stamp (first: %d ns); they are "
                           "placed at their log time (set ingest.time_source = \"log_time\" to "
                           "use the log time for every message)", self.path, topic,
                           "negative" if stamp_ns < 0 else "zero", stamp_ns)

    def clock_of(self, topic: str) -> str:
        """Which clock stamped `topic`'s records: "header stamps", "log time", or a mix."""
        fallback = self._log_time_stamps.get(topic, 0)
        if self.use_log_time or (fallback and fallback >= self.message_counts.get(topic, 0)):
            return "log time"
        return f"header stamps, {fallback} at log time" if fallback else "header stamps"

    def _on_damage(self, exc: BaseException, data_complete: bool) -> None:
        if isinstance(exc, EndOfFile | EOFError):
            reason = ("the file ends inside a record (truncated: recorder crashed or copy "
                      "incomplete)")
        elif isinstance(exc, CRCValidationError):
            reason = "a chunk fails its CRC check (corrupt data)"
        elif isinstance(exc, zstandard.ZstdError | RuntimeError):
            reason = "a chunk does not decompress (corrupt data)"
        elif isinstance(exc, RecordLengthLimitExceeded):
            reason = ("a record runs past the end of the file (truncated: recorder crashed or "
                      "copy incomplete; or a corrupt record length)")
        elif isinstance(exc, InvalidMagic):
            reason = "the closing magic bytes are wrong (corrupt end of file)"
        else:
            reason = f"a record is malformed (corrupt data: {one_line(exc)})"
        if data_complete:
            logger.warning("%s: %s after the data section; all messages were read",
                           self.file, reason)
            self.salvaged = f"{self.file.name}: {reason} after the data section"
            return
        t = self.last_log_time_ns
        when = f"log time {t / 1e9:.6f} s" if t is not None else "before any message"
        where = (f"byte {self.valid_bytes - self._offset} of {self.file.name} (byte "
                 f"{self.valid_bytes} of {self.size} over the bag's files)"
                 if len(self.input.files) > 1 else f"byte {self.valid_bytes} of {self.size}")
        self.damage = f"{reason}; valid data ends at {where} ({when})"
        if not self.allow_truncated:
            raise InputError(f"{self.file}: {self.damage}; re-copy or repair the log, or pass "
                             "--allow-truncated to use the data before the damage") from exc

