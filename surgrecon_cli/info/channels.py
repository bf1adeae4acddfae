"""Scan a log's files once each: per channel statistics, every transform, and the first
message of every other readable channel.

Fast: counts and log-time spans come from the summary and message indexes when a file has
them (`mcap.scan`); only transform messages are decoded in full, and of every other channel
that surgrecon can read only its first message (for its frame id and a detail such as the
image format). A file without indexes is streamed once.

A log split over several files (a rosbag2 bag folder, split .mcap files; `log_input`) is
described as one: a channel is the same (topic, schema, encoding) in every file, its counts
are summed and its span runs from its first message in any file to its last.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from mcap.records import Channel, Message, Schema

from ..core.geometry.poses import rectified_rig_pose
from ..core.sync.streams import mean_rate_hz
from ..core.sync.tf_samples import TransformSamples, concat_samples
from ..errors import GeometryError
from ..io.logs.encodings.base import KINDS
from ..io.logs.encodings.registry import DECODERS, DESERIALIZERS, find_decoder
from ..io.logs.records import CameraInfoRecord, ImageRecord, JointStateRecord, PoseRecord
from ..io.logs.scan import ALL, FIRST, SKIP, ChannelScan, LogScan, scan_mcap
from ..io.logs.transforms import TransformCollector, TransformLog, is_static_channel


@dataclass(frozen=True)
class ChannelInfo:
    """One channel: `kind` what its schema carries ("" if surgrecon cannot read it), message
    count, log times (ns) of the first and last message (-1 if none), mean rate (Hz; 0 =
    none: one message, or all within 1 ms, `core.sync.streams.mean_rate_hz`), the
    first message's frame id ("" if none or not read), a short `detail`, for transform
    channels `static` (latched) and the child frames, and for camera intrinsics the
    `stereo_baseline_m` their projection P places the camera off its rig's first camera
    (|(Tx, Ty)| / fx′, m; 0 = none: a monocular calibration, or the first camera)."""

    topic: str
    schema_name: str
    message_encoding: str
    kind: str
    count: int
    first_ns: int
    last_ns: int
    rate_hz: float
    frame_id: str = ""
    detail: str = ""
    static: bool = False
    child_frames: tuple[str, ...] = ()
    stereo_baseline_m: float = 0.0

    @property
    def span_s(self) -> float:
        """Seconds from the first to the last message (0 with fewer than two)."""
        return (self.last_ns - self.first_ns) * 1e-9 if self.count > 1 else 0.0


@dataclass(frozen=True)
class FileInfo:
    """One file of the log: bytes, messages, log-time span (ns, -1 without messages),
    whether its indexes were used, and its damage (None, or where valid data ends)."""

    path: Path
    size: int
    messages: int
    first_ns: int
    last_ns: int
    indexed: bool
    damage: str | None


@dataclass(frozen=True)
class ChannelScanResult:
    """What the scan of every file found: the first file's header profile and library, the
    files, the channels (merged over the files, in order of first appearance), every
    transform sample, and per transform topic the transforms it carried."""

    profile: str
    library: str
    files: tuple[FileInfo, ...]
    channels: tuple[ChannelInfo, ...]
    samples: TransformSamples
    transform_topics: tuple[str, ...]


class _FirstMessages:
    """Decodes the first message of each readable non-transform channel: kind, frame, detail."""

    def __init__(self) -> None:
        self._deserializers: dict[str, Any] = {}
        # channel id -> kind, frame, detail, stereo baseline (m)
        self.found: dict[int, tuple[str, str, str, float]] = {}

    def select(self, channel: Channel, schema: Schema | None) -> str:
        name = schema.name if schema else ""
        return FIRST if find_decoder(channel.message_encoding, name, KINDS) else SKIP

    def add(self, channel: Channel, schema: Schema | None, message: Message) -> None:
        name = schema.name if schema else ""
        decoder = find_decoder(channel.message_encoding, name, KINDS)
        if decoder is None:
            return
        enc = channel.message_encoding
        try:
            if enc not in self._deserializers:
                self._deserializers[enc] = DESERIALIZERS[enc]()
            records = decoder.convert(self._deserializers[enc].for_schema(schema)(message.data))
        except Exception as exc:  # third-party decoders raise anything on malformed bytes
            if (enc, name) in DECODERS:
                self.found[channel.id] = (decoder.kind, "", "first message does not decode "
                                                            f"({type(exc).__name__})", 0.0)
            return  # generic JSON that is not joint states
        record = records[0] if records else None
        if decoder.kind == "joint_states" and not (
                isinstance(record, JointStateRecord) and len(record.positions)):
            if (enc, name) in DECODERS:
                self.found[channel.id] = (decoder.kind, "", "no joints", 0.0)
            return
        self.found[channel.id] = (decoder.kind, *_frame_and_detail(record))


def _frame_and_detail(record: Any) -> tuple[str, str, float]:
    """A first message's frame id, detail and stereo baseline (m, `ChannelInfo`)."""
    if isinstance(record, ImageRecord):
        if record.width:
            return record.frame_id, f"{record.width}x{record.height} {record.format}", 0.0
        return record.frame_id, record.format, 0.0
    if isinstance(record, CameraInfoRecord):
        detail = f"{record.width}x{record.height} {record.distortion_model}"
        baseline = 0.0
        if record.R is not None and record.P is not None:
            try:
                offset = rectified_rig_pose(record.R, record.P)[:3, 3]
            except GeometryError:  # a non-finite calibration: no baseline shown
                offset = np.zeros(3)
            baseline = float(np.linalg.norm(offset))
        if baseline > 0:
            detail += f", stereo baseline {baseline * 1e3:.1f} mm"
        return record.frame_id, detail, baseline
    if isinstance(record, PoseRecord):
        return record.frame_id, f"in {record.frame_id}" if record.frame_id else "", 0.0
    if isinstance(record, JointStateRecord):
        return "", f"{len(record.positions)} joints", 0.0
    return "", "", 0.0


def _scan_file(path: Path, time_source: str) -> tuple[LogScan, TransformLog, dict]:
    """One file: its scan, its transforms, and the first messages' {channel id: (kind,
    frame, detail)}. Raises InputError when it is not MCAP or a transform does not decode."""
    transforms = TransformCollector(path, use_log_time=time_source == "log_time")
    firsts = _FirstMessages()

    def select(channel: Channel, schema: Schema | None) -> str:
        if transforms.select(channel, schema) == ALL:
            return ALL
        return firsts.select(channel, schema)

    def on_message(channel: Channel, schema: Schema | None, message: Message) -> None:
        if select(channel, schema) == ALL:
            transforms.add(channel, schema, message)
        else:
            firsts.add(channel, schema, message)

    scan = scan_mcap(path, select, on_message)
    return scan, transforms.result(scan), firsts.found


class _Merged:
    """One channel's statistics summed over the files."""

    def __init__(self, c: ChannelScan) -> None:
        self.c = c
        self.count, self.first_ns, self.last_ns = 0, -1, -1
        self.kind, self.frame_id, self.detail, self.baseline = "", "", "", 0.0
        self.transforms: int | None = None  # None: not a transform channel
        self.static = False
        self.child_frames: set[str] = set()

    def add(self, c: ChannelScan, first: tuple[str, str, str, float] | None,
            tf_log: TransformLog) -> None:
        if c.count:
            self.first_ns = c.first_log_ns if self.first_ns < 0 else min(self.first_ns,
                                                                         c.first_log_ns)
            self.last_ns = max(self.last_ns, c.last_log_ns)
        self.count += c.count
        if c.topic in tf_log.topics and find_decoder(c.message_encoding, c.schema_name,
                                                     ("transforms",)):
            self.transforms = (self.transforms or 0) + tf_log.counts.get(c.topic, 0)
            self.static = self.static or is_static_channel(c.topic, c.metadata)
            self.child_frames.update(tf_log.child_frames.get(c.topic, ()))
        elif first is not None and not self.kind:
            self.kind, self.frame_id, self.detail, self.baseline = first

    def info(self) -> ChannelInfo:
        c = self.c
        rate = mean_rate_hz(self.count, self.first_ns, self.last_ns)
        if self.transforms is not None:
            frames = tuple(sorted(self.child_frames))
            detail = (f"{self.transforms} transforms, {len(frames)} child frames"
                      + (", static" if self.static else ""))
            return ChannelInfo(c.topic, c.schema_name, c.message_encoding, "transforms",
                               self.count, self.first_ns, self.last_ns, rate, "", detail,
                               self.static, frames)
        return ChannelInfo(c.topic, c.schema_name, c.message_encoding, self.kind, self.count,
                           self.first_ns, self.last_ns, rate, self.frame_id, self.detail,
                           stereo_baseline_m=self.baseline)


def scan_channels(files: Sequence[Path], time_source: str = "header") -> ChannelScanResult:
    """Scan every file in order (see the module docstring). Damage does not raise: what was
    read before it is described and the file's `damage` says where it is. Raises InputError
    when a file is not MCAP or a transform message does not decode."""
    merged: dict[tuple[str, str, str], _Merged] = {}
    file_infos, samples, tf_topics = [], [], {}
    profile = library = ""
    for k, path in enumerate(files):
        scan, tf_log, firsts = _scan_file(Path(path), time_source)
        if k == 0:
            profile, library = scan.profile, scan.library
        for c in scan.channels:
            key = (c.topic, c.schema_name, c.message_encoding)
            merged.setdefault(key, _Merged(c)).add(c, firsts.get(c.id), tf_log)
        samples.append(tf_log.samples)
        tf_topics.update(dict.fromkeys(tf_log.topics))
        counted = [c for c in scan.channels if c.count]
        file_infos.append(FileInfo(
            Path(path), scan.size, scan.message_count,
            min((c.first_log_ns for c in counted), default=-1),
            max((c.last_log_ns for c in counted), default=-1), scan.indexed, scan.damage))
    return ChannelScanResult(profile, library, tuple(file_infos),
                             tuple(m.info() for m in merged.values()), concat_samples(samples),
                             tuple(tf_topics))
