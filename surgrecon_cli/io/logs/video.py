"""`foxglove.CompressedVideo` (H.264 / H.265, Annex B) -> one decoded image per message.

Foxglove's rules for the stream: each message holds the NAL units of exactly one frame, a
keyframe (H.264 IDR, H.265 IRAP) carries its parameter sets (SPS/PPS, VPS), and there are no
B-frames. One `VideoDecoder` per topic (the decoder is stateful) decodes with PyAV (FFmpeg),
an optional dependency imported only when a video topic is met: `pip install
"surgrecon[video]"`.

Frame-exact: every packet is tagged with its message's index on the topic and every decoded
frame is matched back by that tag, so a decoder that holds frames back (delay) or reorders
them (B-frames, outside Foxglove's rules) still gives each message its own image and stamp;
`flush` drains the decoder at the end of the log. A message after the first keyframe that
yields no frame (or a damaged one) is an error naming the topic and stamp, raised once the
decoder is `REORDER_LIMIT` frames past it or at the end; messages before the first keyframe
cannot be decoded and are skipped, with one warning per topic. Lost and duplicated messages
are found by `video_checks.StreamCheck`: duplicates are not decoded, and `problems` (after
`flush`) lists the gaps with the frames decoded against a missing reference.
"""

from __future__ import annotations

import logging
from collections import OrderedDict
from typing import Any

import cv2
import numpy as np

from ...core.sync.streams import fmt_stamp
from ...errors import InputError
from .images import MAX_IMAGE_PIXELS, StoredImage
from .records import ImageRecord
from .video_checks import StreamCheck, VideoProblem, nal_units

logger = logging.getLogger(__name__)

CODECS = {"h264": "h264", "h265": "hevc"}
"""CompressedVideo `format` -> FFmpeg decoder name."""
INSTALL_HINT = 'pip install "surgrecon[video]"'
REORDER_LIMIT = 16
"""Frames a decoder may hold back and reorder (H.264/H.265: at most the 16 of the decoded
picture buffer); a message this far behind the frames coming out has lost its frame."""


def import_av(topic: str, fmt: str) -> Any:
    """The `av` module, or a one-line InputError naming the topic and the install command."""
    try:
        import av
        import av.error
        import av.video.reformatter
    except ImportError:
        raise InputError(f"{topic}: foxglove.CompressedVideo ({fmt}) needs PyAV, which is not "
                         f"installed; {INSTALL_HINT}") from None
    return av


def nal_types(data: bytes, fmt: str) -> list[int]:
    """The NAL unit types of an Annex B access unit (start codes 00 00 01 / 00 00 00 01)."""
    return [u[0] & 0x1F if fmt == "h264" else (u[0] >> 1) & 0x3F for u in nal_units(data)]


def is_keyframe(data: bytes, fmt: str) -> bool:
    """Whether the access unit holds a keyframe: an H.264 IDR slice (type 5) or an H.265
    IRAP picture (types 16-23: BLA, IDR, CRA)."""
    types = nal_types(data, fmt)
    if fmt == "h264":
        return 5 in types
    return any(16 <= t <= 23 for t in types)


def _interpolation(av: Any) -> Any:
    """swscale flags for 4:2:0 -> RGB: chroma interpolated at full resolution with exact
    rounding (its default fast path is ~1.2 grey levels dark); None (the default) with a
    PyAV too old to pass flags."""
    flags = av.video.reformatter.Interpolation
    if not all(hasattr(flags, n) for n in ("ACCURATE_RND", "FULL_CHR_H_INT")):
        return None
    return flags.BILINEAR | flags.ACCURATE_RND | flags.FULL_CHR_H_INT


class VideoDecoder:
    """Decodes one topic's CompressedVideo messages, in log order; see the module docstring.

    `decode(record)` and `flush()` return `(stamp_ns, StoredImage)` pairs (PNG, lossless),
    in message order, for the frames that came out of the decoder; frames decoded against
    a missing reference (after a lost message, up to the next keyframe) are left out, and
    `problems` lists the lost and duplicated messages.
    """

    def __init__(self, topic: str, fmt: str) -> None:
        fmt = fmt.lower()
        if fmt not in CODECS:
            raise InputError(f"{topic}: CompressedVideo format {fmt!r} is not supported "
                             f"(supported: {', '.join(CODECS)})")
        self.av = import_av(topic, fmt)
        self.topic = topic
        self.format = fmt
        self.context = self.av.CodecContext.create(CODECS[fmt], "r")
        self.context.thread_count = 1  # frame threads would delay output; one is plenty
        self.interpolation = _interpolation(self.av)
        self.pending: OrderedDict[int, int] = OrderedDict()  # packet index -> stamp
        self.sent = 0
        self.skipped: list[int] = []  # stamps of messages before the first keyframe
        self.started = False
        self.check = StreamCheck(fmt)
        self.damaged: set[int] = set()  # packet indices decoded against a missing reference

    def decode(self, record: ImageRecord) -> list[tuple[int, StoredImage]]:
        if str(record.format).lower() != self.format:
            raise InputError(f"{self.topic}: video at stamp {fmt_stamp(record.stamp_ns)} is "
                             f"{record.format!r}, the topic started as {self.format!r}")
        data = bytes(record.data)
        if not data:  # (an empty packet would tell FFmpeg that the stream ends)
            raise InputError(f"{self.topic}: video message at stamp "
                             f"{fmt_stamp(record.stamp_ns)} is empty")
        keyframe = is_keyframe(data, self.format)
        if not self.started:
            if not keyframe:
                self.skipped.append(record.stamp_ns)
                return []
            self.started = True
            self._warn_skipped()
        damaged = self.check.admit(record.stamp_ns, data, keyframe)
        if damaged is None:  # a duplicate
            return []
        index = self.sent
        self.sent += 1
        if damaged:
            self.damaged.add(index)
        self.pending[index] = record.stamp_ns
        packet = self.av.Packet(data)
        packet.pts = index
        return self._frames(packet, record.stamp_ns)

    def flush(self) -> list[tuple[int, StoredImage]]:
        """Drain the decoder at the end of the topic; every sent message must have a frame."""
        if not self.started:
            if self.skipped:
                raise InputError(
                    f"{self.topic}: no keyframe in its {len(self.skipped)} video messages "
                    f"({self.format}: {'IDR' if self.format == 'h264' else 'IRAP'} picture "
                    "with its parameter sets), so none decodes")
            return []
        out = self._frames(None, None)
        for index in self.damaged.intersection(self.pending):
            del self.pending[index]
        if self.pending:
            stamp = next(iter(self.pending.values()))
            raise InputError(f"{self.topic}: video message at stamp {fmt_stamp(stamp)} gives "
                             f"no frame ({len(self.pending)} of {self.sent} messages without "
                             "one at the end of the log)")
        return out

    @property
    def problems(self) -> list[VideoProblem]:
        """Lost and duplicated messages found so far (`video_checks.VideoProblem`)."""
        return self.check.problems

    def _warn_skipped(self) -> None:
        if self.skipped:
            logger.warning("%s: %d video messages before the first keyframe (stamps %s to %s) "
                           "cannot be decoded and are skipped", self.topic, len(self.skipped),
                           fmt_stamp(self.skipped[0]), fmt_stamp(self.skipped[-1]))

    def _frames(self, packet: Any, stamp_ns: int | None) -> list[tuple[int, StoredImage]]:
        where = (f"video message at stamp {fmt_stamp(stamp_ns)}" if stamp_ns is not None
                 else "video at the end of the log")
        try:
            frames = self.context.decode(packet)
        except self.av.error.FFmpegError as exc:
            why = getattr(exc, "strerror", None) or " ".join(str(exc).split())
            raise InputError(f"{self.topic}: {where} does not decode ({self.format}: "
                             f"{why})") from exc
        out = []
        for frame in frames:
            index = frame.pts if frame.pts is not None else next(iter(self.pending), -1)
            if index not in self.pending:
                raise InputError(f"{self.topic}: {where}: the decoder returned a frame that "
                                 "belongs to no message")
            missed = [k for k in self.pending if k < index - REORDER_LIMIT]
            for k in missed:  # (a decoder may give no frame for a damaged one)
                if k not in self.damaged:
                    raise InputError(f"{self.topic}: video message at stamp "
                                     f"{fmt_stamp(self.pending[k])} gives no frame")
                del self.pending[k]
            stamp = self.pending.pop(index)
            if index in self.damaged:
                continue
            if frame.is_corrupt:
                raise InputError(f"{self.topic}: video message at stamp {fmt_stamp(stamp)} "
                                 "decodes to a damaged frame (missing or corrupt data)")
            out.append((stamp, self._stored(frame)))
        return out

    def _stored(self, frame: Any) -> StoredImage:
        width, height = int(frame.width), int(frame.height)
        if width * height > MAX_IMAGE_PIXELS:
            raise InputError(f"{self.topic}: video frames are {width}x{height} px, more than the "
                             f"{MAX_IMAGE_PIXELS / 1e6:.0f} Mpx limit")
        # YUV -> BGR with the stream's own matrix and range (BT.601 when it names none).
        bgr = np.ascontiguousarray(frame.to_ndarray(format="bgr24",
                                                    interpolation=self.interpolation))
        ok, png = cv2.imencode(".png", bgr)
        if not ok:  # pragma: no cover - OpenCV cannot fail on a valid uint8 image
            raise InputError(f"{self.topic}: a decoded video frame could not be stored as PNG")
        return StoredImage(png.tobytes(), "png", width, height)
