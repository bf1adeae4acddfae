"""Read a few channels of an MCAP log quickly: from the summary and indexes where they are
intact, by streaming the file otherwise.

With a summary (statistics, chunk indexes) and message indexes, per-channel message counts
and log-time spans come from the indexes without decompressing anything, and only the chunks
holding a selected channel's messages are decompressed. A file without them (recorder
crashed, unindexed writer) is streamed once from the start; damage there ends the scan and is
reported in `LogScan.damage` (the caller decides whether that is an error). Reads are bounded
by the file size and chunks decompressed with `bounded.chunk_records`, as in `reader`.
"""

from __future__ import annotations

import io
import struct
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from mcap.exceptions import McapError
from mcap.records import (
    Channel,
    Chunk,
    ChunkIndex,
    Footer,
    Header,
    Message,
    Schema,
    Statistics,
)
from mcap.stream_reader import StreamReader

from ...errors import InputError
from .bounded import BoundedFile, as_stream, chunk_records, expand_chunks
from .rosbag import bag_records, check_bag_magic, is_bag
from .stream import STREAM_ERRORS, RecordStream, one_line

MCAP_MAGIC = b"\x89MCAP0\r\n"
_FOOTER_AND_MAGIC = 9 + 20 + 8
_MESSAGE_INDEX_OPCODE = 0x07

SKIP, FIRST, ALL = "", "first", "all"
"""What `scan_mcap` delivers of a channel: nothing, its earliest message, every message."""

Select = Callable[[Channel, "Schema | None"], str]
OnMessage = Callable[[Channel, "Schema | None", Message], None]


@dataclass(frozen=True)
class ChannelScan:
    """One channel: message count and the log times (ns) of its first and last message
    (-1 when it has none)."""

    id: int
    topic: str
    schema_name: str
    schema_encoding: str
    message_encoding: str
    metadata: dict[str, str]
    count: int
    first_log_ns: int
    last_log_ns: int


@dataclass(frozen=True)
class LogScan:
    """What a scan found: header profile/library, channels (by id), whether the indexes were
    used, and `damage` (None, or one line saying where valid data ends)."""

    path: Path
    size: int
    profile: str
    library: str
    channels: tuple[ChannelScan, ...]
    indexed: bool
    damage: str | None = None
    schemas: dict[int, Schema] = field(default_factory=dict, repr=False)

    @property
    def message_count(self) -> int:
        return sum(c.count for c in self.channels)


_Chunks = list[tuple[ChunkIndex, dict[int, np.ndarray]]]
"""Chunk indexes in file order, each with the log times (ns) of each channel's messages."""


@dataclass
class _Summary:
    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    chunk_indexes: list[ChunkIndex] = field(default_factory=list)
    statistics: Statistics | None = None


def scan_mcap(path: Path, select: Select, on_message: OnMessage) -> LogScan:
    """Scan `path`: `select(channel, schema)` says per channel SKIP, FIRST or ALL, and
    `on_message(channel, schema, message)` receives those messages (in file order, not
    necessarily log-time order). Raises InputError when the file is not MCAP."""
    path = Path(path)
    size = path.stat().st_size
    if is_bag(path):
        check_bag_magic(path)
        profile = "ros1" if path.suffix == ".bag" else "ros2"
        return _scan_records(path, size, Header(profile, "rosbags"), bag_records(path),
                             lambda: size, select, on_message)
    with open(path, "rb") as raw:
        f = BoundedFile(raw, size)
        if f.read(len(MCAP_MAGIC)) != MCAP_MAGIC:
            raise InputError(f"{path}: not an MCAP file (it does not start with the MCAP magic "
                             "bytes); pass a .mcap log")
        header = _header(f)
        summary, chunks = None, None
        try:
            summary = _read_summary(f, size)
            if summary is not None:
                chunks = _plan(f, summary)
        except STREAM_ERRORS:
            chunks = None
        if summary is not None and chunks is not None:
            return _scan_indexed(path, f, header, summary, chunks, select, on_message)
        f.seek(0)
        records = StreamReader(as_stream(f), validate_crcs=True, emit_chunks=True,
                               record_size_limit=size).records
        return _scan_records(path, size, header, expand_chunks(records), lambda: f.pos, select,
                             on_message)


# -- indexed ---------------------------------------------------------------------------------
def _header(f: BoundedFile) -> Header:
    try:
        record = next(StreamReader(as_stream(f), skip_magic=True,
                                   record_size_limit=f.size).records)
    except (*STREAM_ERRORS, StopIteration):
        return Header("", "")
    return record if isinstance(record, Header) else Header("", "")


def _read_summary(f: BoundedFile, size: int) -> _Summary | None:
    """The summary section, or None without one (no footer, or summary_start 0)."""
    if size < len(MCAP_MAGIC) * 2 + _FOOTER_AND_MAGIC:
        return None
    f.seek(-_FOOTER_AND_MAGIC, io.SEEK_END)
    tail = StreamReader(as_stream(f), skip_magic=True, record_size_limit=size).records
    footer = next(tail)
    if not isinstance(footer, Footer) or not 0 < footer.summary_start < size:
        return None
    if f.read(len(MCAP_MAGIC)) != MCAP_MAGIC:
        return None
    f.seek(footer.summary_start)
    summary = _Summary()
    for record in StreamReader(as_stream(f), skip_magic=True, emit_chunks=True,
                               record_size_limit=size).records:
        if isinstance(record, Schema):
            summary.schemas[record.id] = record
        elif isinstance(record, Channel):
            summary.channels[record.id] = record
        elif isinstance(record, ChunkIndex):
            summary.chunk_indexes.append(record)
        elif isinstance(record, Statistics):
            summary.statistics = record
        elif isinstance(record, Footer):
            return summary
        elif isinstance(record, Chunk):
            return None
    return None


def _plan(f: BoundedFile, summary: _Summary) -> _Chunks | None:
    """Each chunk (in file order) with the log times of each channel's messages in it, from
    the message indexes; None when the indexes cannot account for every message (then the
    file is streamed)."""
    stats = summary.statistics
    if stats is None:
        return None
    chunks = []
    for ci in sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset):
        if not ci.message_index_offsets and ci.uncompressed_size > 0:
            return None
        per_channel = _message_index_times(f, ci)
        if not set(per_channel) <= set(summary.channels):
            return None
        chunks.append((ci, per_channel))
    indexed = sum(len(t) for _, per_channel in chunks for t in per_channel.values())
    if indexed != stats.message_count:
        return None  # messages outside chunks, or indexes out of step with the statistics
    return chunks


def _message_index_times(f: BoundedFile, ci: ChunkIndex) -> dict[int, np.ndarray]:
    """Log times (ns) of each channel's messages in one chunk, parsed from the raw message
    index records that follow it (opcode, uint64 length, uint16 channel, uint32 byte length,
    then (uint64 log time, uint64 offset) pairs)."""
    f.seek(ci.chunk_start_offset + ci.chunk_length)
    data = f.read(ci.message_index_length)
    if len(data) != ci.message_index_length:
        raise McapError("message index runs past the end of the file")
    out: dict[int, np.ndarray] = {}
    pos = 0
    while pos < len(data):
        if pos + 9 > len(data):
            raise McapError("truncated message index")
        opcode = data[pos]
        (length,) = struct.unpack_from("<Q", data, pos + 1)
        start, pos = pos + 9, pos + 9 + length
        if pos > len(data):
            raise McapError("truncated message index")
        if opcode != _MESSAGE_INDEX_OPCODE:
            continue
        channel_id, n_bytes = struct.unpack_from("<HI", data, start)
        if n_bytes % 16 or start + 6 + n_bytes > pos:
            raise McapError("malformed message index")
        pairs = np.frombuffer(data, dtype="<u8", count=n_bytes // 8, offset=start + 6)
        out[channel_id] = pairs[0::2].astype(np.int64)
    return out


def _scan_indexed(
    path: Path,
    f: BoundedFile,
    header: Header,
    summary: _Summary,
    chunks: _Chunks,
    select: Select,
    on_message: OnMessage,
) -> LogScan:
    counts: dict[int, int] = {}
    first: dict[int, int] = {}
    last: dict[int, int] = {}
    for _, per_channel in chunks:
        for cid, t in per_channel.items():
            if len(t):
                counts[cid] = counts.get(cid, 0) + len(t)
                first[cid] = min(first.get(cid, int(t[0])), int(t.min()))
                last[cid] = max(last.get(cid, int(t[0])), int(t.max()))
    modes = {cid: select(ch, summary.schemas.get(ch.schema_id))
             for cid, ch in summary.channels.items()}
    first_chunk: dict[int, int] = {}  # FIRST channels: the chunk holding the earliest message
    for k, (_, per_channel) in enumerate(chunks):
        for cid, t in per_channel.items():
            if modes[cid] == FIRST and cid not in first_chunk and len(t) and (
                    int(t.min()) == first[cid]):
                first_chunk[cid] = k
    damage = None
    delivered: set[int] = set()
    for k, (ci, per_channel) in enumerate(chunks):
        wanted = {cid for cid in per_channel if modes[cid] == ALL or first_chunk.get(cid) == k}
        if not wanted:
            continue
        try:
            records = _chunk_at(f, ci)
        except STREAM_ERRORS as exc:
            damage = (f"the chunk at byte {ci.chunk_start_offset} cannot be read "
                      f"({one_line(exc, 160)}); it and later chunks were not read")
            break
        for record in records:
            if not isinstance(record, Message) or record.channel_id not in wanted:
                continue
            cid = record.channel_id
            if modes[cid] == FIRST:
                if cid in delivered or record.log_time != first[cid]:
                    continue
                delivered.add(cid)
            ch = summary.channels[cid]
            on_message(ch, summary.schemas.get(ch.schema_id), record)
    channels = tuple(_channel_scan(ch, summary.schemas, counts.get(cid, 0), first.get(cid, -1),
                                   last.get(cid, -1))
                     for cid, ch in sorted(summary.channels.items()))
    return LogScan(path, f.size, header.profile, header.library, channels, True, damage,
                   summary.schemas)


def _chunk_at(f: BoundedFile, ci: ChunkIndex) -> list:
    f.seek(ci.chunk_start_offset)
    record = next(StreamReader(as_stream(f), skip_magic=True, emit_chunks=True,
                               record_size_limit=f.size).records)
    if not isinstance(record, Chunk):
        raise McapError(f"no chunk at byte {ci.chunk_start_offset}")
    return chunk_records(record)


# -- streaming -------------------------------------------------------------------------------
def _scan_records(path: Path, size: int, header: Header, records: Iterator, pos: Callable[[], int],
                  select: Select, on_message: OnMessage) -> LogScan:
    """Scan a file's records (MCAP streamed, or a bag's) in file order; `pos()` is the bytes
    read of its `size`."""
    stream = RecordStream(records, pos, through_data_end=False)
    modes: dict[int, str] = {}
    counts: dict[int, int] = {}
    first: dict[int, int] = {}
    last: dict[int, int] = {}
    for record in stream:
        if isinstance(record, Channel):
            modes[record.id] = select(record, stream.schemas.get(record.schema_id))
            continue
        cid = record.channel_id
        n = counts.get(cid, 0)
        counts[cid] = n + 1
        first[cid] = min(first.get(cid, record.log_time), record.log_time)
        last[cid] = max(last.get(cid, record.log_time), record.log_time)
        if modes[cid] == ALL or (modes[cid] == FIRST and n == 0):
            ch = stream.channels[cid]
            on_message(ch, stream.schemas.get(ch.schema_id), record)
    damage = None
    if stream.unknown_channel is not None:
        damage = (f"a message on unknown channel {stream.unknown_channel} at byte "
                  f"{stream.valid}; reading stopped")
    elif stream.error is not None:
        t = max(last.values(), default=None)
        when = f"log time {t / 1e9:.6f} s" if t is not None else "before any message"
        damage = (f"valid data ends at byte {stream.valid} of {size} ({when}): truncated or "
                  f"corrupt ({one_line(stream.error, 160)})")
    schemas, channels = stream.schemas, stream.channels
    out = tuple(_channel_scan(ch, schemas, counts.get(cid, 0), first.get(cid, -1),
                              last.get(cid, -1)) for cid, ch in sorted(channels.items()))
    return LogScan(path, size, header.profile, header.library, out, False, damage, schemas)


def _channel_scan(ch: Channel, schemas: dict[int, Schema], count: int, first: int,
                  last: int) -> ChannelScan:
    schema = schemas.get(ch.schema_id)
    return ChannelScan(ch.id, ch.topic, schema.name if schema else "",
                       schema.encoding if schema else "", ch.message_encoding,
                       dict(ch.metadata), count, first, last)

