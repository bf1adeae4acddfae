"""What every encoding adapter provides: a deserializer (bytes -> native message) per message
encoding, and converters (native message -> encoding-neutral records) per schema name.

Converters leave `stamp_ns` at 0 when a message has no stamp (or a zero one); the reader then
uses the record's log time.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from mcap.records import Schema

from ..records import Record

KINDS = ("image", "camera_info", "pose", "transforms", "joint_states")
"""What a schema carries; a topic role accepts some kinds (see `topics.ROLE_KINDS`)."""

Convert = Callable[[Any], list[Record]]


def rectification(r: Any, p: Any) -> tuple[np.ndarray | None, np.ndarray | None]:
    """A camera calibration message's R (3, 3) and P (3, 4) when it has them (9 and 12
    numbers, P's focal lengths set), else None each (ROS CameraInfo, Foxglove
    CameraCalibration)."""
    R = None if r is None else np.asarray(list(r), dtype=float).ravel()
    P = None if p is None else np.asarray(list(p), dtype=float).ravel()
    if R is None or P is None or R.size != 9 or P.size != 12 or not (P[0] and P[5]):
        return None, None
    return R.reshape(3, 3), P.reshape(3, 4)


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
