"""The `RUN/ingest/` folder: what ingest extracted, in a form later stages load quickly.

cameras.json holds the camera ids (sorted strings), intrinsics and the ingest report;
frames.npz the per-frame arrays (see `IngestedLog`); images/ every image as recorded
(compressed bytes kept; raw images and decoded video frames stored as PNG); video/ a video
camera's packets as recorded (`VideoPackets`, for the export). Paths: io/run/layout.py.
"""

from __future__ import annotations

import functools
import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ...core.geometry.cameras import CameraModel
from ...core.sync.streams import PoseStream
from ...errors import InputError, RunFolderError
from ..logs.images import DECODE_FLAGS, REDUCED_FLAGS, to_8bit
from .atomic import file_identity, write_json, write_npz
from .layout import RunLayout


@dataclass(frozen=True)
class IngestedLog:
    """Frames of a log after time synchronisation and pose interpolation.

    cameras: sorted camera ids (C,); models: intrinsics per camera index;
    stamps_ns (T,) int64 frame times; image_stamps_ns (T, C) int64 (-1 = no image);
    poses (T, C, 4, 4) camera-to-world at each image's stamp, NaN where unusable;
    usable (T, C) bool: image present, decoded and pose interpolated within tolerance;
    tool_poses (T, 4, 4) tool tip in world at the frame stamp (NaN where unknown);
    extra_tool_poses (T, K, 4, 4) the same of each `[[tools]]` tool (K = 0 without);
    joint_names (J,), joint_positions (T, J) (NaN where unknown);
    image_paths[t][c]: relative path of the stored image or "".
    """

    root: Path
    cameras: tuple[str, ...]
    models: tuple[CameraModel, ...]
    stamps_ns: np.ndarray
    image_stamps_ns: np.ndarray
    poses: np.ndarray
    usable: np.ndarray
    tool_poses: np.ndarray
    joint_names: tuple[str, ...]
    joint_positions: np.ndarray
    image_paths: tuple[tuple[str, ...], ...]
    report: dict = field(default_factory=dict)
    extra_tool_poses: np.ndarray = field(default_factory=lambda: np.zeros((0, 0, 4, 4)))

    @property
    def n_frames(self) -> int:
        return int(self.stamps_ns.shape[0])

    def all_tool_poses(self, frame: int) -> np.ndarray:
        """(K + 1, 4, 4): the `[tool]` pose then each `[[tools]]` pose at a frame, as
        `Config.tool_configs()` lists their geometry."""
        extra = (self.extra_tool_poses[frame] if len(self.extra_tool_poses)
                 else np.zeros((0, 4, 4)))
        return np.concatenate([self.tool_poses[frame][None], extra])

    def frame_images(self, frame: int) -> list[np.ndarray | None]:
        """Images of every camera at a frame (None where the camera is unusable)."""
        return [self.load_image(frame, c) if self.usable[frame, c] else None
                for c in range(len(self.cameras))]

    def usable_poses(self, frame: int) -> np.ndarray:
        """Camera-to-world poses (C, 4, 4) at a frame, NaN where the camera is unusable."""
        return np.where(self.usable[frame][:, None, None], self.poses[frame], np.nan)

    def load_image(self, frame: int, camera_index: int, reduced: int = 1) -> np.ndarray:
        """Image (H, W, 3) uint8 RGB of one camera at one frame (16-bit images scaled from
        the camera's range: io.logs.images.to_8bit of its `pixel_max`); `reduced` 2, 4 or
        8: decoded at that fraction of its size (a JPEG's cheaper decode; a preview)."""
        rel = self.image_paths[frame][camera_index]
        if not rel:
            raise RunFolderError(f"frame {frame}: camera {self.cameras[camera_index]} has no image")
        path = os.path.join(self.root, rel)  # not a Path: see RunLayout.registration_file
        data = np.fromfile(path, dtype=np.uint8)
        bgr = cv2.imdecode(data, DECODE_FLAGS | REDUCED_FLAGS.get(reduced, 0))
        if bgr is None:
            raise InputError(f"{path}: stored image does not decode; re-run ingest")
        peak = self.report.get("cameras", {}).get(self.cameras[camera_index], {}).get(
            "pixel_max", 65535)
        return cv2.cvtColor(to_8bit(bgr, peak), cv2.COLOR_BGR2RGB)


def save_pose_streams(root: Path, cameras: list[PoseStream], tool: PoseStream) -> None:
    """The pose streams as recorded (in the world frame, before interpolation to image
    stamps): per camera index CC `camera_CC_{stamps_ns,positions,quats}` and `tool_*`, for
    trajectory export (stamps ns, positions m, quaternions x y z w)."""
    arrays = {}
    for name, stream in [*((f"camera_{c:02d}", s) for c, s in enumerate(cameras)),
                         ("tool", tool)]:
        arrays[f"{name}_stamps_ns"] = stream.stamps_ns.astype(np.int64)
        arrays[f"{name}_positions"] = stream.positions.astype(np.float64)
        arrays[f"{name}_quats"] = stream.quats.astype(np.float64)
    write_npz(RunLayout.ingest_streams(root), **arrays)


def load_pose_streams(root: Path) -> dict[str, PoseStream]:
    """{"camera_CC" | "tool": stream} as saved by `save_pose_streams` ({} for a run ingested
    before streams were kept)."""
    path = RunLayout.ingest_streams(root)
    if not path.is_file():
        return {}
    with np.load(path, allow_pickle=False) as z:
        names = sorted({k.rsplit("_", 2)[0] for k in z.files if k.endswith("_stamps_ns")})
        return {n: PoseStream(z[f"{n}_stamps_ns"], z[f"{n}_positions"], z[f"{n}_quats"])
                for n in names}


def save_ingested(log: IngestedLog) -> None:
    """Write cameras.json and frames.npz (images are written by ingest as it streams)."""
    root = log.root
    write_json(
        RunLayout.ingest_cameras(root),
        {
            "cameras": list(log.cameras),
            "models": [m.to_dict() for m in log.models],
            "report": log.report,
        },
    )
    write_npz(
        RunLayout.ingest_frames(root),
        stamps_ns=log.stamps_ns.astype(np.int64),
        image_stamps_ns=log.image_stamps_ns.astype(np.int64),
        poses=log.poses,
        usable=log.usable,
        tool_poses=log.tool_poses,
        extra_tool_poses=log.extra_tool_poses,
        joint_names=np.array(log.joint_names, dtype=str),
        joint_positions=log.joint_positions,
        image_paths=np.array(log.image_paths, dtype=str).reshape(
            len(log.stamps_ns), len(log.cameras)
        ),
    )


def load_ingested(root: Path) -> IngestedLog:
    """Load `RUN/ingest/`; raises RunFolderError if ingest has not completed.

    Loaded once per process and ingest folder (a worker registers many frames; reading
    frames.npz again for each would cost O(T) per frame, ~0.3 s at 100k frames): the files
    are replaced, never rewritten in place, so their device, inode, times and size identify
    them. The arrays are read-only, shared by every caller of the process."""
    root = Path(root)
    try:
        stamp = ingest_identity(root)
    except FileNotFoundError as exc:
        raise RunFolderError(f"{root}: no ingested data; run `surgrecon ingest` first") from exc
    return _load_ingested(str(root), stamp)


def ingest_identity(root: Path | str) -> tuple[tuple[int, ...], ...]:
    """The identity of `RUN/ingest/`'s files (io/atomic.file_identity), for caches of what
    is derived from them. Raises FileNotFoundError before ingest has completed."""
    return file_identity(RunLayout.ingest_cameras(Path(root)), RunLayout.ingest_frames(Path(root)))


@functools.lru_cache(maxsize=2)
def _load_ingested(root_name: str, _stamp: tuple[tuple[int, ...], ...]) -> IngestedLog:
    root = Path(root_name)
    try:
        meta = json.loads(RunLayout.ingest_cameras(root).read_text())
        with np.load(RunLayout.ingest_frames(root), allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except FileNotFoundError as exc:
        raise RunFolderError(f"{root}: no ingested data; run `surgrecon ingest` first") from exc
    for array in arrays.values():
        array.flags.writeable = False
    return IngestedLog(
        root=root,
        cameras=tuple(meta["cameras"]),
        models=tuple(CameraModel.from_dict(m) for m in meta["models"]),
        stamps_ns=arrays["stamps_ns"],
        image_stamps_ns=arrays["image_stamps_ns"],
        poses=arrays["poses"],
        usable=arrays["usable"],
        tool_poses=arrays["tool_poses"],
        joint_names=tuple(str(n) for n in arrays["joint_names"]),
        joint_positions=arrays["joint_positions"],
        image_paths=tuple(tuple(str(p) for p in row) for row in arrays["image_paths"]),
        report=meta.get("report", {}),
        extra_tool_poses=arrays.get("extra_tool_poses", np.zeros((0, 0, 4, 4))),
    )


@dataclass(frozen=True)
class VideoPackets:
    """A video camera's packets as recorded (from its first keyframe): format "h264" or
    "h265", data (B,) uint8 all packets back to back, sizes (P,) bytes and stamps_ns (P,)
    of each."""

    format: str
    data: np.ndarray
    sizes: np.ndarray
    stamps_ns: np.ndarray

    def packets(self) -> list[tuple[int, bytes]]:
        """(stamp_ns, bytes) of every packet, in recorded order."""
        ends = np.cumsum(self.sizes)
        return [(int(s), self.data[e - n:e].tobytes())
                for s, e, n in zip(self.stamps_ns, ends, self.sizes, strict=True)]


def save_video(root: Path, camera_index: int, video: VideoPackets) -> None:
    """`ingest/video/CC.npz` of camera index CC."""
    write_npz(RunLayout.ingest_video(root, camera_index), format=np.array(video.format),
              data=video.data, sizes=video.sizes, stamps_ns=video.stamps_ns)


def load_video(root: Path, camera_index: int) -> VideoPackets | None:
    """Camera index CC's packets as recorded, None for a camera that is not a video."""
    path = RunLayout.ingest_video(Path(root), camera_index)
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            return VideoPackets(str(z["format"]), z["data"], z["sizes"], z["stamps_ns"])
    except (OSError, ValueError, KeyError) as exc:
        raise RunFolderError(f"{path}: unreadable ({exc}); re-run ingest") from exc
