"""MCAP records read without trusting the lengths written in the file.

The `mcap` library reads a record's fields with `read(length)` for lengths taken from the
file, and Python allocates `length` bytes before reading; a chunk is decompressed to whatever
its zstd/lz4 frame claims. A corrupt length could thus ask for gigabytes. Here reads never
ask for more than the file has left, a chunk's uncompressed size is checked against
`MAX_CHUNK_BYTES` and against its frame before decompressing, and the summary section is read
without decompressing anything.
"""

from __future__ import annotations

import dataclasses
import io
from collections.abc import Callable, Iterator
from typing import IO, Any, Protocol, cast

import zstandard
from mcap.exceptions import McapError, UnsupportedCompressionError
from mcap.records import Channel, Chunk, Footer, McapRecord, Schema
from mcap.stream_reader import StreamReader, breakup_chunk

try:
    import lz4.frame as lz4_frame
except ImportError:  # optional, like in `mcap`
    lz4_frame = None

MAX_CHUNK_BYTES = 1 << 29
"""Largest uncompressed chunk read (512 MiB); recorders write chunks of a few MiB."""
_FOOTER_AND_MAGIC = 9 + 20 + 8


class Readable(Protocol):
    def read(self, n: int = -1, /) -> bytes: ...


def as_stream(f: Readable) -> IO[bytes]:
    """`f` typed as the `IO[bytes]` that mcap's StreamReader is annotated to take: it only ever
    calls `read(n)` on its input (through ReadDataStream), which is all `f` needs to have."""
    return cast("IO[bytes]", f)


class BoundedFile:
    """A seekable binary file whose `read(n)` asks for at most the bytes left before `size`."""

    def __init__(self, raw: IO[bytes], size: int) -> None:
        self.raw = raw
        self.size = size
        self.pos = raw.tell()

    def read(self, n: int | None = -1) -> bytes:
        left = max(self.size - self.pos, 0)
        data = self.raw.read(left if n is None or n < 0 else min(n, left))
        self.pos += len(data)
        return data

    def seek(self, offset: int, whence: int = io.SEEK_SET) -> int:
        self.pos = self.raw.seek(offset, whence)
        return self.pos

    def tell(self) -> int:
        return self.pos


def chunk_records(chunk: Chunk) -> list[McapRecord]:
    """The records inside a chunk (CRC checked), decompressing at most its declared size.

    Raises McapError when the declared size is over `MAX_CHUNK_BYTES` or disagrees with the
    compressed frame, zstandard.ZstdError / RuntimeError on corrupt compressed data, and what
    `mcap` raises on a CRC mismatch or malformed records.
    """
    size = chunk.uncompressed_size
    if size > MAX_CHUNK_BYTES:
        raise McapError(f"a chunk claims {size} bytes uncompressed, more than the "
                        f"{MAX_CHUNK_BYTES >> 20} MiB limit")
    if chunk.compression == "zstd":
        declared = zstandard.frame_content_size(chunk.data)
        if declared not in (-1, size):
            raise McapError(f"a chunk claims {size} bytes uncompressed, its zstd frame {declared}")
        data = zstandard.ZstdDecompressor().decompress(chunk.data, max_output_size=size)
    elif chunk.compression == "lz4":
        if lz4_frame is None:
            raise UnsupportedCompressionError("lz4")
        declared = lz4_frame.get_frame_info(chunk.data)["content_size"]
        if declared not in (0, size):
            raise McapError(f"a chunk claims {size} bytes uncompressed, its lz4 frame {declared}")
        data = lz4_frame.LZ4FrameDecompressor().decompress(chunk.data, max_length=size)
    elif chunk.compression == "":
        data = chunk.data
    else:
        raise UnsupportedCompressionError(chunk.compression)
    if len(data) != size:
        raise McapError(f"a chunk claims {size} bytes uncompressed but holds {len(data)}")
    return breakup_chunk(dataclasses.replace(chunk, compression="", data=data), validate_crc=True)


def expand_chunks(records: Iterator[McapRecord]) -> Iterator[McapRecord]:
    """Top-level records with each chunk replaced by its records (bounded decompression)."""
    for record in records:
        if isinstance(record, Chunk):
            yield from chunk_records(record)
        else:
            yield record


def read_summary(f: BoundedFile) -> tuple[dict[int, Schema], dict[int, Channel]] | None:
    """Schemas and channels of the summary section, or None if the file has none (or the
    footer points at something else). Raises what `mcap` raises on malformed records."""
    if f.size < 2 * _FOOTER_AND_MAGIC:
        return None
    f.seek(-_FOOTER_AND_MAGIC, io.SEEK_END)
    footer = next(StreamReader(as_stream(f), skip_magic=True, record_size_limit=f.size).records)
    if not isinstance(footer, Footer) or not 0 < footer.summary_start < f.size:
        return None
    f.seek(footer.summary_start)
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    reader = StreamReader(as_stream(f), skip_magic=True, emit_chunks=True,
                          record_size_limit=f.size)
    for record in reader.records:
        if isinstance(record, Schema):
            schemas[record.id] = record
        elif isinstance(record, Channel):
            channels[record.id] = record
        elif isinstance(record, Footer):
            return schemas, channels
        elif isinstance(record, Chunk):
            return None  # not a summary section
    return None


class TrackedFile:
    """File wrapper: SHA-256 and position of everything read, progress callback."""

    def __init__(self, raw: IO[bytes] | BoundedFile,
                 on_bytes: Callable[[int], None] | None, sha: Any) -> None:
        self.raw = raw
        self.on_bytes = on_bytes
        self.sha = sha  # one hash over the log's files in order
        self.pos = 0

    def read(self, n: int = -1) -> bytes:
        data = self.raw.read(n)
        self.sha.update(data)
        self.pos += len(data)
        if self.on_bytes is not None and data:
            self.on_bytes(len(data))
        return data

    def drain(self) -> None:
        while self.read(1 << 20):
            pass
