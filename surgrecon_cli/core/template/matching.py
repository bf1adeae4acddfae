"""Pose-guided feature matching and multi-camera tracks.

Matches must agree with the epipolar geometry of the *tracked* relative pose (no RANSAC
fundamental matrix is estimated): the Lowe ratio test is run among the candidates within
`epipolar_px` of the epipolar line, and matches must be mutual best.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..geometry.poses import invert_pose
from .features import Features

BLOCK_CELLS = 1 << 22  # ours: float32 cells (16 MB) of one block of a matching matrix
SAMPLE_STRIDE = 8  # ours: the ratio test's first pass sees every 8th descriptor of the other image


def essential_matrix(pose_i: np.ndarray, pose_j: np.ndarray) -> np.ndarray:
    """E with x_j^T E x_i = 0 for normalised homogeneous points, from camera-to-world poses."""
    rel = invert_pose(pose_j) @ pose_i  # camera i -> camera j
    R, t = rel[:3, :3], rel[:3, 3]
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    return tx @ R


def row_blocks(n_rows: int, n_cols: int) -> list[slice]:
    """Slices of at most BLOCK_CELLS // n_cols rows: the blocks a (n_rows, n_cols) float32
    matrix is computed in, so memory stays bounded (16 MB a block) at any feature count."""
    step = max(1, BLOCK_CELLS // max(n_cols, 1))
    return [slice(s, min(s + step, n_rows)) for s in range(0, n_rows, step)]


def epipolar_candidates(
    E: np.ndarray, xi: np.ndarray, xj: np.ndarray, f_i: float, f_j: float, tol_px: float
) -> tuple[np.ndarray, np.ndarray]:
    """All pairs (ia, jb) of normalised points xi (Ni, 2), xj (Nj, 2) whose symmetric epipolar
    distance is at most `tol_px` (focal lengths f convert normalised units to pixels); sorted
    by ia, then jb.

    Every point lies on one epipolar plane (the plane through both camera centres and its
    ray); with E = [t]x R its normal, in camera j, is E x̃_i for a point of i and t × x̃_j
    for a point of j, perpendicular to the baseline t. Two points at plane angle difference
    Δ (about the baseline) are at least 0.5 |sin Δ| (A_i f_i + B_j f_j) px from each other's
    epipolar lines, where A, B (≥ 0, normalised units) are the components of their rays
    across the baseline. So the points of j are sorted by plane angle once and each point
    of i takes, by binary search, the band of angles that bound allows (using the smallest
    B_j of image j); the exact distance then decides among the band's points. The band
    never misses a pair: the result is that of testing every pair.
    """
    empty = np.zeros(0, int)
    scale2 = 0.5 * float((E * E).sum())  # |t|² of E = [t]x R
    if len(xi) == 0 or len(xj) == 0 or scale2 == 0.0:
        return empty, empty.copy()
    t = np.linalg.svd(E)[0][:, 2] * np.sqrt(scale2)  # E^T t = 0
    t_unit = t / np.linalg.norm(t)
    u1 = np.cross(t_unit, [1.0, 0.0, 0.0] if abs(t_unit[0]) < 0.9 else [0.0, 1.0, 0.0])
    u1 /= np.linalg.norm(u1)
    u2 = np.cross(t_unit, u1)
    hj = np.column_stack([xj, np.ones(len(xj))])
    normal_i = np.column_stack([xi, np.ones(len(xi))]) @ E.T  # (Ni, 3), = t × R x̃_i
    normal_j = np.cross(t, hj)  # (Nj, 3)
    angle_i = np.mod(np.arctan2(normal_i @ u2, normal_i @ u1), np.pi)
    angle_j = np.mod(np.arctan2(normal_j @ u2, normal_j @ u1), np.pi)
    length = np.sqrt(scale2)
    across_i = np.linalg.norm(normal_i, axis=1) / length  # A_i
    across_j = np.linalg.norm(normal_j, axis=1) / length  # B_j
    with np.errstate(divide="ignore"):
        sin_max = 2.0 * tol_px / (across_i * f_i + across_j.min() * f_j)
    # half-width of the band (rad), widened against rounding; pi: every point of j
    half = np.where(sin_max < 1.0, np.arcsin(np.minimum(sin_max, 1.0)) * 1.0001 + 1e-9, np.pi)
    order = np.argsort(angle_j, kind="stable")
    sorted_j = angle_j[order]
    n_j = len(xj)
    wrapped = np.concatenate([sorted_j - np.pi, sorted_j, sorted_j + np.pi])
    whole = half >= 0.5 * np.pi
    lo = np.where(whole, n_j, np.searchsorted(wrapped, angle_i - half, side="left"))
    hi = np.where(whole, 2 * n_j, np.searchsorted(wrapped, angle_i + half, side="right"))
    count = hi - lo
    ia = np.repeat(np.arange(len(xi)), count)
    within = np.arange(len(ia)) - np.repeat(np.cumsum(count) - count, count)
    jb = order[(lo[ia] + within) % n_j]
    # the symmetric distance (`epipolar_distances_px`) from per-point lines and norms
    norm_j = np.linalg.norm(normal_i[:, :2], axis=1)  # of the lines in j
    norm_i = np.linalg.norm((hj @ E)[:, :2], axis=1)  # of the lines in i
    alg = np.abs(np.einsum("ij,ij->i", normal_i[ia], hj[jb]))
    keep = 0.5 * alg * (f_j / norm_j[ia] + f_i / norm_i[jb]) <= tol_px
    ia, jb = ia[keep], jb[keep]
    by_pair = np.lexsort((jb, ia))
    return ia[by_pair], jb[by_pair]


def epipolar_distances_px(E: np.ndarray, xi: np.ndarray, xj: np.ndarray, f_i: float,
                          f_j: float) -> np.ndarray:
    """Symmetric epipolar distance (M,) px of matched normalised points xi, xj (M, 2): the
    mean of each point's distance to the other's epipolar line, in its image's pixels."""
    hi = np.column_stack([xi, np.ones(len(xi))])
    hj = np.column_stack([xj, np.ones(len(xj))])
    lines_j, lines_i = hi @ E.T, hj @ E
    alg = np.abs((lines_j * hj).sum(1))
    return 0.5 * alg * (f_j / np.linalg.norm(lines_j[:, :2], axis=1)
                        + f_i / np.linalg.norm(lines_i[:, :2], axis=1))


def _first_per_group(group: np.ndarray, value: np.ndarray, n_groups: int):
    """Per group id: index of the smallest value (the first such on ties) and the two
    smallest values (inf if none): one stable sort of `group`, then linear passes."""
    order = np.argsort(group, kind="stable")
    g, v = group[order], value[order]
    best_idx = np.full(n_groups, -1)
    best = np.full(n_groups, np.inf)
    second = np.full(n_groups, np.inf)
    if len(g) == 0:
        return best_idx, best, second
    starts = np.flatnonzero(np.concatenate([[True], g[1:] != g[:-1]]))
    lowest = np.minimum.reduceat(v, starts)
    segment = np.repeat(np.arange(len(starts)), np.diff(np.append(starts, len(g))))
    at_min = np.flatnonzero(v == lowest[segment])
    first = at_min[np.concatenate([[True], segment[at_min[1:]] != segment[at_min[:-1]]])]
    rest = v.copy()
    rest[first] = np.inf
    ids = g[starts]
    best_idx[ids] = order[first]
    best[ids] = lowest
    second[ids] = np.minimum.reduceat(rest, starts)
    return best_idx, best, second


def ray_depths(
    xi: np.ndarray, xj: np.ndarray, pose_i: np.ndarray, pose_j: np.ndarray,
    pairs: tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """Depth (M,) m in camera i of the closest approach of the rays through normalised
    points xi (M, 2) of camera i and xj (M, 2) of camera j (NaN for parallel rays); with
    `pairs` (ia, jb) (M,) each, of the rays through xi[ia] and xj[jb] (xi, xj then hold each
    image's points once: what depends on one ray is computed once per point)."""
    ia, jb = pairs if pairs is not None else (slice(None), slice(None))
    di = np.column_stack([xi, np.ones(len(xi))]) @ pose_i[:3, :3].T
    dj = np.column_stack([xj, np.ones(len(xj))]) @ pose_j[:3, :3].T
    w0 = pose_i[:3, 3] - pose_j[:3, 3]
    a, c = (di * di).sum(1)[ia], (dj * dj).sum(1)[jb]
    d, e = (di @ w0)[ia], (dj @ w0)[jb]
    b = (di[ia] * dj[jb]).sum(1)
    denom = a * c - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(denom > 1e-12, (b * e - c * d) / denom, np.nan)  # z of x̃ = (x, y, 1)


@dataclass(frozen=True)
class CameraView:
    """One camera's image as matching sees it: its `features`, camera-to-world `pose`
    (4, 4) and `focal` length (px, converting normalised units to pixels)."""

    features: Features
    pose: np.ndarray
    focal: float


@dataclass(frozen=True)
class PairGates:
    """What a pose-guided match between cameras i and j must pass: Lowe's `ratio`, lie
    within `epipolar_px` (px) of each other's epipolar lines and triangulate inside
    `depth_range` (near, far) m of camera i."""

    ratio: float
    epipolar_px: float
    depth_range: tuple[float, float]


def match_pair(view_i: CameraView, view_j: CameraView, gates: PairGates) -> np.ndarray:
    """Indices (M, 2) of mutual, ratio-tested matches between the features of two images
    that pass `gates`: the candidates of a feature are a short epipolar segment, not a
    line."""
    fi, fj, pose_i, pose_j = view_i.features, view_j.features, view_i.pose, view_j.pose
    f_i, f_j = view_i.focal, view_j.focal
    ratio, epipolar_px, depth_range = gates.ratio, gates.epipolar_px, gates.depth_range
    if len(fi) < 2 or len(fj) < 2:
        return np.zeros((0, 2), int)
    E = essential_matrix(pose_i, pose_j)
    ia, jb = epipolar_candidates(E, fi.normalized, fj.normalized, f_i, f_j, epipolar_px)
    z = ray_depths(fi.normalized, fj.normalized, pose_i, pose_j, (ia, jb))
    inside = (z >= depth_range[0]) & (z <= depth_range[1])
    return ratio_mutual_matches(fi.descriptors, fj.descriptors, ia[inside], jb[inside], ratio)


def ratio_mutual_matches(
    da: np.ndarray, db: np.ndarray, ia: np.ndarray, jb: np.ndarray, ratio: float
) -> np.ndarray:
    """Indices (M, 2) of the mutual, ratio-tested matches between descriptors da (Na, 128)
    and db (Nb, 128) float32 among the geometric candidate pairs (ia, jb) (ia ascending).

    Row a's match is its nearest candidate; the Lowe ratio test judges it against every
    other b: the runner-up is the second-best candidate or the best non-candidate,
    whichever is closer (a lone candidate would otherwise always pass). It must also be the
    nearest candidate of its b (mutual). The squared distances of the candidate pairs are
    computed pair by pair; a row's distances to every b only for the rows still matched
    after the mutual check and the ratio test among candidates (in blocks of rows,
    `row_blocks`, never as one Na x Nb matrix), and first to every SAMPLE_STRIDE-th b
    only: a b that beats a row fails it, so the rows it fails need no other b (a template
    at 1920x1080: ~2/3 of them; the same matches)."""
    rows_with, ia = np.unique(ia, return_inverse=True)  # a row without candidates never matches
    da = da[rows_with]
    n_a, n_b = len(da), len(db)
    if n_a == 0 or n_b == 0:
        return np.zeros((0, 2), int)
    sq_a, sq_b = (da * da).sum(1).astype(float), (db * db).sum(1)
    # |x|² + |y|² - 2 x.y, as float32 up to the row's |x|² (added in float64)
    part = np.empty(len(ia), np.float32)
    step = max(1, BLOCK_CELLS // da.shape[1])
    for s in range(0, len(ia), step):
        a, b = ia[s:s + step], jb[s:s + step]
        part[s:s + step] = np.einsum("ij,ij->i", da[a], db[b]) * np.float32(-2.0) + sq_b[b]
    d2 = np.maximum(part + sq_a[ia], 0.0)
    best_c, best, second = _first_per_group(ia, d2, n_a)
    col_c, _, _ = _first_per_group(jb, d2, n_b)  # ties: the earliest row
    col_row = np.where(col_c >= 0, ia[np.maximum(col_c, 0)], -1)
    best_b = jb[best_c]  # every row has a candidate
    rows_all = np.arange(n_a)
    alive = (col_row[best_b] == rows_all) & (best < (ratio**2) * second)
    # the best non-candidate can still be closer than the second candidate. A row that
    # fails is mostly beaten by many b, so every SAMPLE_STRIDE-th b fails most of them
    # first (any b that beats a row fails it, as the nearest would); the rest see every b.
    for columns in (np.arange(0, n_b, SAMPLE_STRIDE), np.arange(n_b)):
        alive &= ~_beaten((da, sq_a), (db, sq_b), np.flatnonzero(alive), columns,
                          (best_b, best), ratio**2)
    return np.column_stack([rows_with[alive], best_b[alive]])


def _beaten(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray],
            check: np.ndarray, columns: np.ndarray, best: tuple[np.ndarray, np.ndarray],
            ratio2: float) -> np.ndarray:
    """(Na,) bool, True for the rows `check` of descriptors a = (da (Na, 128) float32, their
    squared norms sq_a) beaten in the ratio test by a descriptor of b = (db (Nb, 128),
    sq_b) among `columns` (ascending) other than the row's best: best = (its index best_b
    (Na,), its squared distance (Na,)), beaten when that distance >= ratio2 x the other's.
    Computed in blocks of rows (`row_blocks`)."""
    (da, sq_a), (db, sq_b), (best_b, best_d2) = a, b, best
    out = np.zeros(len(da), bool)
    n_c = len(columns)
    db, sq_b = db[columns], sq_b[columns]
    at = np.minimum(np.searchsorted(columns, best_b), n_c - 1)  # the best's column, if there
    for rows in row_blocks(len(check), n_c):
        r = check[rows]
        full = da[r] @ db.T
        full *= -2.0
        full += sq_b
        own = np.flatnonzero(columns[at[r]] == best_b[r])
        full[own, at[r[own]]] = np.inf
        runner = np.maximum(full.min(axis=1) + sq_a[r], 0.0)
        out[r] = best_d2[r] >= ratio2 * runner
    return out


def build_tracks(
    n_features: list[int], merges: Sequence[tuple[int, int, np.ndarray]]
) -> tuple[list[np.ndarray], int]:
    """Chain matches into tracks, merging in `merges` order (union-find); each merge is
    (camera i, camera j, (M, 2) feature indices in i and j).

    A merge that would put two features of one image into one track is refused, so
    the earlier (better-conditioned, better-matched) pairs of the sequence win conflicts.
    Returns per camera the track id (N_c,) of each feature (-1 = untracked) and the number
    of tracks. The loop runs over matches (thousands), once per template.
    """
    offsets = np.concatenate([[0], np.cumsum(n_features)]).astype(int)
    total = int(offsets[-1])
    camera = np.repeat(np.arange(len(n_features)), n_features)
    parent = list(range(total))
    cameras_of = [1 << int(c) for c in camera]  # bitmask of cameras in each root's track

    def find(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for i, j, matches in merges:
        for a, b in (matches + offsets[[i, j]]).tolist():
            ra, rb = find(a), find(b)
            if ra != rb and not cameras_of[ra] & cameras_of[rb]:
                parent[rb] = ra
                cameras_of[ra] |= cameras_of[rb]
    roots = np.array(parent, dtype=int)
    while not np.array_equal(roots[roots], roots):  # pointer jumping to every feature's root
        roots = roots[roots]
    size = np.bincount(roots, minlength=total)
    tracked = size[roots] >= 2
    _, track = np.unique(roots[tracked], return_inverse=True)
    ids = np.full(total, -1)
    ids[tracked] = track
    n_tracks = int(track.max()) + 1 if tracked.any() else 0
    return [ids[offsets[k] : offsets[k + 1]] for k in range(len(n_features))], n_tracks
