"""The simulator's ground truth file `NAME.gt.npz` read and validated:
faces (F, 3), vertices (T, V, 3) m, labels (T, V) by core/labels.true_labels, stamps_ns (T,);
optional (files written before the deformation measures lack them): tool_poses (T, 4, 4)
the true tool-tip pose in the world at every frame, indentation_m (T,) the simulator's dent
depth along the tool axis."""

from __future__ import annotations

import zipfile
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ...core.sync.streams import nearest_stamps
from ...errors import InputError
from ..run.folder import file_sha256
from .lfs import refuse_lfs_pointer

_KEYS = ("faces", "vertices", "labels", "stamps_ns")
_OPTIONAL = ("tool_poses", "indentation_m")


@dataclass(frozen=True)
class GroundTruth:
    """faces (F, 3) int; vertices (T, V, 3) m; labels (T, V) uint8; stamps_ns (T,) int64;
    path and SHA-256 of the file it came from; tool_poses (T, 4, 4) and indentation_m (T,)
    m, or None in files that do not have them."""

    path: Path
    sha256: str
    faces: np.ndarray
    vertices: np.ndarray
    labels: np.ndarray
    stamps_ns: np.ndarray
    tool_poses: np.ndarray | None = None
    indentation_m: np.ndarray | None = None

    @property
    def n_frames(self) -> int:
        return int(self.vertices.shape[0])

    def at_stamps(self, stamps_ns: np.ndarray, tolerance_ns: int) -> GroundTruth:
        """The truth at the frames of stamps (K,) ns (a part of the log ingested:
        ingest.start_s / duration_s / every): its frame nearest each stamp, which must lie
        within tolerance_ns; InputError naming the file and the first frame without one."""
        order = np.argsort(self.stamps_ns, kind="stable")
        pick, off = nearest_stamps(self.stamps_ns[order], np.asarray(stamps_ns, np.int64))
        if (off > tolerance_ns).any():
            k = int(np.argmax(off > tolerance_ns))
            raise InputError(f"{self.path}: no ground-truth frame within {tolerance_ns / 1e6:g} "
                             f"ms of the run's frame {k} ({off[k] / 1e6:.1f} ms away): the truth "
                             "of another log?")
        rows = order[pick]
        return replace(self, vertices=self.vertices[rows], labels=self.labels[rows],
                       stamps_ns=self.stamps_ns[rows],
                       tool_poses=None if self.tool_poses is None else self.tool_poses[rows],
                       indentation_m=None if self.indentation_m is None
                       else self.indentation_m[rows])


def gt_path_beside(log_path: Path) -> Path:
    """`NAME.mcap` -> `NAME.gt.npz` in the same folder (where `surgrecon simulate` puts it)."""
    log_path = Path(log_path).absolute()  # `.` (a bag folder) has no name of its own
    return log_path.with_name(log_path.name.removesuffix(".mcap") + ".gt.npz")


def load_ground_truth(path: Path) -> GroundTruth:
    """Read and check a ground-truth file; InputError naming the file on any problem."""
    path = Path(path)
    refuse_lfs_pointer(path, "ground truth")
    try:
        with np.load(path, allow_pickle=False) as z:
            missing = [k for k in _KEYS if k not in z.files]
            if missing:
                raise InputError(f"{path}: not a surgrecon ground truth (missing "
                                 f"{', '.join(missing)}; expected {', '.join(_KEYS)})")
            data = {k: z[k] for k in (*_KEYS, *_OPTIONAL) if k in z.files}
    except FileNotFoundError as exc:
        raise InputError(f"{path}: no such ground-truth file") from exc
    except (OSError, ValueError, zipfile.BadZipFile) as exc:
        raise InputError(f"{path}: unreadable ground truth ({exc})") from exc
    faces, vertices = data["faces"], data["vertices"]
    labels, stamps = data["labels"], data["stamps_ns"]
    if vertices.ndim != 3 or vertices.shape[2] != 3 or vertices.shape[0] < 1:
        raise InputError(f"{path}: vertices must be (T, V, 3), got {vertices.shape}")
    n_frames, n_vertices = vertices.shape[:2]
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
        raise InputError(f"{path}: faces must be (F, 3), got {faces.shape}")
    if faces.min() < 0 or faces.max() >= n_vertices:
        raise InputError(f"{path}: faces index vertices outside 0..{n_vertices - 1}")
    if labels.shape != (n_frames, n_vertices):
        raise InputError(f"{path}: labels must be ({n_frames}, {n_vertices}), got {labels.shape}")
    if stamps.shape != (n_frames,):
        raise InputError(f"{path}: stamps_ns must be ({n_frames},), got {stamps.shape}")
    if not np.isfinite(vertices).all():
        raise InputError(f"{path}: vertices contain NaN/Inf")
    optional = {}
    for key, shape in (("tool_poses", (n_frames, 4, 4)), ("indentation_m", (n_frames,))):
        if key in data:
            if data[key].shape != shape:
                raise InputError(f"{path}: {key} must be {shape}, got {data[key].shape}")
            optional[key] = data[key].astype(float)
    return GroundTruth(path=path, sha256=file_sha256(path), faces=faces.astype(np.int64),
                       vertices=vertices.astype(float), labels=labels.astype(np.uint8),
                       stamps_ns=stamps.astype(np.int64), **optional)
