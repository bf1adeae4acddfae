"""Seeded mutations of tiny MCAP logs for tests/test_fuzz.py.

Base logs come from tests/synth_log.py (2 cameras, 64x48 px, 3 frames; every encoding; PNG,
JPEG and raw images; poses as PoseStamped or transforms). Families:
- byte level (`byte_mutation`): truncation, flipped bytes (in chunks, anywhere, in the
  summary), inflated record lengths, chunk fields and string lengths, a corrupt footer, zstd
  chunks that lie about their size (`real_zstd_bomb`: one that truly inflates to 1.5 GiB);
- inside chunks (`chunk_mutation`, recompressed with valid CRCs so that the parsers behind
  the CRC check see them): inner record and string lengths, missing / unknown schemas, wrong
  schema names and encodings, corrupt schema and message bytes, inflated sequence lengths,
  unknown channels, duplicated and reordered records;
- message level (`message_mutation`, records changed before writing): NaN and zero-norm
  quaternions, non-finite positions, zero-size images, a raw image claiming 60000x60000 px,
  PNG/JPEG headers claiming huge sizes, corrupt image bytes, duplicated, out-of-order and odd
  stamps, wrong record types on a topic, bad intrinsics, joint states and raw encodings, a
  missing topic; an empty first joint state, a JPEG with stray bytes before its size
  marker, NaN / second parent / cycle / self-transform on TF frames nobody uses, negative
  stamps, frame ids of 100 kB (issue 25).
"""

from __future__ import annotations

import dataclasses
import io
import random
import struct
import zlib
from pathlib import Path

import numpy as np
import synth_log
import zstandard
from synth_log import SynthSpec

from surgrecon_cli.io.logs.records import (
    CameraInfoRecord,
    ImageRecord,
    JointStateRecord,
    PoseRecord,
)

MAGIC = b"\x89MCAP0\r\n"
OP_FOOTER, OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_CHUNK, OP_DATA_END = 0x02, 3, 4, 5, 6, 0x0F
ENCODINGS = ("ros2", "ros1", "foxglove-protobuf", "foxglove-json")
BIG = (1 << 31, (1 << 32) - 1, 1 << 40, (1 << 63) - 1, (1 << 64) - 1)
TF_CONFIG = ('[topics]\ncamera_pose = "/tf"\ncamera_frame = "endoscope_{camera}_optical"\n'
             'tool_pose = "/tf"\ntool_frame = "raven_tool_tip"\n')


def _u64(data: bytes | bytearray, pos: int) -> int:
    return struct.unpack_from("<Q", data, pos)[0]


def top_records(data: bytes) -> list[tuple[int, int, int]]:
    """(offset, opcode, body length) of every top-level record up to the footer."""
    out, pos = [], len(MAGIC)
    while pos + 9 <= len(data) - len(MAGIC):
        opcode, length = data[pos], _u64(data, pos + 1)
        out.append((pos, opcode, length))
        if opcode == OP_FOOTER:
            break
        pos += 9 + length
    return out


@dataclasses.dataclass
class ChunkView:
    """Fields of a Chunk record at `offset` (body = offset + 9)."""

    offset: int
    start: int
    end: int
    usize: int
    crc: int
    compression: bytes
    data: bytes

    @classmethod
    def parse(cls, data: bytes, offset: int) -> ChunkView:
        b = offset + 9
        start, end, usize = struct.unpack_from("<QQQ", data, b)
        crc, clen = struct.unpack_from("<II", data, b + 24)
        comp = data[b + 32: b + 32 + clen]
        dlen = _u64(data, b + 32 + clen)
        body = data[b + 40 + clen: b + 40 + clen + dlen]
        return cls(offset, start, end, usize, crc, comp, body)

    def records(self) -> bytes:
        if self.compression == b"zstd":
            return zstandard.ZstdDecompressor().decompress(self.data)
        return self.data

    @staticmethod
    def build(start: int, end: int, inner: bytes, usize: int | None = None,
              crc: int | None = None, compressed: bytes | None = None) -> bytes:
        comp = zstandard.ZstdCompressor(level=1).compress(inner) if compressed is None \
            else compressed
        body = struct.pack("<QQQII", start, end, len(inner) if usize is None else usize,
                           zlib.crc32(inner) if crc is None else crc, 4) + b"zstd"
        body += struct.pack("<Q", len(comp)) + comp
        return bytes([OP_CHUNK]) + struct.pack("<Q", len(body)) + body


def inner_records(inner: bytes) -> list[tuple[int, int, bytes]]:
    """(opcode, declared length, body) of the records inside a chunk."""
    out, pos = [], 0
    while pos + 9 <= len(inner):
        opcode, length = inner[pos], _u64(inner, pos + 1)
        out.append((opcode, length, inner[pos + 9: pos + 9 + length]))
        pos += 9 + length
    return out


def pack_records(records: list[tuple[int, int, bytes]]) -> bytes:
    return b"".join(bytes([op]) + struct.pack("<Q", length) + body
                    for op, length, body in records)


def rebuild(data: bytes, chunks: dict[int, bytes]) -> bytes:
    """The log with the chunks at the given offsets replaced (or removed, b""), message
    indexes and the summary dropped (their offsets would be stale): header, chunks, DataEnd
    (no CRC), a footer without summary."""
    out = bytearray(MAGIC)
    for offset, opcode, length in top_records(data):
        if opcode == OP_DATA_END:
            break
        if offset in chunks:
            out += chunks[offset]
        elif opcode in (0x01, OP_CHUNK):
            out += data[offset: offset + 9 + length]
    out += bytes([OP_DATA_END]) + struct.pack("<QI", 4, 0)
    out += bytes([OP_FOOTER]) + struct.pack("<QQQI", 20, 0, 0, 0) + MAGIC
    return bytes(out)


# ============================================================================ base logs
@dataclasses.dataclass
class Base:
    name: str
    spec: SynthSpec
    encoding: str
    data: bytes
    config: str = ""


def base_spec(**changes) -> SynthSpec:
    return SynthSpec(cameras=(0, 1), frames=3, **changes)


def build_log(tmp: Path, spec: SynthSpec, encoding: str) -> bytes:
    path = tmp / "build.mcap"
    synth_log.write(path, spec, encoding, chunk_size=4096)
    return path.read_bytes()


def make_bases(tmp: Path) -> list[Base]:
    bases = []
    for encoding in ENCODINGS:
        for fmt in ("png", "rgb8"):
            spec = base_spec(image_format=fmt)
            bases.append(Base(f"{encoding}-{fmt}", spec, encoding, build_log(tmp, spec, encoding)))
    for encoding in ("ros2", "foxglove-json"):
        spec = base_spec(image_format="jpeg")
        bases.append(Base(f"{encoding}-jpeg", spec, encoding, build_log(tmp, spec, encoding)))
    spec = base_spec(tf_topic="/tf")
    for encoding in ("ros2", "foxglove-protobuf"):
        bases.append(Base(f"{encoding}-tf", spec, encoding, build_log(tmp, spec, encoding),
                          TF_CONFIG))
    return bases


# ============================================================================ byte level
def flip_bytes(data: bytearray, lo: int, hi: int, rng: random.Random, n: int) -> None:
    for _ in range(n):
        if hi > lo:
            data[rng.randrange(lo, hi)] ^= rng.choice((0x01, 0x80, 0xFF, rng.randrange(1, 256)))


def byte_mutation(base: Base, rng: random.Random, family: str) -> tuple[bytes, str]:
    """(mutated bytes, check for exit 0) for one byte-level family."""
    data = bytearray(base.data)
    recs = top_records(base.data)
    chunks = [r for r in recs if r[1] == OP_CHUNK]
    data_end = next(r[0] for r in recs if r[1] == OP_DATA_END)
    if family == "truncate":
        return bytes(data[: rng.randrange(0, len(data))]), "prefix"
    if family == "flip_chunk":
        offset, _, length = rng.choice(chunks)
        flip_bytes(data, offset + 9, offset + 9 + length, rng, rng.randint(1, 4))
        return bytes(data), "same"
    if family == "flip_any":
        flip_bytes(data, len(MAGIC), len(data), rng, rng.randint(1, 6))
        return bytes(data), "same"
    if family == "flip_summary":
        flip_bytes(data, data_end, len(data), rng, rng.randint(1, 6))
        return bytes(data), "same"
    if family == "record_length":
        offset, _, length = rng.choice(recs)
        value = rng.choice((*BIG, length + rng.randint(1, 64), len(data), len(data) * 3, 0))
        struct.pack_into("<Q", data, offset + 1, value)
        return bytes(data), "same"
    if family == "chunk_field":
        chunk = ChunkView.parse(base.data, rng.choice(chunks)[0])
        b = chunk.offset + 9
        field, fmt = rng.choice(((16, "<Q"), (24, "<I"), (28, "<I"),
                                 (32 + len(chunk.compression), "<Q")))
        value = rng.choice((*BIG, len(data))) & ((1 << (8 * struct.calcsize(fmt))) - 1)
        struct.pack_into(fmt, data, b + field, value)
        return bytes(data), "same"
    if family == "string_length":
        # a length prefix of a string in the Header or in the summary's Schema/Channel records
        offset, opcode, _ = rng.choice([r for r in recs if r[1] in (0x01, OP_SCHEMA, OP_CHANNEL)])
        pos = {0x01: 9, OP_SCHEMA: 11, OP_CHANNEL: 13}[opcode]
        struct.pack_into("<I", data, offset + pos, rng.choice((*BIG[:2], 1 << 30, 70000)))
        return bytes(data), "same"
    if family == "footer":
        footer = next(r[0] for r in recs if r[1] == OP_FOOTER)
        value = rng.choice((0, 8, data_end, chunks[0][0], chunks[-1][0] + 17, len(data) - 5,
                            *BIG))
        struct.pack_into("<Q", data, footer + 9 + rng.choice((0, 8)), value)
        return bytes(data), "same"
    if family == "zstd_bomb":
        chunk = ChunkView.parse(base.data, rng.choice(chunks)[0])
        inner = chunk.records()
        kind = rng.choice(("no_content_size", "content_size_lies"))
        if kind == "no_content_size":
            comp = zstandard.ZstdCompressor(level=1, write_content_size=False).compress(inner)
            new = ChunkView.build(chunk.start, chunk.end, inner, usize=rng.choice(BIG[1:4]),
                                  compressed=comp)
        else:
            new = ChunkView.build(chunk.start, chunk.end, inner, usize=len(inner) // 2)
        return rebuild(base.data, {chunk.offset: new}), "same"
    raise ValueError(family)


BYTE_FAMILIES = ("truncate", "flip_chunk", "flip_any", "flip_summary", "record_length",
                 "chunk_field", "string_length", "footer", "zstd_bomb")


def real_zstd_bomb(base: Base) -> bytes:
    """A chunk that truthfully decompresses to 1.5 GiB (zeros after the real records)."""
    chunk = ChunkView.parse(base.data, next(r[0] for r in top_records(base.data)
                                            if r[1] == OP_CHUNK))
    inner = chunk.records()
    total = len(inner) + (3 << 29)
    sink = io.BytesIO()
    cctx = zstandard.ZstdCompressor(level=1)
    with cctx.stream_writer(sink, size=total, closefd=False) as w:
        w.write(inner)
        zeros = bytes(1 << 24)
        for _ in range((3 << 29) // len(zeros)):
            w.write(zeros)
    new = ChunkView.build(chunk.start, chunk.end, b"", usize=total, crc=0,
                          compressed=sink.getvalue())
    return rebuild(base.data, {chunk.offset: new})


# ============================================================================ inside chunks
def _mutate_string(body: bytes, pos: int, rng: random.Random) -> bytes:
    b = bytearray(body)
    if pos + 4 <= len(b):
        struct.pack_into("<I", b, pos, rng.choice((*BIG[:2], 1 << 30, len(body) + 1, 0)))
    return bytes(b)


def chunk_mutation(base: Base, rng: random.Random, family: str) -> bytes:
    """Mutate the records inside one chunk, recompress with a valid CRC, rebuild the log."""
    chunk_offsets = [r[0] for r in top_records(base.data) if r[1] == OP_CHUNK]
    views = [ChunkView.parse(base.data, o) for o in chunk_offsets]
    needs = {"inner_string": (OP_SCHEMA, OP_CHANNEL), "schema_id": (OP_CHANNEL,),
             "schema_name": (OP_SCHEMA, OP_CHANNEL), "schema_data": (OP_SCHEMA,)}.get(
        family, (OP_MESSAGE,))
    views = [v for v in views if any(op in needs for op, _, _ in inner_records(v.records()))]
    chunk = rng.choice(views)
    recs = inner_records(chunk.records())
    idx = {op: [i for i, r in enumerate(recs) if r[0] == op]
           for op in (OP_SCHEMA, OP_CHANNEL, OP_MESSAGE)}
    if family == "inner_length":
        i = rng.randrange(len(recs))
        op, _, body = recs[i]
        recs[i] = (op, rng.choice((*BIG, len(body) + rng.randint(1, 99), 0, 3)), body)
    elif family == "inner_string":
        i = rng.choice(idx[OP_SCHEMA] + idx[OP_CHANNEL])
        op, length, body = recs[i]
        if op == OP_SCHEMA:
            name_len = struct.unpack_from("<I", body, 2)[0]
            pos = rng.choice((2, 6 + name_len))
        else:
            topic_len = struct.unpack_from("<I", body, 4)[0]
            pos = rng.choice((4, 8 + topic_len))
        recs[i] = (op, length, _mutate_string(body, pos, rng))
    elif family == "schema_id":
        i = rng.choice(idx[OP_CHANNEL])
        op, length, body = recs[i]
        recs[i] = (op, length, body[:2] + struct.pack("<H", rng.choice((0, 999))) + body[4:])
    elif family == "schema_name":
        i = rng.choice(idx[OP_SCHEMA] or idx[OP_CHANNEL])
        op, _, body = recs[i]
        if op == OP_SCHEMA:
            name_len = struct.unpack_from("<I", body, 2)[0]
            name = rng.choice((b"sensor_msgs/msg/JointState", b"foxglove.RawImage",
                               b"geometry_msgs/msg/PoseStamped", b"", b"nonsense/Type",
                               b"\xff\xfe"))
            body = body[:2] + struct.pack("<I", len(name)) + name + body[6 + name_len:]
        else:  # change the message encoding of a channel
            topic_len = struct.unpack_from("<I", body, 4)[0]
            enc_len = struct.unpack_from("<I", body, 8 + topic_len)[0]
            enc = rng.choice((b"cdr", b"json", b"protobuf", b"ros1", b"flatbuffer", b""))
            body = (body[: 8 + topic_len] + struct.pack("<I", len(enc)) + enc
                    + body[12 + topic_len + enc_len:])
        recs[i] = (op, len(body), body)
    elif family == "schema_data":
        i = rng.choice(idx[OP_SCHEMA])
        op, _, body = recs[i]
        b = bytearray(body)
        name_len = struct.unpack_from("<I", b, 2)[0]
        enc_len = struct.unpack_from("<I", b, 6 + name_len)[0]
        start = 10 + name_len + enc_len + 4
        if rng.random() < 0.5 and len(b) > start:
            flip_bytes(b, start, len(b), rng, rng.randint(1, 8))
        else:
            b = b[: rng.randrange(start, len(b) + 1)]
            struct.pack_into("<I", b, start - 4, len(b) - start)
        recs[i] = (op, len(b), bytes(b))
    elif family == "message_data":
        i = rng.choice(idx[OP_MESSAGE])
        op, _, body = recs[i]
        b = bytearray(body)
        how = rng.choice(("flip", "cut", "grow", "empty"))
        if how == "flip":
            flip_bytes(b, 22, len(b), rng, rng.randint(1, 8))
        elif how == "cut":
            b = b[: rng.randrange(22, len(b) + 1)]
        elif how == "grow":
            b += bytes(rng.randrange(256) for _ in range(rng.randint(1, 64)))
        else:
            b = b[:22]
        recs[i] = (op, len(b), bytes(b))
    elif family == "inflate_count":
        # a small uint32 in a message payload (a sequence or string length in CDR / ROS 1)
        i = rng.choice(idx[OP_MESSAGE])
        op, length, body = recs[i]
        b = bytearray(body)
        small = [p for p in range(22, len(b) - 3) if 0 < struct.unpack_from("<I", b, p)[0] < 4096]
        if small:
            struct.pack_into("<I", b, rng.choice(small), rng.choice((*BIG[:2], 1 << 28, 1 << 20)))
        recs[i] = (op, length, bytes(b))
    elif family == "message_channel":
        i = rng.choice(idx[OP_MESSAGE])
        op, length, body = recs[i]
        recs[i] = (op, length, struct.pack("<H", rng.choice((0, 77, 65535))) + body[2:])
    elif family == "duplicate_records":
        for i in sorted(rng.sample(idx[OP_MESSAGE], min(3, len(idx[OP_MESSAGE]))), reverse=True):
            recs.insert(i, recs[i])
    elif family == "reorder_records":
        msgs = idx[OP_MESSAGE]
        shuffled = [recs[i] for i in msgs]
        rng.shuffle(shuffled)
        for i, r in zip(msgs, shuffled, strict=True):
            recs[i] = r
    else:
        raise ValueError(family)
    new = ChunkView.build(chunk.start, chunk.end, pack_records(recs))
    return rebuild(base.data, {chunk.offset: new})


CHUNK_FAMILIES = ("inner_length", "inner_string", "schema_id", "schema_name", "schema_data",
                  "message_data", "inflate_count", "message_channel", "duplicate_records",
                  "reorder_records")


# ============================================================================ message level
def _png_header(width: int, height: int) -> bytes:
    """A PNG whose IHDR claims width x height px (valid CRCs), with a tiny IDAT."""
    def chunk(kind: bytes, payload: bytes) -> bytes:
        return (struct.pack(">I", len(payload)) + kind + payload
                + struct.pack(">I", zlib.crc32(kind + payload)))
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr)
            + chunk(b"IDAT", zlib.compress(b"\x00" * 64)) + chunk(b"IEND", b""))


def _jpeg_header(width: int, height: int) -> bytes:
    """The start of a baseline JPEG whose SOF0 claims width x height px."""
    real = synth_log.encode(synth_log.image_rgb(0, 0), "jpeg")
    sof = real.find(b"\xff\xc0")
    return real[: sof + 5] + struct.pack(">HH", height, width) + real[sof + 9:]


def _pick(messages: list, rng: random.Random, kind: type, k: int = 1) -> list[int]:
    found = [i for i, m in enumerate(messages) if isinstance(m[2], kind)]
    return rng.sample(found, min(k, len(found)))


def message_mutation(family: str, rng: random.Random):
    """A SynthSpec.mutate function for one message-level family, and the expected exit."""
    expect = "any"

    def replace(messages, kind, k=1, **changes):
        for i in _pick(messages, rng, kind, k):
            topic, t, rec = messages[i]
            fields = {key: (v(rec) if callable(v) else v) for key, v in changes.items()}
            messages[i] = (topic, t, dataclasses.replace(rec, **fields))
        return messages

    if family == "nan_quaternion":
        expect = "2"
        q = rng.choice(([np.nan, 0, 0, 1], [0, 0, 0, np.nan], [np.inf, 0, 0, 1]))
        fn = lambda m: replace(m, PoseRecord, orientation=np.array(q, float))  # noqa: E731
    elif family == "zero_quaternion":
        expect = "2"
        fn = lambda m: replace(m, PoseRecord, orientation=np.zeros(4))  # noqa: E731
    elif family == "nan_position":
        expect = "2"
        fn = lambda m: replace(m, PoseRecord,  # noqa: E731
                               position=np.array([np.nan, 1e308 * 10, 0.0]))
    elif family == "zero_size_image":
        expect = "2"
        changes = rng.choice(({"data": b""}, {"format": "rgb8", "width": 0, "height": 0,
                                              "step": 0, "data": b""},
                              {"format": "rgb8", "width": 64, "height": 0, "step": 192},
                              {"data": _png_header(0, 0)}))
        fn = lambda m: replace(m, ImageRecord, **changes)  # noqa: E731
    elif family == "huge_raw_image":
        expect = "2"
        step = rng.choice((180000, 0, 1 << 31))
        fmt = rng.choice(("rgb8", "mono16", "bgra8"))
        fn = lambda m: replace(m, ImageRecord, format=fmt, width=60000,  # noqa: E731
                               height=60000, step=step)
    elif family == "huge_compressed_image":
        expect = "2"
        w, h = rng.choice(((60000, 60000), (30000, 30000), (20000, 20000), (1 << 31, 1)))
        data = _png_header(w, h) if rng.random() < 0.5 else _jpeg_header(min(w, 65535),
                                                                         min(h, 65535))
        fn = lambda m: replace(m, ImageRecord, format="png", data=data,  # noqa: E731
                               width=0, height=0, step=0)
    elif family == "corrupt_image":
        def corrupt(rec):
            b = bytearray(rec.data)
            flip_bytes(b, len(b) // 4, len(b), rng, rng.randint(1, 6))
            return bytes(b[: rng.choice((len(b), len(b) - 7, len(b) // 2))])
        fn = lambda m: replace(m, ImageRecord, k=2, data=corrupt)  # noqa: E731
    elif family == "duplicate_stamps":
        def fn(messages):
            for i in _pick(messages, rng, rng.choice((ImageRecord, PoseRecord)), 3):
                messages.append(messages[i])
            return messages
    elif family == "out_of_order_stamps":
        def fn(messages):
            idx = _pick(messages, rng, rng.choice((ImageRecord, PoseRecord, JointStateRecord)),
                        4)
            stamps = [messages[i][2].stamp_ns for i in idx]
            rng.shuffle(stamps)
            for i, s in zip(idx, stamps, strict=True):
                topic, t, rec = messages[i]
                messages[i] = (topic, t, dataclasses.replace(rec, stamp_ns=s))
            return messages
    elif family == "odd_stamps":
        stamp = rng.choice((0, 1, synth_log.T0 + 10**15, (1 << 31) * 10**9 - 1))
        fn = lambda m: replace(m, rng.choice((ImageRecord, PoseRecord)),  # noqa: E731
                               k=2, stamp_ns=stamp)
    elif family == "wrong_type":
        def fn(messages):
            # every record on one topic replaced by a record of another role
            topic = rng.choice(sorted({m[0] for m in messages}))
            other = rng.choice([m[2] for m in messages if m[0] != topic])
            return [(t, lt, dataclasses.replace(other, stamp_ns=r.stamp_ns)
                     if t == topic else r) for t, lt, r in messages]
    elif family == "bad_intrinsics":
        changes = rng.choice(({"K": np.full((3, 3), np.nan)}, {"K": np.zeros((3, 3))},
                              {"K": np.ones(4)}, {"width": 0, "height": 0},
                              {"width": 60000, "height": 60000},
                              {"D": np.ones(14)}, {"D": np.array([np.nan] * 5)},
                              {"distortion_model": "equidistant"}))
        fn = lambda m: replace(m, CameraInfoRecord, k=2, **changes)  # noqa: E731
    elif family == "bad_joints":
        changes = rng.choice(({"positions": np.array([np.nan, np.inf, 0.0])},
                              {"positions": np.zeros(0)}, {"names": ()},
                              {"names": ("a",) * 3}, {"positions": np.zeros(7)}))
        fn = lambda m: replace(m, JointStateRecord, k=3, **changes)  # noqa: E731
    elif family == "bad_raw_image":
        changes = rng.choice(({"format": "32FC1", "width": 64, "height": 48, "step": 256},
                              {"format": "rgb8", "width": 64, "height": 48, "step": 10},
                              {"format": "rgb8", "width": 64, "height": 48, "step": 1 << 31},
                              {"format": "mono8", "width": 64, "height": 48, "step": 64},
                              {"format": "rgb8", "width": 1 << 31, "height": 1, "step": 0}))
        fn = lambda m: replace(m, ImageRecord, **changes)  # noqa: E731
    elif family == "empty_first_joint_state":  # ROS publishers send these before homing
        expect = "0"

        def fn(messages):
            joints = [i for i, m in enumerate(messages) if isinstance(m[2], JointStateRecord)]
            if joints:
                i = min(joints, key=lambda i: messages[i][1])
                topic, t, rec = messages[i]
                messages[i] = (topic, t, dataclasses.replace(rec, names=(),
                                                             positions=np.zeros(0)))
            return messages
    elif family == "stray_byte_jpeg":  # libjpeg skips stray bytes before a marker
        expect = "2"
        side = rng.choice((20000, 30000, 65535))
        header = _jpeg_header(side, side)
        sof = header.find(b"\xff\xc0")
        stray = bytes(rng.choice(range(255)) for _ in range(rng.randint(1, 3)))
        data = header[:sof] + stray + rng.choice((b"", b"\xff\xff")) + header[sof:]
        fn = lambda m: replace(m, ImageRecord, format="jpeg", data=data,  # noqa: E731
                               width=0, height=0, step=0)
    elif family == "tf_unused_frame_problem":  # tf2 only warns about frames nobody uses
        expect = "0"
        kind = rng.choice(("nan", "two_parents", "cycle", "self"))
        pairs = {"nan": [("world", "probe")], "two_parents": [("world", "arm"), ("map", "arm")],
                 "cycle": [("ring_a", "ring_b"), ("ring_b", "ring_a")],
                 "self": [("hand", "hand")]}[kind]
        xyz = np.array([np.nan, 0, 0]) if kind == "nan" else np.zeros(3)

        def fn(messages):
            t = synth_log.T0 + 5 * synth_log.MS
            return messages + [("/tf", t, PoseRecord(t - synth_log.MS, parent, child, xyz,
                                                     np.array([0.0, 0, 0, 1])))
                               for parent, child in pairs]
    elif family == "negative_stamps":
        stamp = -rng.randint(1, 10**12)
        fn = lambda m: replace(m, rng.choice((ImageRecord, PoseRecord,  # noqa: E731
                                              JointStateRecord)), k=2, stamp_ns=stamp)
    elif family == "long_frame_id":  # echoed in errors: cut, never whole
        expect = "2"
        name = rng.choice(("f", "é", "\n")) * rng.choice((5000, 100_000))
        fn = lambda m: replace(m, PoseRecord, frame_id=name)  # noqa: E731
    elif family == "drop_topic":
        def fn(messages):
            topic = rng.choice(sorted({m[0] for m in messages}))
            return [m for m in messages if m[0] != topic]
    else:
        raise ValueError(family)
    return fn, expect


MESSAGE_FAMILIES = ("nan_quaternion", "zero_quaternion", "nan_position", "zero_size_image",
                    "huge_raw_image", "huge_compressed_image", "corrupt_image", "duplicate_stamps",
                    "out_of_order_stamps", "odd_stamps", "wrong_type", "bad_intrinsics",
                    "bad_joints", "bad_raw_image", "drop_topic", "empty_first_joint_state",
                    "stray_byte_jpeg", "tf_unused_frame_problem", "negative_stamps",
                    "long_frame_id")
