"""Gaps and duplicates in a `foxglove.CompressedVideo` stream, found before decoding.

A lost message silently damages every later frame of its topic up to the next keyframe:
the decoder predicts them from a picture it never saw (FFmpeg conceals, flags nothing).
CompressedVideo carries no frame counter, so `StreamCheck` uses what the stream itself says:

- H.264: the slice header's `frame_num`, which steps by one (mod MaxFrameNum) after every
  reference picture and restarts at 0 on an IDR picture. A picture whose `frame_num` is
  neither the previous reference picture's nor the next one follows a lost reference
  picture (unless the SPS allows gaps). Parsed from the SPS/PPS the keyframes carry.
- H.265 (no frame counter in the slice header before its picture order count, which
  encoders need not step by one), and H.264 streams whose headers cannot be read: the
  stamps. A stamp step above `GAP_FACTOR` times the median of the last `PERIOD_WINDOW`
  steps is a lost message (not judged before the stream's fourth message).
- Both: a message whose payload and stamp repeat one of the last `DUPLICATE_WINDOW`
  messages' is a duplicate; it is not decoded (decoding it twice shifts the decoder's
  references). (Payloads alone may repeat: a still scene can encode to the same bytes.)

Frames from a gap up to the next keyframe are *damaged*: decoded against a missing
reference. (Not detected: an H.264 `memory_management_control_operation` 5, which resets
`frame_num` without an IDR picture; no common encoder emits it mid-stream.)
"""

from __future__ import annotations

import hashlib
from collections import deque
from dataclasses import dataclass, field

import numpy as np

GAP_FACTOR = 1.5
"""Stamp-based gaps: a step above this many median steps is a lost message."""
DUPLICATE_WINDOW = 16
"""Payloads remembered for duplicate detection (the decoded picture buffer's size)."""
PERIOD_WINDOW = 32
"""Stamp steps whose median is the stream's period (the stamp-based check)."""
_SLICE_HEADER_BYTES = 64
_HIGH_PROFILES = (100, 110, 122, 244, 44, 83, 86, 118, 128, 138, 139, 134, 135)


class _Bits:
    """Exp-Golomb bit reader over an RBSP (emulation prevention bytes removed)."""

    def __init__(self, nal: bytes) -> None:
        rbsp = nal.replace(b"\x00\x00\x03", b"\x00\x00")
        self.value = int.from_bytes(rbsp, "big")
        self.size = 8 * len(rbsp)
        self.pos = 0

    def u(self, n: int) -> int:
        if self.pos + n > self.size:
            raise ValueError("truncated header")
        self.pos += n
        return (self.value >> (self.size - self.pos)) & ((1 << n) - 1)

    def ue(self) -> int:
        zeros = 0
        while self.u(1) == 0:
            zeros += 1
            if zeros > 31:
                raise ValueError("bad Exp-Golomb code")
        return (1 << zeros) - 1 + self.u(zeros)

    def se(self) -> int:
        k = self.ue()
        return (k + 1) // 2 if k % 2 else -(k // 2)


@dataclass(frozen=True)
class _Sps:
    log2_max_frame_num: int
    separate_colour_plane: bool
    gaps_allowed: bool


def _skip_scaling_list(bits: _Bits, size: int) -> None:
    last = nxt = 8
    for _ in range(size):
        if nxt:
            nxt = (last + bits.se() + 256) % 256
        last = nxt or last


def _sps(nal: bytes) -> tuple[int, _Sps]:
    """(sps id, fields) of an H.264 SPS NAL unit (7.3.2.1.1)."""
    bits = _Bits(nal[1:])
    profile = bits.u(8)
    bits.u(16)  # constraint flags, level
    sps_id = bits.ue()
    separate = False
    if profile in _HIGH_PROFILES:
        chroma = bits.ue()
        if chroma == 3:
            separate = bool(bits.u(1))
        bits.ue(), bits.ue(), bits.u(1)  # bit depths, transform bypass
        if bits.u(1):  # seq_scaling_matrix_present_flag
            for i in range(12 if chroma == 3 else 8):
                if bits.u(1):
                    _skip_scaling_list(bits, 16 if i < 6 else 64)
    log2_max_frame_num = bits.ue() + 4
    poc_type = bits.ue()
    if poc_type == 0:
        bits.ue()
    elif poc_type == 1:
        bits.u(1), bits.se(), bits.se()
        for _ in range(bits.ue()):
            bits.se()
    bits.ue()  # max_num_ref_frames
    return sps_id, _Sps(log2_max_frame_num, separate, bool(bits.u(1)))


@dataclass
class H264FrameNumbers:
    """`frame_num` continuity of an H.264 stream, one access unit at a time."""

    sps: dict[int, _Sps] = field(default_factory=dict)
    pps: dict[int, int] = field(default_factory=dict)  # pps id -> sps id
    previous: int | None = None  # frame_num of the last reference picture

    def check(self, units: list[bytes]) -> tuple[int, int] | None:
        """(expected, found) frame_num when this access unit (its NAL units, start codes
        removed) follows a lost reference picture; None when it does not, or when its
        headers cannot be read."""
        try:
            return self._check(units)
        except (ValueError, KeyError):
            return None

    def _check(self, units: list[bytes]) -> tuple[int, int] | None:
        for nal in units:
            kind = nal[0] & 0x1F
            if kind == 7:
                sps_id, sps = _sps(nal)
                self.sps[sps_id] = sps
            elif kind == 8:
                bits = _Bits(nal[1:])
                pps_id = bits.ue()
                self.pps[pps_id] = bits.ue()
            elif kind in (1, 5):
                return self._slice(nal, kind == 5)
        return None

    def _slice(self, nal: bytes, idr: bool) -> tuple[int, int] | None:
        bits = _Bits(nal[1:_SLICE_HEADER_BYTES])  # (frame_num is in its first bytes)
        bits.ue(), bits.ue()  # first_mb_in_slice, slice_type
        sps = self.sps[self.pps[bits.ue()]]
        if sps.separate_colour_plane:
            bits.u(2)
        frame_num = bits.u(sps.log2_max_frame_num)
        previous, reference = self.previous, bool(nal[0] & 0x60)
        if reference:
            self.previous = frame_num
        if idr or previous is None or sps.gaps_allowed:
            return None
        expected = (previous + 1) % (1 << sps.log2_max_frame_num)
        return None if frame_num in (previous, expected) else (expected, frame_num)


def nal_units(data: bytes) -> list[bytes]:
    """The NAL units of an Annex B access unit (start codes 00 00 01 / 00 00 00 01)."""
    starts = []
    pos = data.find(b"\x00\x00\x01")
    while pos >= 0:
        starts.append(pos + 3)
        pos = data.find(b"\x00\x00\x01", pos + 3)
    ends = [s - 3 for s in starts[1:]] + [len(data)]
    return [data[s:e].rstrip(b"\x00") or b"\x00" for s, e in zip(starts, ends, strict=True)
            if s < len(data)]


@dataclass
class VideoProblem:
    """One problem of a video stream: `kind` "gap" (a lost message before `stamp_ns`) or
    "duplicate" (the message at `stamp_ns` repeats an earlier one and was not decoded);
    `detail` says how it was found; `damaged` the stamps (ns) of the messages after a gap
    up to the next keyframe, whose frames would be decoded against the missing reference."""

    kind: str
    stamp_ns: int
    detail: str
    damaged: list[int] = field(default_factory=list)


class StreamCheck:
    """Checks one topic's messages in log order (see the module docstring).

    `admit(stamp_ns, data, keyframe)` before decoding each message: None for a duplicate
    (do not decode it), else whether the message's frame is damaged. `problems` lists
    what was found so far.
    """

    def __init__(self, fmt: str) -> None:
        self.numbers = H264FrameNumbers() if fmt == "h264" else None
        self.recent: deque[bytes] = deque(maxlen=DUPLICATE_WINDOW)  # payload + stamp digests
        self.steps: deque[int] = deque(maxlen=PERIOD_WINDOW)  # recent positive stamp steps
        self.last_stamp: int | None = None
        self.problems: list[VideoProblem] = []
        self.gap: VideoProblem | None = None  # the gap whose damage lasts until a keyframe

    def admit(self, stamp_ns: int, data: bytes, keyframe: bool) -> bool | None:
        stamp = int(stamp_ns)
        hashed = hashlib.blake2b(data, digest_size=16)
        hashed.update(stamp.to_bytes(8, "little", signed=True))
        digest = hashed.digest()
        if digest in self.recent:
            self.problems.append(VideoProblem("duplicate", stamp,
                                              "same payload and stamp as an earlier message"))
            return None
        self.recent.append(digest)
        lost = self._lost(stamp, data)
        if keyframe:
            self.gap = None
        elif lost is not None:
            self.gap = VideoProblem("gap", stamp, lost)
            self.problems.append(self.gap)
        if self.gap is not None:
            self.gap.damaged.append(stamp)
        return self.gap is not None

    def _lost(self, stamp: int, data: bytes) -> str | None:
        """How a message lost before this one shows, None if none did."""
        if self.numbers is not None:
            lost = self.numbers.check(nal_units(data))
            if lost is not None:
                return f"h264 frame_num {lost[1]}, expected {lost[0]}"
            if self.numbers.previous is not None:
                return None  # numbered stream: the stamps are not needed
        previous, self.last_stamp = self.last_stamp, stamp
        if previous is None or stamp <= previous:
            return None
        step = stamp - previous
        period = float(np.median(self.steps)) if len(self.steps) >= 3 else None
        self.steps.append(step)
        if period is None or step <= GAP_FACTOR * period:
            return None
        return f"stamp step {step / 1e6:g} ms, the stream's is {period / 1e6:g} ms"
