"""Image messages -> bytes to store: compressed JPEG/PNG kept as recorded, anything else
(raw `rgb8`/`bgr8`/`mono8`/..., Bayer mosaics, YUV 4:2:2, other compressed formats) stored
as PNG.

The size an image claims (raw width/height, PNG/JPEG header) is checked against
`MAX_IMAGE_PIXELS` before anything is allocated for it. What the C decoders print while
decoding (libjpeg's "Corrupt JPEG data: ...", libpng's errors) is collected instead of landing
on stderr: corrupt data is a ValueError naming the decoder's message, anything else a logged
warning."""

from __future__ import annotations

import contextlib
import logging
import os
import struct
import sys
import tempfile
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np

from ... import IMAGE_PIXEL_LIMIT
from .records import ImageRecord

logger = logging.getLogger(__name__)

_STDERR_LOCK = threading.Lock()
MAX_IMAGE_PIXELS = IMAGE_PIXEL_LIMIT
"""Largest image accepted (67 Mpx; an 8K camera has 33 Mpx); OpenCV's decoders refuse larger
ones too (OPENCV_IO_MAX_IMAGE_PIXELS, set in surgrecon_cli/__init__.py)."""
DECODE_FLAGS = cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION | cv2.IMREAD_ANYDEPTH
"""How every image is decoded: 3-channel BGR, pixels as stored (8 or 16 bit: `to_8bit`). An
EXIF orientation tag is ignored, as ROS (cv_bridge) does: the calibration and the size in
CameraInfo describe the stored pixels, and a rotated image would match neither."""
REDUCED_FLAGS = {2: cv2.IMREAD_REDUCED_COLOR_2, 4: cv2.IMREAD_REDUCED_COLOR_4,
                 8: cv2.IMREAD_REDUCED_COLOR_8}  # with DECODE_FLAGS: decoded at 1/2, 1/4, 1/8
_JPEG_MAGIC = b"\xff\xd8\xff"
_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
_CORRUPT = ("Corrupt JPEG data", "Premature end of JPEG file")  # libjpeg: data was damaged
# ROS sensor_msgs/image_encodings name -> (channels, dtype, cv2 conversion to BGR or None).
# Bayer names give the colours of the top-left 2x2 block; OpenCV names its codes after the
# second row's second and third pixels, hence rggb -> BayerBG (as cv_bridge maps them).
# yuv422 is UYVY (U0 Y0 V0 Y1), yuv422_yuy2 is YUYV (Y0 U0 Y1 V0); OpenCV converts them with
# BT.601 limited-range coefficients.
_RAW = {
    "rgb8": (3, np.uint8, cv2.COLOR_RGB2BGR),
    "bgr8": (3, np.uint8, None),
    "8uc3": (3, np.uint8, None),
    "rgba8": (4, np.uint8, cv2.COLOR_RGBA2BGR),
    "bgra8": (4, np.uint8, cv2.COLOR_BGRA2BGR),
    "rgb16": (3, np.uint16, cv2.COLOR_RGB2BGR),
    "bgr16": (3, np.uint16, None),
    "rgba16": (4, np.uint16, cv2.COLOR_RGBA2BGR),
    "bgra16": (4, np.uint16, cv2.COLOR_BGRA2BGR),
    "mono8": (1, np.uint8, None),
    "8uc1": (1, np.uint8, None),
    "mono16": (1, np.uint16, None),
    "16uc1": (1, np.uint16, None),
    "bayer_rggb8": (1, np.uint8, cv2.COLOR_BayerBG2BGR),
    "bayer_bggr8": (1, np.uint8, cv2.COLOR_BayerRG2BGR),
    "bayer_gbrg8": (1, np.uint8, cv2.COLOR_BayerGR2BGR),
    "bayer_grbg8": (1, np.uint8, cv2.COLOR_BayerGB2BGR),
    "bayer_rggb16": (1, np.uint16, cv2.COLOR_BayerBG2BGR),
    "bayer_bggr16": (1, np.uint16, cv2.COLOR_BayerRG2BGR),
    "bayer_gbrg16": (1, np.uint16, cv2.COLOR_BayerGR2BGR),
    "bayer_grbg16": (1, np.uint16, cv2.COLOR_BayerGB2BGR),
    "yuv422": (2, np.uint8, cv2.COLOR_YUV2BGR_UYVY),
    "yuv422_yuy2": (2, np.uint8, cv2.COLOR_YUV2BGR_YUY2),
}
_EVEN_WIDTH = ("bayer_", "yuv422")  # 2x2 mosaics and 4:2:2 pairs need even sizes


@dataclass(frozen=True)
class StoredImage:
    """What ingest writes for one image: file bytes, extension ('jpg'/'png'), size in px."""

    data: bytes
    ext: str
    width: int
    height: int
    peak: int = 255  # largest pixel value: 255 for 8-bit data, measured for 16-bit


def prepare_image(record: ImageRecord) -> StoredImage:
    """Decode (to validate and measure) and choose the stored form. ValueError if it does not
    decode, with the reason."""
    if record.format.lower() in _RAW or (record.width and record.height and record.step):
        return _raw(record)
    data = bytes(record.data)
    if not data:
        raise ValueError("empty image data")
    claimed = header_size(data)
    if claimed is not None:
        _check_pixels(*claimed)
    kind = record.format or "compressed"
    with _native_stderr() as native:
        try:
            bgr = cv2.imdecode(np.frombuffer(data, np.uint8), DECODE_FLAGS)
        except cv2.error as exc:  # e.g. above OpenCV's pixel limit
            raise ValueError(f"{kind} data ({len(data)} bytes) is refused by the decoder "
                             f"(larger than the {MAX_IMAGE_PIXELS / 1e6:.0f} Mpx limit or "
                             "damaged)") from exc
    if bgr is None:
        why = f" ({native[-1]})" if native else ""
        raise ValueError(f"{kind} data ({len(data)} bytes) does not decode{why}")
    corrupt = [line for line in native if line.startswith(_CORRUPT)]
    if corrupt:
        raise ValueError(f"{kind} data ({len(data)} bytes) is corrupt ({corrupt[0]})")
    for line in native:
        logger.warning("%s image: %s", kind, line)
    height, width = bgr.shape[:2]
    peak = _peak(bgr)
    if data.startswith(_JPEG_MAGIC):
        return StoredImage(data, "jpg", width, height, peak)
    if data.startswith(_PNG_MAGIC):
        return StoredImage(data, "png", width, height, peak)
    return StoredImage(_png(bgr), "png", width, height, peak)


def _peak(img: np.ndarray) -> int:
    """The largest pixel value of a 16-bit image (255 for 8-bit data: nothing to measure)."""
    return int(img.max()) if img.dtype == np.uint16 and img.size else 255


def to_8bit(img: np.ndarray, peak: int) -> np.ndarray:
    """A decoded image as uint8: 8-bit data as it is; 16-bit data scaled from its real range,
    0 .. 2^b - 1 with b (8 to 16) the fewest bits that hold `peak` (the camera's largest value
    over the log): a 12-bit camera's 0..4095 fill 0..255, not 0..15 as the high byte alone
    would."""
    if img.dtype == np.uint8:
        return img
    top = float((1 << max(8, min(16, int(peak).bit_length()))) - 1)
    return cv2.convertScaleAbs(img, alpha=255.0 / top)


def _raw(record: ImageRecord) -> StoredImage:
    """Raw pixels (ROS `sensor_msgs/Image` / Foxglove RawImage layout: rows of `step` bytes)
    -> PNG of the BGR (or mono) image; Bayer mosaics demosaiced (bilinear), YUV 4:2:2
    converted, 16-bit data byte-swapped when the message says big-endian."""
    encoding = record.format.lower()
    spec = _RAW.get(encoding)
    if spec is None:
        raise ValueError(f"raw encoding {record.format!r} is not supported "
                         f"(supported: {', '.join(sorted(_RAW))})")
    channels, dtype, conversion = spec
    width, height = int(record.width), int(record.height)
    _check_pixels(width, height)
    if encoding.startswith(_EVEN_WIDTH) and (width % 2 or (encoding.startswith("bayer_")
                                                           and height % 2)):
        raise ValueError(f"raw {record.format} image is {width}x{height} px; the encoding "
                         "needs an even width" + (" and height" if "bayer" in encoding else ""))
    row = width * channels * np.dtype(dtype).itemsize
    step = int(record.step) or row
    if width <= 0 or height <= 0 or step < row or len(record.data) < step * height:
        raise ValueError(f"raw {record.format} image {width}x{height} (step {step}) needs "
                         f"{step * height} bytes, has {len(record.data)}")
    buf = np.frombuffer(record.data, np.uint8, count=step * height).reshape(height, step)[:, :row]
    order: Literal[">", "<"] = ">" if record.big_endian else "<"
    img = np.ascontiguousarray(buf).view(np.dtype(dtype).newbyteorder(order))
    img = img.astype(dtype).reshape(height, width, channels)
    if channels == 1:
        img = img[:, :, 0]
    if conversion is not None:
        img = cv2.cvtColor(img, conversion)
    return StoredImage(_png(img), "png", width, height, _peak(img))


def _check_pixels(width: int, height: int) -> None:
    if width <= 0 or height <= 0:
        raise ValueError(f"it claims {width}x{height} px")
    if width * height > MAX_IMAGE_PIXELS:
        raise ValueError(f"it claims {width}x{height} px, more than the "
                         f"{MAX_IMAGE_PIXELS / 1e6:.0f} Mpx limit")


def header_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) from a PNG IHDR or a JPEG SOFn header, None for other data.
    ValueError for a PNG or JPEG whose header gives no size (nothing is decoded then)."""
    if data.startswith(_PNG_MAGIC):
        if len(data) < 24 or data[12:16] != b"IHDR":
            raise ValueError("PNG data without an IHDR header")
        width, height = struct.unpack(">II", data[16:24])
        return width, height
    if data.startswith(_JPEG_MAGIC):
        return _jpeg_size(data)
    return None


def structure_problem(data: bytes) -> str | None:
    """Why PNG or JPEG bytes are cut short, or None when their structure is whole (other data:
    None). Cheap (nothing decoded, no checksum): a PNG's chunks must chain by their lengths
    from the signature to an IEND chunk; a JPEG needs an end-of-image marker after its first
    start of scan (0xFF 0xD9 cannot occur inside entropy-coded data). A damaged byte inside
    the compressed data passes here; decoding (ingest) finds that."""
    if data.startswith(_PNG_MAGIC):
        pos, end = len(_PNG_MAGIC), len(data)
        while pos + 8 <= end:
            length, kind = struct.unpack_from(">I4s", data, pos)
            pos += 12 + length
            if kind == b"IEND":
                return None if pos <= end else "truncated (its IEND chunk is cut short)"
        return "truncated (no IEND chunk: the file ends inside its chunks)"
    if data.startswith(_JPEG_MAGIC):
        scan = data.find(b"\xff\xda")
        if scan < 0 or data.rfind(b"\xff\xd9") < scan:
            return "truncated (no end-of-image marker after its image data)"
    return None


def _jpeg_size(data: bytes) -> tuple[int, int]:
    """(width, height) of the JPEG's first start-of-frame marker, found as libjpeg finds
    markers: bytes other than 0xFF before a marker skipped (libjpeg's "extraneous bytes"),
    fill bytes (0xFF 0xFF...) skipped, standalone markers (TEM, RSTn, SOI) without a length,
    every other segment skipped by its length. ValueError when the scan reaches the image
    data (SOS), the end (EOI) or the end of the bytes without a frame size."""
    pos, end = 2, len(data)
    while True:
        pos = data.find(b"\xff", pos)
        while 0 <= pos < end - 1 and data[pos + 1] == 0xFF:
            pos += 1
        if pos < 0 or pos + 1 >= end:
            break
        marker = data[pos + 1]
        pos += 2
        if marker == 0x00 or marker == 0x01 or 0xD0 <= marker <= 0xD8:
            continue  # a stuffed byte or a standalone marker
        if marker in (0xD9, 0xDA) or pos + 2 > end:
            break
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):  # start of frame
            if pos + 7 > end:
                break
            height, width = struct.unpack(">HH", data[pos + 3: pos + 7])
            return width, height
        pos += struct.unpack(">H", data[pos: pos + 2])[0]
    raise ValueError("JPEG data without a readable frame size before its image data")


@contextlib.contextmanager
def _native_stderr() -> Iterator[list[str]]:
    """Collect the lines C libraries write to file descriptor 2 meanwhile. File descriptors
    are per process: one thread at a time redirects (several logs may be ingested by
    threads at once); anything else written to stderr meanwhile is collected too."""
    lines: list[str] = []
    with _STDERR_LOCK, contextlib.ExitStack() as stack:
        try:
            sys.stderr.flush()
            tmp = stack.enter_context(tempfile.TemporaryFile())
            saved: int | None = os.dup(2)
        except (OSError, ValueError, AttributeError):  # no usable stderr or temp dir
            saved = None
        if saved is None:
            yield lines
            return
        os.dup2(tmp.fileno(), 2)
        try:
            yield lines
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            tmp.seek(0)
            text = tmp.read().decode("utf-8", errors="replace")
            lines.extend(line.strip() for line in text.splitlines() if line.strip())


def _png(img: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", img)
    if not ok:
        raise ValueError("image could not be re-encoded as PNG")
    return buf.tobytes()
