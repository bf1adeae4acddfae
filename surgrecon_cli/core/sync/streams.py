"""Time synchronisation of a multi-camera log: frames from image stamps, poses at image times.

Pure numpy. A *frame* is the set of images (at most one per camera) whose stamps lie within
the sync tolerance of each other (`ingest.sync_tolerance_ms`). Tracker and robot streams
are interpolated (linear position, slerp rotation, `geometry.interpolate_poses`) to
image/frame stamps and never extrapolated: a query outside a stream or inside a gap longer
than the limit is invalid.
Stamps are int64 nanoseconds.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from ...errors import InputError
from ..geometry.poses import interpolate_poses, make_pose

QUAT_NORM_TOLERANCE = 1e-3
"""|‖q‖ − 1| above this is an invalid orientation; below it the quaternion is normalised."""
REPEAT_POSITION_M = 1e-3
REPEAT_ROTATION_RAD = float(np.radians(0.1))
"""Samples of one stream at one stamp agree when within these of the first (1 mm, the
accuracy required, and 0.1°, about 1 mm at 0.5 m); otherwise they conflict."""


@dataclass(frozen=True)
class FrameGrouping:
    """Images grouped into frames.

    stamps_ns (T,) int64: frame stamp = median of its image stamps, increasing;
    image_index (T, C) int64: index into camera c's sorted stamps, -1 = no image in that frame;
    duplicates (C,) int: images left out because the camera already had one in that frame;
    late (C,) int: images that matched no other camera's image within the tolerance (they form a
    frame of their own; only counted when there are several cameras).
    """

    stamps_ns: np.ndarray
    image_index: np.ndarray
    duplicates: np.ndarray
    late: np.ndarray

    @property
    def n_frames(self) -> int:
        return int(self.stamps_ns.shape[0])


def group_frames(image_stamps_ns: Sequence[np.ndarray], tolerance_ns: int) -> FrameGrouping:
    """Group per-camera image stamps (C arrays of (N_c,) int64 ns, each sorted) into frames.

    Greedy in time: a frame starts at the earliest image not yet used and takes every image up
    to `tolerance_ns` later, at most one per camera (the earliest); a camera's further images in
    that window are duplicates. The result does not depend on the order of the cameras.
    """
    if tolerance_ns <= 0:
        raise ValueError(f"tolerance_ns must be > 0, got {tolerance_ns}")
    n_cams = len(image_stamps_ns)
    stamps = [np.asarray(s, dtype=np.int64) for s in image_stamps_ns]
    for c, s in enumerate(stamps):
        if s.ndim != 1 or (s.size > 1 and np.any(np.diff(s) < 0)):
            raise ValueError(f"camera {c}: image stamps must be a sorted 1-D array")
    all_t = np.concatenate(stamps) if n_cams else np.zeros(0, np.int64)
    all_c = np.concatenate([np.full(len(s), c) for c, s in enumerate(stamps)]) if n_cams else all_t
    all_i = np.concatenate([np.arange(len(s)) for s in stamps]) if n_cams else all_t
    order = np.lexsort((all_c, all_t))
    all_t, all_c, all_i = all_t[order], all_c[order], all_i[order]

    rows: list[np.ndarray] = []
    frame_stamps: list[int] = []
    duplicates = np.zeros(n_cams, dtype=np.int64)
    late = np.zeros(n_cams, dtype=np.int64)
    start = 0
    while start < len(all_t):
        stop = int(np.searchsorted(all_t, all_t[start] + tolerance_ns, side="right"))
        row = np.full(n_cams, -1, dtype=np.int64)
        used: list[int] = []
        for k in range(start, stop):
            c = int(all_c[k])
            if row[c] >= 0:
                duplicates[c] += 1
            else:
                row[c] = all_i[k]
                used.append(k)
        if len(used) == 1 and n_cams > 1:
            late[int(all_c[used[0]])] += 1
        rows.append(row)
        frame_stamps.append(_median_ns(all_t[used]))
        start = stop
    image_index = np.array(rows, dtype=np.int64).reshape(len(rows), n_cams)
    return FrameGrouping(np.array(frame_stamps, dtype=np.int64), image_index, duplicates, late)


@dataclass(frozen=True)
class PoseStream:
    """A validated pose stream: stamps (M,) int64 ns strictly increasing, positions (M, 3) m,
    unit quaternions (M, 4) x y z w."""

    stamps_ns: np.ndarray
    positions: np.ndarray
    quats: np.ndarray
    conflict_stamps_ns: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    conflict_sizes: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    """Stamps (K,) ns where samples conflicted and were dropped (`validate_pose_stream`),
    and their largest disagreement (K, 2): position m, rotation rad."""
    constant: bool = False
    """The one sample holds at every stamp (a chain of latched `/tf_static` transforms: a
    rig fixed in the world), not only between samples."""

    def __len__(self) -> int:
        return int(self.stamps_ns.shape[0])


def nearest_stamps(stamps_ns: np.ndarray, query_ns: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """For each query stamp (N,) ns, the index (N,) of the nearest of stamps (T,) ns
    (increasing, T >= 1; the earlier on a tie) and its distance (N,) ns from it."""
    hi = np.clip(np.searchsorted(stamps_ns, query_ns), 0, len(stamps_ns) - 1)
    lo = np.clip(hi - 1, 0, None)
    near = np.where(np.abs(stamps_ns[hi] - query_ns) < np.abs(stamps_ns[lo] - query_ns), hi, lo)
    return near, np.abs(stamps_ns[near] - query_ns)


def select_frames(stamps_ns: np.ndarray, start_s: float, duration_s: float, every: int
                  ) -> np.ndarray:
    """The frames (K,) of frame stamps (T,) ns to keep: from `start_s` s after the first
    frame for `duration_s` s (0: to the end; the window is half-open), every `every`-th of
    them, the first kept. Empty when none falls in the window."""
    since = (np.asarray(stamps_ns, np.int64) - int(stamps_ns[0])) / 1e9
    inside = since >= start_s - 1e-9
    if duration_s > 0:
        inside &= since < start_s + duration_s - 1e-9
    return np.flatnonzero(inside)[::max(int(every), 1)]


def validate_pose_stream(
    name: str, stamps_ns: np.ndarray, positions: np.ndarray, quats: np.ndarray
) -> PoseStream:
    """Sort by stamp, check and normalise the quaternions, resolve repeated stamps.

    stamps_ns (M,), positions (M, 3), quats (M, 4). Raises `InputError` naming `name` (the
    topic) and the stamp of the first non-finite value or non-unit quaternion
    (|‖q‖ − 1| > 1e-3); smaller deviations are normalised away.

    Several samples at one stamp: when they all agree with the first (within
    `REPEAT_POSITION_M` and `REPEAT_ROTATION_RAD`; a message recorded twice) the first is
    kept; when they conflict, none can be trusted and all are dropped (the stream is
    interpolated across that stamp from its neighbours, within the gap limit), listed in
    the result's `conflict_stamps_ns` / `conflict_sizes` for the caller to warn about.
    """
    stamps = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
    pos = np.asarray(positions, dtype=float).reshape(-1, 3)
    q = np.asarray(quats, dtype=float).reshape(-1, 4)
    if not (len(stamps) == len(pos) == len(q)):
        raise ValueError(f"{name}: {len(stamps)} stamps, {len(pos)} positions, {len(q)} quats")
    order = np.argsort(stamps, kind="stable")
    stamps, pos, q = stamps[order], pos[order], q[order]
    bad = ~(np.isfinite(pos).all(axis=1) & np.isfinite(q).all(axis=1))
    if bad.any():
        k = int(np.argmax(bad))
        raise InputError(
            f"{name}: pose at stamp {fmt_stamp(stamps[k])} has non-finite values "
            f"(position {pos[k].tolist()}, orientation {q[k].tolist()})"
        )
    norms = np.linalg.norm(q, axis=1)
    off = np.abs(norms - 1.0) > QUAT_NORM_TOLERANCE
    if off.any():
        k = int(np.argmax(off))
        raise InputError(
            f"{name}: pose at stamp {fmt_stamp(stamps[k])} has a non-unit quaternion "
            f"(|q| = {norms[k]:.6g}, expected 1 within {QUAT_NORM_TOLERANCE:g})"
        )
    q = q / norms[:, None]
    first = np.ones(len(stamps), dtype=bool)  # the first sample of each stamp
    first[1:] = np.diff(stamps) > 0
    starts = np.flatnonzero(first)
    group = np.cumsum(first) - 1
    lead = starts[group]
    moved = np.linalg.norm(pos - pos[lead], axis=1)
    turned = 2 * np.arccos(np.clip(np.abs(np.einsum("ij,ij->i", q, q[lead])), 0.0, 1.0))
    size = np.stack([moved, turned], axis=1)
    size = np.maximum.reduceat(size, starts, axis=0) if len(starts) else size
    conflict = (size[:, 0] > REPEAT_POSITION_M) | (size[:, 1] > REPEAT_ROTATION_RAD)
    keep = first & ~conflict[group]
    return PoseStream(stamps[keep], pos[keep], q[keep], stamps[starts[conflict]],
                      size[conflict])


def poses_at(
    stream: PoseStream, query_ns: np.ndarray, max_gap_ns: int
) -> tuple[np.ndarray, np.ndarray]:
    """Interpolated poses (Q, 4, 4) at stamps (Q,) ns, NaN where invalid, and valid (Q,) bool.

    Invalid: before the first / after the last sample, or inside a gap > `max_gap_ns`; a
    constant stream is valid everywhere.
    """
    query = np.asarray(query_ns, dtype=np.int64).reshape(-1)
    out = np.full((len(query), 4, 4), np.nan)
    if len(query) == 0:
        return out, np.zeros(0, dtype=bool)
    if stream.constant and len(stream):
        out[:] = make_pose(stream.positions[:1], stream.quats[:1])
        return out, np.ones(len(query), dtype=bool)
    pos, quat, valid = interpolate_poses(
        stream.stamps_ns, stream.positions, stream.quats, query, int(max_gap_ns)
    )
    if valid.any():
        out[valid] = make_pose(pos[valid], quat[valid])
    return out, valid


def interpolate_values(
    stamps_ns: np.ndarray, values: np.ndarray, query_ns: np.ndarray, max_gap_ns: int
) -> np.ndarray:
    """Linear interpolation of samples (M, J) at sorted stamps (M,) to query stamps (Q,).

    Returns (Q, J); NaN outside the samples or inside gaps > `max_gap_ns` (never extrapolated).
    NaN samples stay NaN in the result wherever they are used.
    """
    stamps = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
    vals = np.asarray(values, dtype=float)
    vals = vals[:, None] if vals.ndim == 1 else vals
    if vals.ndim != 2 or len(vals) != len(stamps):
        raise ValueError(f"values must be (M, J) with M = {len(stamps)}, got {vals.shape}")
    query = np.asarray(query_ns, dtype=np.int64).reshape(-1)
    out = np.full((len(query), vals.shape[1]), np.nan)
    if len(stamps) == 0 or len(query) == 0:
        return out
    hi = np.searchsorted(stamps, query, side="left")
    hi_c = np.clip(hi, 0, len(stamps) - 1)
    exact = stamps[hi_c] == query
    lo_c = np.clip(hi - 1, 0, len(stamps) - 1)
    inside = (hi > 0) & (hi < len(stamps))
    gap = stamps[hi_c] - stamps[lo_c]
    ok = exact | (inside & (gap <= max_gap_ns))
    s = np.where(gap > 0, (query - stamps[lo_c]) / np.where(gap > 0, gap, 1), 1.0)
    s = np.where(exact, 1.0, s)[:, None]
    interp = vals[lo_c] * (1 - s) + vals[hi_c] * s
    exact_rows = np.where(exact)[0]
    interp[exact_rows] = vals[hi_c[exact_rows]]
    out[ok] = interp[ok]
    return out


def base_to_world_pose(base_to_world: Sequence[float]) -> np.ndarray:
    """[x y z qx qy qz qw] (m) -> pose (4, 4); raises `InputError` on a non-unit quaternion."""
    values = np.asarray(base_to_world, dtype=float).reshape(-1)
    if values.shape != (7,) or not np.isfinite(values).all():
        raise InputError(f"tool.base_to_world must be 7 finite numbers, got {values.tolist()}")
    norm = np.linalg.norm(values[3:])
    if abs(norm - 1.0) > QUAT_NORM_TOLERANCE:
        raise InputError(f"tool.base_to_world: quaternion norm {norm:.6g} is not 1")
    return make_pose(values[:3], values[3:] / norm)


MIN_RATE_SPAN_NS = 1_000_000
"""A mean rate needs its messages spread over at least this (1 ms): a burst (latched static
transforms, messages recorded together) has a span of ns to µs and no meaningful rate."""


def mean_rate_hz(count: int, first_ns: int, last_ns: int) -> float:
    """Mean rate (Hz) of `count` messages from first_ns to last_ns; 0 (no rate) with fewer
    than two or a span under MIN_RATE_SPAN_NS."""
    span_ns = last_ns - first_ns
    if count < 2 or span_ns < MIN_RATE_SPAN_NS:
        return 0.0
    return float((count - 1) / (span_ns * 1e-9))


def rate_hz(stamps_ns: np.ndarray) -> float:
    """Mean sample rate (Hz) of sorted stamps (N,) ns (`mean_rate_hz`; 0 = no rate)."""
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    if len(stamps) < 2:
        return 0.0
    return mean_rate_hz(len(stamps), int(stamps[0]), int(stamps[-1]))


def _median_ns(stamps: np.ndarray) -> int:
    """Median of int64 ns stamps in integer arithmetic (floats lose ns at epoch scale)."""
    s = np.sort(stamps)
    n = len(s)
    lo, hi = int(s[(n - 1) // 2]), int(s[n // 2])
    return lo + (hi - lo) // 2


def fmt_stamp(stamp_ns: int | np.integer) -> str:
    """ns -> 'S.NNNNNNNNN s' (exact: no float rounding)."""
    stamp = int(stamp_ns)
    return f"{stamp // 1_000_000_000}.{stamp % 1_000_000_000:09d} s"
