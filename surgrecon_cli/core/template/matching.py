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
    distance is at most `tol_px` (focal lengths f convert normalised units to pixels); ia
    ascending.

    A float32 pass over the algebraic error x_j^T E x_i, in blocks of rows, with a per-row
    bound that never misses a pair, then the exact distance on the few survivors.
    """
    hi = np.column_stack([xi, np.ones(len(xi))])
    hj = np.column_stack([xj, np.ones(len(xj))])
    lines_j = hi @ E.T  # epipolar lines in image j of the points of i (Ni, 3)
    lines_i = hj @ E  # lines in image i of the points of j (Nj, 3)
    nj = np.linalg.norm(lines_j[:, :2], axis=1)
    ni = np.linalg.norm(lines_i[:, :2], axis=1)
    # distance = 0.5 |alg| (f_j / nj[i] + f_i / ni[j]) >= 0.5 |alg| (f_j / nj[i] + f_i / max ni)
    bound = (tol_px / (0.5 * (f_j / nj + f_i / ni.max(initial=0.0))) * 1.0001).astype(np.float32)
    lines32, hj32 = lines_j.astype(np.float32), hj.T.astype(np.float32)
    found = []
    blocks = row_blocks(len(xi), len(xj))
    size = (blocks[0].stop if blocks else 0, len(xj))
    buffer, screen = np.empty(size, np.float32), np.empty(size, bool)
    for rows in blocks:
        alg = np.abs(lines32[rows] @ hj32, out=buffer[: rows.stop - rows.start])  # (block, Nj)
        ia, jb = np.nonzero(np.less_equal(alg, bound[rows, None], out=screen[: len(alg)]))
        found.append((ia + rows.start, jb))
    ia = np.concatenate([f[0] for f in found]) if found else np.zeros(0, int)
    jb = np.concatenate([f[1] for f in found]) if found else np.zeros(0, int)
    keep = epipolar_distances_px(E, xi[ia], xj[jb], f_i, f_j) <= tol_px
    return ia[keep], jb[keep]


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
    """Per group id: index of the smallest value and the two smallest values (inf if none)."""
    order = np.lexsort((value, group))
    g, v = group[order], value[order]
    start = np.ones(len(g), bool)
    start[1:] = g[1:] != g[:-1]
    best_pos = np.flatnonzero(start)
    best_idx = np.full(n_groups, -1)
    best = np.full(n_groups, np.inf)
    second = np.full(n_groups, np.inf)
    best_idx[g[best_pos]] = order[best_pos]
    best[g[best_pos]] = v[best_pos]
    has_second = best_pos + 1 < len(g)
    has_second[has_second] &= ~start[best_pos[has_second] + 1]
    second[g[best_pos[has_second]]] = v[best_pos[has_second] + 1]
    return best_idx, best, second


def ray_depths(
    xi: np.ndarray, xj: np.ndarray, pose_i: np.ndarray, pose_j: np.ndarray
) -> np.ndarray:
    """Depth (M,) m in camera i of the closest approach of the rays through normalised
    points xi (M, 2) of camera i and xj (M, 2) of camera j (NaN for parallel rays)."""
    di = np.column_stack([xi, np.ones(len(xi))]) @ pose_i[:3, :3].T
    dj = np.column_stack([xj, np.ones(len(xj))]) @ pose_j[:3, :3].T
    w0 = pose_i[:3, 3] - pose_j[:3, 3]
    a, b, c = (di * di).sum(1), (di * dj).sum(1), (dj * dj).sum(1)
    d, e = di @ w0, dj @ w0
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
    z = ray_depths(fi.normalized[ia], fj.normalized[jb], pose_i, pose_j)
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
    nearest candidate of its b (mutual). Squared distances are computed in blocks of rows
    (`row_blocks`), never as one Na x Nb matrix; the column bests merge across blocks."""
    rows_with, ia = np.unique(ia, return_inverse=True)  # a row without candidates never matches
    da = da[rows_with]
    n_a, n_b = len(da), len(db)
    sq_a_all, sq_b = (da * da).sum(1), (db * db).sum(1)
    best_b = np.full(n_a, -1)
    passes = np.zeros(n_a, bool)
    col_d2 = np.full(n_b, np.inf)
    col_row = np.full(n_b, -1)
    bounds = np.searchsorted(ia, [(r.start, r.stop) for r in row_blocks(n_a, n_b)])
    for (lo, hi), rows in zip(bounds, row_blocks(n_a, n_b), strict=True):
        # |x|² + |y|² - 2 x.y; the row's |x|² is added only where a value is used.
        part = da[rows] @ db.T
        part *= -2.0
        part += sq_b
        sq_a = sq_a_all[rows].astype(float)
        a, b = ia[lo:hi] - rows.start, jb[lo:hi]
        d2 = np.maximum(part[a, b] + sq_a[a], 0.0)
        best_c, best, second = _first_per_group(a, d2, len(sq_a))
        part[a, b] = np.inf
        second = np.minimum(second, np.maximum(part.min(axis=1) + sq_a, 0.0))
        has = best_c >= 0
        best_b[rows] = np.where(has, b[np.maximum(best_c, 0)], -1)
        passes[rows] = has & (best < (ratio**2) * second)  # squared distances
        col_c, col_best, _ = _first_per_group(b, d2, n_b)
        better = col_best < col_d2  # strict: on a tie the earlier row stays, as in one pass
        col_d2[better] = col_best[better]
        col_row[better] = a[col_c[better]] + rows.start
    rows_all = np.arange(n_a)
    keep = passes & (col_row[np.maximum(best_b, 0)] == rows_all)
    return np.column_stack([rows_with[keep], best_b[keep]])


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
