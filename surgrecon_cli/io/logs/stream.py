"""The one loop over a log file's records in file order: a streamed MCAP file (chunks
expanded, io/logs/bounded.py) or a bag's records in the same form (io/logs/rosbag.py).
Both the reader (io/logs/reader.py, ingest) and the scan (io/logs/scan.py, `info`) walk a
file through `RecordStream`; each says in its own words what a stop means."""

from __future__ import annotations

import struct
from collections.abc import Callable, Iterator

import zstandard
from mcap.exceptions import McapError
from mcap.records import Channel, DataEnd, Footer, McapRecord, Message, Schema

# What a damaged or truncated file raises while its records are read (mcap's parser,
# zstd/lz4, struct unpacking, a record length past the end).
STREAM_ERRORS = (McapError, ValueError, struct.error, EOFError, OverflowError, MemoryError,
                 zstandard.ZstdError, RuntimeError, KeyError, IndexError)


class RecordStream:
    """Iterate a file's records: yields each channel once (when first declared, with the
    schemas declared so far in `schemas`) and each message of a declared channel.

    After the iteration: `valid` is the bytes read up to the end of the last whole record
    (`pos()` after it), `error` the exception that stopped the stream early, or
    `unknown_channel` the id of a message's undeclared channel that stopped it;
    `data_complete` once the data section ended (DataEnd), `footer` once the footer was
    read. `through_data_end=False` stops at the end of the data section."""

    def __init__(self, records: Iterator[McapRecord], pos: Callable[[], int],
                 through_data_end: bool = True) -> None:
        self._records = records
        self._pos = pos
        self._through_data_end = through_data_end
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        self.valid = 0
        self.error: BaseException | None = None
        self.unknown_channel: int | None = None
        self.data_complete = False
        self.footer = False

    def __iter__(self) -> Iterator[Channel | Message]:
        while True:
            try:
                record = next(self._records)
            except StopIteration:
                return
            except STREAM_ERRORS as exc:
                self.error = exc
                return
            self.valid = self._pos()
            if isinstance(record, Schema):
                self.schemas[record.id] = record
            elif isinstance(record, Channel):
                if record.id not in self.channels:
                    self.channels[record.id] = record
                    yield record
            elif isinstance(record, Message):
                if record.channel_id not in self.channels:
                    self.unknown_channel = record.channel_id
                    return
                yield record
            elif isinstance(record, DataEnd):
                self.data_complete = True
                if not self._through_data_end:
                    return
            elif isinstance(record, Footer):
                self.footer = True
                return


def one_line(exc: BaseException, limit: int = 200) -> str:
    """An exception's text on one line, at most `limit` characters (its type's name when
    it has no text)."""
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if len(text) <= limit else text[:limit - 3] + "..."
