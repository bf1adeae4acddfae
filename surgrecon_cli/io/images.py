"""Image messages -> bytes to store: compressed JPEG/PNG kept as recorded, anything else
(raw `rgb8`/`bgr8`/`mono8`/..., other compressed formats) stored as PNG."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .records import ImageRecord

_JPEG_MAGIC = b"\xff\xd8\xff"
_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
# encoding -> (channels, dtype, cv2 conversion to BGR or None)
_RAW = {
    "rgb8": (3, np.uint8, cv2.COLOR_RGB2BGR),
    "bgr8": (3, np.uint8, None),
    "8uc3": (3, np.uint8, None),
    "rgba8": (4, np.uint8, cv2.COLOR_RGBA2BGR),
    "bgra8": (4, np.uint8, cv2.COLOR_BGRA2BGR),
    "mono8": (1, np.uint8, None),
    "8uc1": (1, np.uint8, None),
    "mono16": (1, np.uint16, None),
    "16uc1": (1, np.uint16, None),
}


@dataclass(frozen=True)
class StoredImage:
    """What ingest writes for one image: file bytes, extension ('jpg'/'png'), size in px."""

    data: bytes
    ext: str
    width: int
    height: int


def prepare_image(record: ImageRecord) -> StoredImage:
    """Decode (to validate and measure) and choose the stored form. ValueError if it does not
    decode, with the reason."""
    if record.format.lower() in _RAW or (record.width and record.height and record.step):
        return _raw(record)
    data = bytes(record.data)
    if not data:
        raise ValueError("empty image data")
    bgr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    if bgr is None:
        kind = record.format or "compressed"
        raise ValueError(f"{kind} data ({len(data)} bytes) does not decode")
    height, width = bgr.shape[:2]
    if data.startswith(_JPEG_MAGIC):
        return StoredImage(data, "jpg", width, height)
    if data.startswith(_PNG_MAGIC):
        return StoredImage(data, "png", width, height)
    return StoredImage(_png(bgr), "png", width, height)


def _raw(record: ImageRecord) -> StoredImage:
    spec = _RAW.get(record.format.lower())
    if spec is None:
        raise ValueError(f"raw encoding {record.format!r} is not supported "
                         f"(supported: {', '.join(sorted(_RAW))})")
    channels, dtype, conversion = spec
    width, height = int(record.width), int(record.height)
    row = width * channels * np.dtype(dtype).itemsize
    step = int(record.step) or row
    if width <= 0 or height <= 0 or step < row or len(record.data) < step * height:
        raise ValueError(f"raw {record.format} image {width}x{height} (step {step}) needs "
                         f"{step * height} bytes, has {len(record.data)}")
    buf = np.frombuffer(record.data, np.uint8, count=step * height).reshape(height, step)[:, :row]
    img = np.ascontiguousarray(buf).view(dtype).reshape(height, width, channels)
    if conversion is not None:
        img = cv2.cvtColor(img, conversion)
    return StoredImage(_png(img), "png", width, height)


def _png(img: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", img)
    if not ok:
        raise ValueError("image could not be re-encoded as PNG")
    return buf.tobytes()
