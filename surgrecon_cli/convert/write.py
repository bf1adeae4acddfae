"""The messages `convert` writes, and the config that ingests them.

Per frame (stamp t): on `/tf` world -> rig (identity when the rig is fixed; from the camera
pose file otherwise, at that file's stamps), then per camera its `sensor_msgs/CameraInfo`
and `sensor_msgs/CompressedImage`. Once, first: `/tf_static` rig -> each camera's optical
frame (the calibration's extrinsics). The rig frame is the first camera's optical frame.
A tool pose file becomes `/tf` world -> tool_tip at its own stamps.
"""

from __future__ import annotations

import heapq
import shlex
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import replace

import numpy as np

from ..core.geometry.poses import matrix_to_quat
from ..errors import InputError
from ..io.logs.records import CameraInfoRecord, ImageRecord, PoseRecord, Record
from .calibration import CameraCalibration, Rig
from .sources import Frame
from .stamps import PoseTrack

Message = tuple[str, int, Record]
IMAGE_TOPIC = "/camera/{camera}/image/compressed"
INFO_TOPIC = "/camera/{camera}/camera_info"
CAMERA_FRAME = "{camera}_optical_frame"
TF, TF_STATIC = "/tf", "/tf_static"
WORLD, RIG, TOOL = "world", "rig", "tool_tip"
_IDENTITY_Q = np.array([0.0, 0.0, 0.0, 1.0])


def _tf(stamp_ns: int, parent: str, child: str, position: np.ndarray,
        orientation: np.ndarray) -> PoseRecord:
    return PoseRecord(int(stamp_ns), parent, child, np.asarray(position, float),
                      np.asarray(orientation, float))


def _track(track: PoseTrack, child: str) -> Iterator[Message]:
    for t, p, q in zip(track.stamps_ns, track.positions, track.orientations, strict=True):
        yield TF, int(t), _tf(int(t), WORLD, child, p, q)


def scaled(cam: CameraCalibration, width: int, height: int) -> CameraCalibration:
    """The camera for images that are its calibrated ones resized to width x height px: pixel
    centres map as u' = (u + 0.5) sx - 0.5, so fx' = sx fx and cx' = sx (cx + 0.5) - 0.5."""
    sx, sy = width / cam.width, height / cam.height
    K = cam.K.copy()
    K[0, :] *= sx
    K[1, :] *= sy
    K[0, 2] += 0.5 * sx - 0.5
    K[1, 2] += 0.5 * sy - 0.5
    return replace(cam, K=K, width=width, height=height)


def _check_principal_point(cam: CameraCalibration, origin: str, size: tuple[int, int]) -> None:
    """A calibration that states no image size is taken at the first image's size: refuse it
    (InputError) when its principal point lies outside the central half of that image, as
    when the images were resized after calibration (a real lens centre is a few % off the
    image centre; a half-size image puts the full-size centre near its corner)."""
    cx, cy = float(cam.K[0, 2]), float(cam.K[1, 2])
    w, h = size
    if abs(cx - w / 2) <= w / 4 and abs(cy - h / 2) <= h / 4:
        return
    raise InputError(
        f"image {origin} is {w}x{h} px, but the principal point of camera {cam.name!r}, "
        f"({cx:.0f}, {cy:.0f}) px, lies outside the middle half of it: the calibration is for "
        f"other images (about {2 * cx:.0f}x{2 * cy:.0f} px?); add its calibrated width and "
        "height (imageSize) to the calibration file, with --scale-calibration if the images "
        "were resized")


def _check_aspect(cam: CameraCalibration, origin: str, size: tuple[int, int]) -> None:
    """--scale-calibration from the calibrated size to `size`: InputError when the two aspect
    ratios differ by a factor of 3 or more. A resize keeps the aspect ratio (d-lfd's
    640x480 -> 310x244: 5 %), a half side-by-side video halves it; a stereo video split the
    wrong way changes it 4-fold, and scaled K to those halves, which hold half of each eye."""
    (w, h), cw, ch = size, cam.width, cam.height
    ratio = (w / h) / (cw / ch)
    if 1 / 3 < ratio < 3:
        return
    raise InputError(f"image {origin} is {w}x{h} px; camera {cam.name!r}: the calibration says "
                     f"{cw}x{ch} px, an aspect ratio {max(ratio, 1 / ratio):.3g} times "
                     f"{'wider' if ratio > 1 else 'narrower'}, which no resize makes: a stereo "
                     "video split the wrong way (--stereo-layout), or another camera's "
                     "calibration?")


def _blank(data: bytes) -> bool:
    """Whether encoded image bytes (JPEG / PNG) decode to one flat value (a black frame)."""
    import cv2

    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    return img is None or int(np.ptp(img)) <= 1


def _check_distinct(cameras: Sequence[CameraCalibration], frame: Frame) -> None:
    """Two cameras with byte-identical images (the same folder or video given twice, a mono
    stream duplicated): InputError. Real views of two cameras never agree to the byte, and
    the same image as both eyes reconstructs a flat fake surface at the depth that the
    principal points' offset implies. Blank images (both eyes black before the light is
    on) are alike by nature and pass: build-template names them."""
    seen: dict[bytes, int] = {}
    for k, image in enumerate(frame.images):
        first = seen.setdefault(image.data, k)
        if first != k and not _blank(image.data):
            raise InputError(
                f"images {frame.images[first].origin} and {image.origin} (cameras "
                f"{cameras[first].name!r} and {cameras[k].name!r}, frame {frame.index}) are "
                "identical: each camera needs its own images (the same folder or video given "
                "twice?)")


class _Sizes:
    """Each camera's image size: the calibration's, else its first image's; any other size
    is an error naming the image, unless `scale` (the first image of another size than the
    calibration's rescales the camera's intrinsics to it)."""

    def __init__(self, cameras: Sequence[CameraCalibration], scale: bool) -> None:
        unsized = [c.name for c in cameras if not (c.width and c.height)]
        if scale and unsized:
            raise InputError(f"--scale-calibration: the calibration gives no image size for "
                             f"camera {unsized[0]!r}, so there is nothing to scale from: add "
                             "its calibrated size (imageSize, width and height, or image_width and "
                             "image_height) to the file")
        self.cameras = list(cameras)
        self.sizes = [(c.width, c.height) if c.width and c.height else None for c in cameras]
        self.scale = scale
        self.first = True

    def check(self, frame: Frame) -> None:
        for k, (cam, image) in enumerate(zip(self.cameras, frame.images, strict=True)):
            size = (image.width, image.height)
            if self.sizes[k] is None:
                _check_principal_point(cam, image.origin, size)
                self.sizes[k] = size
            elif self.first and self.scale and size != self.sizes[k]:
                _check_aspect(cam, image.origin, size)
                self.cameras[k] = scaled(cam, *size)
                self.sizes[k] = size
            elif size != self.sizes[k]:
                said = "the calibration says" if cam.width and self.first else \
                    "its first image is"
                w, h = self.sizes[k] or (0, 0)
                hint = " (--scale-calibration if the images are resized)" if \
                    self.first and not self.scale else ""
                raise InputError(f"image {image.origin} is {size[0]}x{size[1]} px; camera "
                                 f"{cam.name!r}: {said} {w}x{h} px{hint}")
        self.first = False


def _frame_messages(rig: Rig, frames: Iterable[Frame], stamps: np.ndarray | None,
                    start_ns: int, fixed_rig: bool, scale: bool) -> Iterator[Message]:
    sizes = _Sizes(rig.cameras, scale)
    last = None
    for k, frame in enumerate(frames):
        if len(frame.images) != len(rig.cameras):
            raise InputError(f"frame {frame.index} has {len(frame.images)} images, the "
                             f"calibration {len(rig.cameras)} cameras")
        sizes.check(frame)
        if k == 0:
            _check_distinct(rig.cameras, frame)
        if stamps is not None:
            t = int(stamps[k])
        elif frame.stamp_ns is not None:
            t = start_ns + frame.stamp_ns
        else:
            raise InputError(f"{frame.images[0].origin} has no time stamp; give --fps")
        if last is not None and t <= last:
            raise InputError(f"{frame.images[0].origin}: stamp {t} ns is not after the frame "
                             f"before ({last} ns); give --fps or a stamps file")
        last = t
        if fixed_rig:
            yield TF, t, _tf(t, WORLD, RIG, np.zeros(3), _IDENTITY_Q)
        for k_cam, (cam, image) in enumerate(zip(sizes.cameras, frame.images, strict=True)):
            frame_id = CAMERA_FRAME.format(camera=cam.name)
            w, h = sizes.sizes[k_cam] or (image.width, image.height)
            yield INFO_TOPIC.format(camera=cam.name), t, CameraInfoRecord(
                t, frame_id, w, h, cam.K, cam.D, cam.model)
            yield IMAGE_TOPIC.format(camera=cam.name), t, ImageRecord(
                t, frame_id, image.format, image.data)


def _within_poses(stream: Iterator[Message],
                  tracks: Sequence[tuple[str, PoseTrack]]) -> Iterator[Message]:
    """The frames' messages; after the last, InputError when none of them lies within the
    time span of a pose file (named by its option in `tracks`): its times are on another
    clock than the frames' (e.g. from 0 s while the frames start at --start-time), and
    ingest would find no camera pose at all, or no tool pose (tool removal silently off)."""
    times: list[int] = []
    for message in stream:
        times.append(message[1])
        yield message
    if not times:
        return
    stamps = np.array(times, dtype=np.int64)
    for option, track in tracks:
        lo, hi = int(track.stamps_ns[0]), int(track.stamps_ns[-1])
        if ((stamps >= lo) & (stamps <= hi)).any():
            continue
        raise InputError(f"{option}: the poses span {lo / 1e9:.3f}..{hi / 1e9:.3f} s but the "
                         f"frames {stamps.min() / 1e9:.3f}..{stamps.max() / 1e9:.3f} s, so no "
                         "frame has a pose from it: give the frames' times on the pose file's "
                         "clock (--stamps FILE, or --start-time and --fps)")


def messages(rig: Rig, frames: Iterable[Frame], stamps: np.ndarray | None,
             start_ns: int, camera_poses: PoseTrack | None = None,
             tool_poses: Sequence[PoseTrack] = (), scale: bool = False) -> Iterator[Message]:
    """Every message of the log, in log-time order (rules in the module docstring). Frame
    stamps: `stamps` (N,) ns, else the frames' own (video times) after `start_ns`; tools
    on /tf as `tool_frame(k)`."""
    checked = [(f"--tool-poses {track.source}", track) for track in tool_poses]
    if camera_poses is not None:
        checked.insert(0, (f"--camera-poses {camera_poses.source}", camera_poses))
    streams = [_within_poses(
        _frame_messages(rig, frames, stamps, start_ns, camera_poses is None, scale), checked)]
    if camera_poses is not None:
        streams.append(_track(camera_poses, RIG))
    streams += [_track(track, tool_frame(k)) for k, track in enumerate(tool_poses)]
    merged = heapq.merge(*streams, key=lambda m: m[1])
    first = next(merged, None)
    if first is None:
        return
    t0 = first[1]
    for cam in rig.cameras:
        yield TF_STATIC, t0, _tf(t0, RIG, CAMERA_FRAME.format(camera=cam.name),
                                 cam.to_rig[:3, 3], matrix_to_quat(cam.to_rig[:3, :3]))
    yield first
    yield from merged


def tool_frame(k: int) -> str:
    """The TF child frame of the k-th `--tool-poses` file: tool_tip, tool_tip_1, ..."""
    return TOOL if k == 0 else f"{TOOL}_{k}"


def config_text(log_name: str, rig: Rig, poses: str, tools: int = 0) -> str:
    """The TOML that runs the written log as it is (`[topics]`, and a `[[tools]]` table per
    tool after the first; the rest defaults)."""
    tool = tools > 0
    names = ", ".join(c.name for c in rig.cameras)
    base = log_name.removesuffix(".mcap")
    lines = [
        f"# Written by `surgrecon convert` for {log_name}; run it with",
        f"#   surgrecon run {shlex.quote(log_name)} -o {shlex.quote('runs/' + base)} "
        f"--config {shlex.quote(base + '.toml')}",
        f"# Cameras {names}; {poses}; calibration lengths read as {rig.units}.",
        "[topics]",
        f'image = "{IMAGE_TOPIC}"',
        f'camera_info = "{INFO_TOPIC}"',
        f'camera_pose = "{TF}"',
        f'camera_frame = "{CAMERA_FRAME}"',
        f'tool_pose = "{TF if tool else ""}"',
        f'tool_frame = "{TOOL}"',
        'joint_states = ""',
        f'world_frame = "{WORLD}"',
    ]
    if tool:
        lines += ["", "# The tool's shaft, masked and removed (defaults: 4 mm radius, 150 mm): set "
                  "them for your instrument.", "# [tool]", "# shaft_radius_m = 0.004",
                  "# shaft_length_m = 0.15"]
    for k in range(1, tools):
        lines += ["", f"# tool {k + 1} (--tool-poses file {k + 1}); its geometry as in [tool]",
                  "[[tools]]", f'pose = "{TF}"', f'frame = "{tool_frame(k)}"']
    return "\n".join(lines) + "\n"
