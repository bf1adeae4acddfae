"""What every encoding adapter provides: a deserializer (bytes -> native message) per message
encoding, and converters (native message -> encoding-neutral records) per schema name.

Converters leave `stamp_ns` at 0 when a message has no stamp (or a zero one); the reader then
uses the record's log time.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

from mcap.records import Schema

from ..records import Record

KINDS = ("image", "camera_info", "pose", "transforms", "joint_states")
"""What a schema carries; a topic role accepts some kinds (see `topics.ROLE_KINDS`)."""

Convert = Callable[[Any], list[Record]]


@dataclass(frozen=True)
class SchemaDecoder:
    """How one (message encoding, schema name) is turned into records."""

    kind: str
    convert: Convert


class Deserializer(Protocol):
    """Turns a channel's message bytes into native message objects, for one message encoding.

    `for_schema` is called once per channel and may cache per schema; the returned function
    raises any exception on malformed bytes (the reader names topic and log time).
    """

    message_encoding: str

    def for_schema(self, schema: Schema | None) -> Callable[[bytes], Any]: ...


def stamp_ns(sec: Any, nsec: Any) -> int:
    """Seconds + nanoseconds (either may be None) -> int nanoseconds."""
    return int(sec or 0) * 1_000_000_000 + int(nsec or 0)
