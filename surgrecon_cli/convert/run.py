"""`convert` end to end: resolve the source, read the calibration, write OUT.mcap (ROS 2, CDR,
through the simulator's log writer) and OUT.toml, both atomically."""

from __future__ import annotations

import ctypes
import re
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from mcap.writer import CompressionType

from ..errors import InputError
from ..io.logs.log_input import VIDEO_SUFFIXES
from ..io.run.atomic import write_text
from ..sim.log_writer import write_log
from .calibration import Rig, load_rig
from .sources import FolderSource, VideoSource, choose_layout, stereo_folders
from .stamps import frame_stamps, read_tum
from .write import config_text, messages

DEFAULT_FPS = 30.0
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # glibc's mallopt parameters (malloc.h)
_NAME = re.compile(r"[A-Za-z0-9_-]+\Z")


@dataclass(frozen=True)
class ConvertRequest:
    """What to convert (the `surgrecon convert` options)."""

    out: Path
    calibration: tuple[Path, ...]
    src: Path | None = None
    cameras: tuple[tuple[str, Path], ...] = ()
    left: str | None = None
    right: str | None = None
    layout: str = "auto"
    units: str | None = None
    fps: float | None = None
    stamps: Path | None = None
    camera_poses: Path | None = None
    tool_poses: tuple[Path, ...] = ()
    image_format: str = "jpeg"
    frames: slice = field(default_factory=lambda: slice(None))
    start_time: float = 1.0
    scale_calibration: bool = False


@dataclass(frozen=True)
class ConvertResult:
    """What was written."""

    log: Path
    config: Path
    frames: int
    cameras: tuple[str, ...]
    units: str
    source: str


def _is_video(path: Path) -> bool:
    return path.is_file() and path.suffix.lower() in VIDEO_SUFFIXES


def _named_rig(rig: Rig, names: Sequence[str]) -> Rig:
    """The rig's cameras in the source's order: by name when the calibration names them all,
    else renamed in order."""
    by_name = {c.name: c for c in rig.cameras}
    if all(n in by_name for n in names):
        return replace(rig, cameras=tuple(by_name[n] for n in names))
    if len(names) != len(rig.cameras):
        raise InputError(f"the source has {len(names)} cameras ({', '.join(names)}), the "
                         f"calibration {len(rig.cameras)} "
                         f"({', '.join(c.name for c in rig.cameras)})")
    return replace(rig, cameras=tuple(replace(c, name=n)
                                      for c, n in zip(rig.cameras, names, strict=True)))


def _source(req: ConvertRequest, rig: Rig) -> tuple[Any, tuple[str, ...], str]:
    """(source, camera names, description)."""
    if req.cameras:
        names = tuple(n for n, _ in req.cameras)
        bad = [n for n in names if not _NAME.match(n)]
        if bad or len(set(names)) < len(names):
            raise InputError(f"--camera names must be distinct letters, digits, _ or - "
                             f"(got {', '.join(names)})")
        paths = [p for _, p in req.cameras]
        if all(_is_video(p) for p in paths):
            return VideoSource(paths, None, req.image_format), names, "one video per camera"
        if all(p.is_dir() for p in paths):
            return FolderSource(paths), names, "one image folder per camera"
        missing = [str(p) for p in paths if not p.exists()]
        raise InputError(f"--camera: {', '.join(missing)} does not exist" if missing else
                         "--camera paths must be all image folders or all videos")
    if req.src is None:
        raise InputError("give SRC (a stereo image folder or a stereo video) or --camera "
                         "NAME=PATH for each camera")
    names = ("left", "right")
    if req.src.is_dir():
        left, right = stereo_folders(req.src, req.left, req.right)
        return FolderSource([left, right]), names, f"stereo folders {left.name}/{right.name}"
    if not req.src.exists():
        raise InputError(f"{req.src} does not exist")
    video = VideoSource([req.src], None, req.image_format)
    first = rig.cameras[0] if rig.cameras else None
    eye = (first.width, first.height) if first is not None else (0, 0)
    video.layout = choose_layout(req.layout, video.size, eye, req.scale_calibration)
    return video, names, f"stereo video, {video.layout}"


def _check_outputs_spare_inputs(req: ConvertRequest) -> None:
    """InputError when OUT or OUT.toml is one of the inputs (a slip such as `-o
    calibration.yaml` or `-o video.mp4` replaced that file with the log)."""
    inputs = [("source", req.src), *(("calibration file", p) for p in req.calibration),
              ("stamps file", req.stamps), ("camera pose file", req.camera_poses),
              *(("tool pose file", p) for p in req.tool_poses),
              *((f"camera {name}'s source", p) for name, p in req.cameras)]
    for out in (req.out, req.out.with_suffix(".toml")):
        for what, path in inputs:
            if path is not None and path.exists() and out.exists() and out.samefile(path):
                raise InputError(f"-o {req.out}: writing {out} would replace the {what} "
                                 f"{path}; choose another output name")


def keep_freed_memory() -> None:
    """Let this process keep the memory it frees (glibc only; elsewhere nothing happens).

    Every image passes through a few buffers of its size (the file, its message, its chunk:
    MBs each); glibc gives such blocks back to the kernel when freed (mmap, heap trim), and
    the next image's buffers then fault their pages in anew: 700,000 page faults and 3/4 of
    the CPU time for 300 PNG stereo frames of 1280x1024 px on a 2-core VM
    (benchmarks/convert_speed.py). With mmap and trim thresholds of 64 and 128 MB the
    buffers are reused; the process holds at most that much freed memory more."""
    try:
        libc = ctypes.CDLL(None)
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return
    mallopt(_M_MMAP_THRESHOLD, 64 << 20)
    mallopt(_M_TRIM_THRESHOLD, 128 << 20)


def convert(req: ConvertRequest,
            progress: Callable[..., Iterable[Any]] = lambda it, **_: it) -> ConvertResult:
    """Write `req.out` (MCAP) and its `.toml` config; InputError on bad input (nothing is
    left under either name then)."""
    if req.image_format not in ("jpeg", "png"):
        raise InputError(f"image format {req.image_format!r}: use jpeg or png")
    _check_outputs_spare_inputs(req)
    keep_freed_memory()
    rig = load_rig(req.calibration, req.units, [n for n, _ in req.cameras])
    source, names, description = _source(req, rig)
    rig = _named_rig(rig, names)
    if source.count is None:
        raise InputError(f"{req.src}: the number of video frames is unknown")
    indices = list(range(source.count))[req.frames]
    if not indices:
        raise InputError(f"no frames to convert (the source has {source.count}, the frame "
                         "range selects none)")
    is_video = isinstance(source, VideoSource)
    start_ns = round(req.start_time * 1e9)
    stamps = frame_stamps(indices, req.fps, req.stamps, None if is_video else DEFAULT_FPS,
                          start_ns)
    camera_poses = read_tum(req.camera_poses, "camera pose file") if req.camera_poses else None
    tool_poses = [read_tum(p, "tool pose file") for p in req.tool_poses]
    frames = progress(source.frames(indices), total=len(indices), desc="convert",
                      unit="frame")
    write_log(req.out, messages(rig, frames, stamps, start_ns, camera_poses, tool_poses,
                                  req.scale_calibration),
              "ros2", compression=CompressionType.NONE)  # images are compressed already
    poses = (f"rig poses from {req.camera_poses.name}" if req.camera_poses
             else "rig fixed in the world")
    config = req.out.with_suffix(".toml")
    write_text(config, config_text(req.out.name, rig, poses, len(tool_poses)))
    return ConvertResult(req.out, config, len(indices), names, rig.units, description)
