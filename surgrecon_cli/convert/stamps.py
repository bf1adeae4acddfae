"""Frame stamps and pose files of `convert`.

Stamps file: one stamp per line (the first number of the line; `#` comments, commas and
blanks separate), in seconds, or integer nanoseconds when the values are integers above
1e12 (EuRoC `data.csv`). TUM trajectory: `t x y z qx qy qz qw` per line, t in seconds,
position in metres. Decimal seconds are read exactly (no float rounding of epoch stamps).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from decimal import Decimal, InvalidOperation
from pathlib import Path

import numpy as np

from ..errors import InputError

_NS_THRESHOLD = 10**12
# Ours: a TUM file whose positions span more than MAX_SPAN_M along an axis, or lie farther
# than MAX_REACH_M from its origin, is most likely in millimetres: an endoscope or a tool
# moves centimetres in a recording, and a tracker sees them within a few metres.
MAX_SPAN_M = 0.3
MAX_REACH_M = 10.0
logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class PoseTrack:
    """Poses of one frame over time: stamps (N,) int64 ns, positions (N, 3) m, orientations
    (N, 4) unit quaternions x y z w; `source` the file they were read from."""

    stamps_ns: np.ndarray
    positions: np.ndarray
    orientations: np.ndarray
    source: str = ""


def _rows(path: Path, what: str) -> list[tuple[int, list[str]]]:
    """(line number, words) of the non-empty, non-comment lines of a text file."""
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError as exc:
        raise InputError(f"{what} {path}: cannot be read ({exc.strerror or exc})") from None
    rows = []
    for number, line in enumerate(text.splitlines(), 1):
        words = line.split("#", 1)[0].replace(",", " ").split()
        if words:
            rows.append((number, words))
    if not rows:
        raise InputError(f"{what} {path}: holds no lines")
    return rows


def _seconds_ns(word: str, path: Path, number: int, what: str) -> int:
    try:
        value = Decimal(word)
    except InvalidOperation:
        raise InputError(f"{what} {path} line {number}: {word!r} is not a number") from None
    if not value.is_finite():
        raise InputError(f"{what} {path} line {number}: {word!r} is not a finite time")
    return int(value * 10**9)


def _increasing(stamps: np.ndarray, path: Path, what: str) -> None:
    """InputError unless the stamps increase and none is negative (MCAP log times are
    unsigned: a negative stamp ended convert in an internal error)."""
    if len(stamps) and stamps[0] < 0:
        raise InputError(f"{what} {path}: its first time, {stamps[0] / 1e9:.9g} s, is negative; "
                         "log times cannot be: add the same constant to every time")
    bad = np.flatnonzero(np.diff(stamps) <= 0)
    if bad.size:
        raise InputError(f"{what} {path}: stamps must increase (entry {bad[0] + 2} is not "
                         "after the one before)")


def read_stamps(path: Path) -> np.ndarray:
    """Frame stamps (N,) int64 ns from a stamps file (rules in the module docstring)."""
    rows = _rows(path, "stamps file")
    words = [(n, w[0]) for n, w in rows]
    if all(w.isdigit() for _, w in words) and int(words[0][1]) > _NS_THRESHOLD:
        stamps = np.array([int(w) for _, w in words], dtype=np.int64)
    else:
        stamps = np.array([_seconds_ns(w, path, n, "stamps file") for n, w in words],
                          dtype=np.int64)
    _increasing(stamps, path, "stamps file")
    return stamps


def read_tum(path: Path, what: str) -> PoseTrack:
    """A TUM trajectory file (rules in the module docstring)."""
    rows = _rows(path, what)
    stamps, values = [], []
    for number, words in rows:
        if len(words) != 8:
            raise InputError(f"{what} {path} line {number}: expected 8 values "
                             f"(t x y z qx qy qz qw), found {len(words)}")
        stamps.append(_seconds_ns(words[0], path, number, what))
        try:
            values.append([float(w) for w in words[1:]])
        except ValueError:
            raise InputError(f"{what} {path} line {number}: not numbers") from None
    arr = np.array(values)
    norms = np.linalg.norm(arr[:, 3:], axis=1)
    bad = np.flatnonzero(~np.isfinite(arr).all(axis=1) | (np.abs(norms - 1) > 1e-3))
    if bad.size:
        raise InputError(f"{what} {path} line {rows[bad[0]][0]}: not a finite position and "
                         "unit quaternion")
    track = PoseTrack(np.array(stamps, dtype=np.int64), arr[:, :3], arr[:, 3:] / norms[:, None],
                      str(path))
    _increasing(track.stamps_ns, path, what)
    span = float(np.ptp(track.positions, axis=0).max())
    reach = float(np.linalg.norm(track.positions, axis=1).max())
    if span > MAX_SPAN_M or reach > MAX_REACH_M:
        logger.warning("%s %s: its positions span %.4g m and reach %.4g m from the origin, "
                       "more than an endoscope or tool moves or a tracker sees: TUM positions "
                       "are metres; if these are millimetres (as trackers often write), divide "
                       "them by 1000", what, path, span, reach)
    return track


def frame_stamps(indices: Sequence[int], fps: float | None, stamps_file: Path | None,
                 default_fps: float | None, start_ns: int) -> np.ndarray | None:
    """Stamps (N,) ns of the frames `indices` of the source: from the stamps file (one line per
    source frame), else from `fps` or `default_fps` (frame i at start + i / fps); None when
    neither is given (a video's own presentation times are used, after `start_ns`)."""
    idx = np.asarray(indices, dtype=np.int64)
    if stamps_file is not None:
        stamps = read_stamps(stamps_file)
        if idx.size and idx.max() >= len(stamps):
            raise InputError(f"stamps file {stamps_file}: has {len(stamps)} stamps, frame "
                             f"{int(idx.max())} needs one")
        return stamps[idx]
    rate = fps or default_fps
    if rate is None:
        return None
    return start_ns + np.round(idx * (1e9 / rate)).astype(np.int64)
