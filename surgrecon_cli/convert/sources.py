"""Image sources of `convert`: per-camera image folders and videos, stereo folders and stereo
videos -> frames of encoded images, one per camera.

Images are kept as they are where the file already is what a ROS `CompressedImage` carries:
JPEG and PNG bytes are copied (8 or 16 bit; the size read from the header, nothing decoded;
a file cut short is refused: `io.logs.images.structure_problem`);
BMP, TIFF and other files OpenCV reads are re-encoded once as PNG (lossless, bit depth kept).
Video frames (decoded by PyAV) are encoded once, as JPEG quality 95 by default (the video is
lossy already; a PNG of a 1280x1024 frame is ~10x larger) or as PNG (`image_format='png'`).
"""

from __future__ import annotations

import logging
import math
import re
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..errors import InputError
from ..io.logs.images import header_size, structure_problem
from ..io.logs.log_input import IMAGE_SUFFIXES

# Hamlyn's rectified sequences: image01 (left) / image02; KITTI's: image_02 / image_03.
STEREO_FOLDERS = (("left", "right"), ("Left", "Right"), ("left_image", "right_image"),
                  ("image_0", "image_1"), ("image01", "image02"), ("image_02", "image_03"),
                  ("cam0", "cam1"))
LAYOUTS = ("auto", "side-by-side", "top-bottom")
JPEG_QUALITY = 95
_JPEG_MAGIC = b"\xff\xd8"
_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class EncodedImage:
    """One camera image as a CompressedImage carries it: `format` 'jpeg' or 'png', size px;
    `origin` names where it came from (file, or video and frame) for messages."""

    data: bytes
    format: str
    width: int
    height: int
    origin: str


@dataclass(frozen=True)
class Frame:
    """One time step: an image per camera (in the source's camera order) and the stamp the
    source knows (video presentation time, ns), or None."""

    index: int
    stamp_ns: int | None
    images: tuple[EncodedImage, ...]


def ordered_map(func: Callable[[Any], Any], items: Iterable[Any], workers: int = 4,
                ahead: int = 8) -> Iterator[Any]:
    """`map(func, items)` on a thread pool, in order, at most `ahead` items in flight (file
    reads, JPEG/PNG coding and zstd release the GIL). Iteration stops at the first error."""
    with ThreadPoolExecutor(max_workers=workers) as pool:
        pending: deque[Future[Any]] = deque()
        try:
            for item in items:
                pending.append(pool.submit(func, item))
                if len(pending) >= ahead:
                    yield pending.popleft().result()
            while pending:
                yield pending.popleft().result()
        finally:
            for future in pending:
                future.cancel()


def _natural_key(path: Path) -> list[Any]:
    """Name order with digit runs compared as numbers (img2 before img10)."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", path.name)]


def list_images(folder: Path) -> list[Path]:
    """The image files of a folder (EuRoC-style `folder/data/` too), in name order; hidden
    files are not images (macOS writes `._NAME.png` metadata beside every file it copies to
    a non-Mac disk)."""
    if not folder.is_dir():
        raise InputError(f"image folder {folder} does not exist")
    files = [p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES
             and not p.name.startswith(".") and p.is_file()]
    if not files and (folder / "data").is_dir():
        return list_images(folder / "data")
    if not files:
        raise InputError(f"image folder {folder} holds no images "
                         f"({', '.join(IMAGE_SUFFIXES)})")
    return sorted(files, key=_natural_key)


def stereo_folders(src: Path, left: str | None, right: str | None) -> tuple[Path, Path]:
    """The left and right image folders inside `src`."""
    if left or right:
        if not (left and right):
            raise InputError("give both --left and --right (the two image folders' names)")
        return src / left, src / right
    for lname, rname in STEREO_FOLDERS:
        if (src / lname).is_dir() and (src / rname).is_dir():
            return src / lname, src / rname
    names = ", ".join(f"{a}/{b}" for a, b in STEREO_FOLDERS)
    raise InputError(f"{src}: no stereo image folders found (looked for {names}); name them "
                     "with --left/--right, or give one folder per camera with --camera")


def encode_file(path: Path) -> EncodedImage:
    """One image file as JPEG/PNG bytes: copied when it is JPEG or PNG, else PNG-encoded."""
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise InputError(f"image {path}: cannot be read ({exc.strerror or exc})") from None
    if data.startswith((_JPEG_MAGIC, _PNG_MAGIC)):
        try:
            size = header_size(data)
        except ValueError:
            size = None
        if size is None:
            raise InputError(f"image {path}: truncated or corrupt header")
        problem = structure_problem(data)
        if problem is not None:
            raise InputError(f"image {path}: {problem}; re-copy or re-export it")
        return EncodedImage(data, "jpeg" if data.startswith(_JPEG_MAGIC) else "png", *size,
                            str(path))
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED) if data else None
    if img is None:
        raise InputError(f"image {path}: not an image OpenCV can read")
    return encode_array(img, "png", str(path))


def encode_array(img: np.ndarray, image_format: str, origin: str) -> EncodedImage:
    """A BGR (or mono) image (H, W[, C]) -> JPEG (quality 95) or PNG bytes."""
    if image_format == "jpeg":
        ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    else:
        ok, buf = cv2.imencode(".png", img)
    if not ok:
        raise InputError(f"{origin}: the image could not be encoded as {image_format}")
    return EncodedImage(buf.tobytes(), image_format, img.shape[1], img.shape[0], origin)


class FolderSource:
    """One image folder per camera; the i-th files (name order) of all folders form frame i."""

    def __init__(self, folders: Sequence[Path]) -> None:
        self.folders = list(folders)
        self.files = [list_images(f) for f in self.folders]
        counts = {len(f) for f in self.files}
        if len(counts) > 1:
            listing = ", ".join(f"{folder} {len(files)}"
                                for folder, files in zip(self.folders, self.files, strict=True))
            raise InputError(f"the image folders hold different numbers of images ({listing}); "
                             "every camera needs one image per frame")
        self.count = len(self.files[0])

    def _frame(self, i: int) -> Frame:
        return Frame(i, None, tuple(encode_file(files[i]) for files in self.files))

    def frames(self, indices: Sequence[int]) -> Iterator[Frame]:
        yield from ordered_map(self._frame, indices)


def _import_av() -> Any:
    try:
        import av
    except ImportError:
        raise InputError('reading videos needs PyAV: pip install "surgrecon[video]"') from None
    return av


class VideoSource:
    """One video per camera, or one stereo video split in two halves (`layout`)."""

    def __init__(self, videos: Sequence[Path], layout: str | None = None,
                 image_format: str = "jpeg") -> None:
        self.videos = list(videos)
        self.layout = layout
        self.image_format = image_format
        av = _import_av()
        counts = []
        for video in self.videos:
            if not video.is_file():
                raise InputError(f"video {video} does not exist")
            try:
                with av.open(str(video)) as container:
                    stream = container.streams.video[0]
                    counts.append(int(stream.frames) or sum(
                        1 for packet in container.demux(stream) if packet.size))
                    self.size = (int(stream.codec_context.width),
                                 int(stream.codec_context.height))
            except (av.error.FFmpegError, IndexError) as exc:
                raise InputError(f"video {video}: cannot be read ({exc})") from None
        self.count: int | None = min(counts)
        if len(set(counts)) > 1:
            listing = ", ".join(f"{video} {n}" for video, n in zip(self.videos, counts,
                                                                    strict=True))
            logger.warning("the videos hold different numbers of frames (%s): the first %d of "
                           "each are converted, the i-th frames of all videos forming frame i; "
                           "a frame lost inside one video shifts every later pair: check that "
                           "the last frames still match", listing, min(counts))

    def _decoded(self, video: Path) -> Iterator[tuple[int | None, np.ndarray]]:
        av = _import_av()
        try:
            with av.open(str(video)) as container:
                stream = container.streams.video[0]
                for frame in container.decode(stream):
                    stamp = None
                    if frame.pts is not None and stream.time_base is not None:
                        stamp = round(Fraction(frame.pts) * stream.time_base * 10**9)
                    yield stamp, frame.to_ndarray(format="bgr24")
        except av.error.FFmpegError as exc:
            raise InputError(f"video {video}: decoding failed ({exc})") from None

    def frames(self, indices: Sequence[int]) -> Iterator[Frame]:
        yield from ordered_map(self._encode, self._decoded_frames(indices))

    def _encode(self, item: tuple[int, int | None, list[tuple[np.ndarray, str]]]) -> Frame:
        i, stamp, views = item
        return Frame(i, stamp, tuple(encode_array(img, self.image_format, origin)
                                     for img, origin in views))

    def _decoded_frames(self, indices: Sequence[int]
                        ) -> Iterator[tuple[int, int | None, list[tuple[np.ndarray, str]]]]:
        """(index, stamp, [(view, origin)]) of the wanted frames, views split per camera."""
        wanted = set(indices)
        last = max(wanted, default=-1)
        streams = [self._decoded(v) for v in self.videos]
        for i in range(last + 1):
            maybe = [next(s, None) for s in streams]
            decoded = [d for d in maybe if d is not None]
            if len(decoded) < len(maybe):
                short = [str(v) for v, d in zip(self.videos, maybe, strict=True) if d is None]
                raise InputError(f"video {', '.join(short)} ends at frame {i}; "
                                 f"frame {last} was asked for")
            if i not in wanted:
                continue
            halves: list[tuple[np.ndarray, str]] = []
            for video, (_, img) in zip(self.videos, decoded, strict=True):
                origin = f"video {video} frame {i}"
                if self.layout is None:
                    halves.append((img, origin))
                else:
                    halves += [(h, origin) for h in split_stereo(img, self.layout)]
            yield i, decoded[0][0], halves


def split_stereo(img: np.ndarray, layout: str) -> tuple[np.ndarray, np.ndarray]:
    """A stereo frame -> (left/top, right/bottom) halves."""
    if layout == "side-by-side":
        half = img.shape[1] // 2
        return img[:, :half], img[:, half: 2 * half]
    half = img.shape[0] // 2
    return img[:half], img[half: 2 * half]


def choose_layout(layout: str, size: tuple[int, int], eye: tuple[int, int],
                  scale: bool = False) -> str:
    """The stereo layout of a `size` (w, h) video: as given, or (auto) the one whose halves have
    the calibrated `eye` size, or with `scale` (--scale-calibration: the video is resized) the
    one whose halves alone have the calibrated aspect ratio within 20 % (0, 0 = unknown: side
    by side when wider than high)."""
    if layout != "auto":
        return layout
    w, h = size
    if eye[0] and eye[1]:
        halves = {"side-by-side": (w // 2, h), "top-bottom": (w, h // 2)}
        for name, half in halves.items():
            if half == eye:
                return name
        aspect = eye[0] / eye[1]
        alike = [name for name, (hw, hh) in halves.items()
                 if hh and abs(math.log(hw / hh / aspect)) < math.log(1.2)]
        if scale and len(alike) == 1:
            return alike[0]
        if len(alike) == 1:
            hw, hh = halves[alike[0]]
            raise InputError(f"the stereo video is {w}x{h} px; its halves {alike[0]} ({hw}x{hh}) "
                             f"have the shape of the calibrated {eye[0]}x{eye[1]} px but not "
                             "its size: add --scale-calibration if the video is the calibrated "
                             "images resized")
        raise InputError(f"the stereo video is {w}x{h} px; neither its halves side by side "
                         f"({w // 2}x{h}) nor top-bottom ({w}x{h // 2}) are the calibrated "
                         f"{eye[0]}x{eye[1]} px: give --stereo-layout (and --scale-calibration "
                         "if the video is the calibrated images resized)")
    return "side-by-side" if w > h else "top-bottom"
