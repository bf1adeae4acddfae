"""Pose-guided feature matching and multi-camera tracks.

Matches must agree with the epipolar geometry of the *tracked* relative pose (no RANSAC
fundamental matrix is estimated): the Lowe ratio test is run among the candidates within
`epipolar_px` of the epipolar line, and matches must be mutual best.
"""

from __future__ import annotations

import numpy as np

from .features import Features
from .geometry import invert_pose


def essential_matrix(pose_i: np.ndarray, pose_j: np.ndarray) -> np.ndarray:
    """E with x_j^T E x_i = 0 for normalised homogeneous points, from camera-to-world poses."""
    rel = invert_pose(pose_j) @ pose_i  # camera i -> camera j
    R, t = rel[:3, :3], rel[:3, 3]
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    return tx @ R


def epipolar_distance_px(
    E: np.ndarray, xi: np.ndarray, xj: np.ndarray, f_i: float, f_j: float
) -> np.ndarray:
    """Symmetric epipolar distance (Ni, Nj) in px between all normalised points xi (Ni, 2)
    and xj (Nj, 2); focal lengths convert normalised units to pixels."""
    hi = np.column_stack([xi, np.ones(len(xi))])
    hj = np.column_stack([xj, np.ones(len(xj))])
    lines_j = hi @ E.T  # epipolar lines in image j of points of i (Ni, 3)
    lines_i = hj @ E  # lines in image i of points of j (Nj, 3)
    alg = lines_j @ hj.T  # x_j^T E x_i  (Ni, Nj)
    nj = np.linalg.norm(lines_j[:, :2], axis=1)[:, None]
    ni = np.linalg.norm(lines_i[:, :2], axis=1)[None, :]
    return 0.5 * np.abs(alg) * (f_j / nj + f_i / ni)


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


def match_pair(
    fi: Features,
    fj: Features,
    pose_i: np.ndarray,
    pose_j: np.ndarray,
    f_i: float,
    f_j: float,
    ratio: float,
    epipolar_px: float,
    depth_range: tuple[float, float],
) -> np.ndarray:
    """Indices (M, 2) of mutual, ratio-tested matches between two images that lie within
    `epipolar_px` of each other's epipolar lines and triangulate inside `depth_range` (m)
    of camera i: the candidates of a feature are a short epipolar segment, not a line."""
    if len(fi) < 2 or len(fj) < 2:
        return np.zeros((0, 2), int)
    E = essential_matrix(pose_i, pose_j)
    geometric_ok = epipolar_distance_px(E, fi.normalized, fj.normalized, f_i, f_j) <= epipolar_px
    ia, jb = np.nonzero(geometric_ok)
    z = ray_depths(fi.normalized[ia], fj.normalized[jb], pose_i, pose_j)
    outside = ~((z >= depth_range[0]) & (z <= depth_range[1]))
    geometric_ok[ia[outside], jb[outside]] = False
    di, dj = fi.descriptors, fj.descriptors
    d2 = (di**2).sum(1)[:, None] + (dj**2).sum(1)[None, :] - 2.0 * (di @ dj.T)
    d2 = np.maximum(d2, 0.0)
    # Ambiguity is judged against every other feature: the runner-up is the second best
    # inside the epipolar segment or the best outside it, whichever is closer. (A lone
    # candidate in the segment would otherwise always pass the ratio test.)
    best_outside = np.where(geometric_ok, np.inf, d2).min(axis=1)
    d2 = np.where(geometric_ok, d2, np.inf)
    order = np.argpartition(d2, 1, axis=1)[:, :2]
    rows = np.arange(len(di))
    best, second = d2[rows, order[:, 0]], d2[rows, order[:, 1]]
    swap = second < best
    best_idx = np.where(swap, order[:, 1], order[:, 0])
    best, second = np.minimum(best, second), np.minimum(np.maximum(best, second), best_outside)
    passes = np.isfinite(best) & (best < (ratio**2) * second)  # squared distances
    mutual = np.argmin(d2, axis=0)[best_idx] == rows
    keep = passes & mutual
    return np.column_stack([rows[keep], best_idx[keep]])


def build_tracks(
    n_features: list[int],
    sequence: list[tuple[int, int]],
    pair_matches: dict[tuple[int, int], np.ndarray],
) -> tuple[list[np.ndarray], int]:
    """Chain pairwise matches into tracks, merging pairs in `sequence` order (union-find).

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

    for i, j in sequence:
        for a, b in (pair_matches[(i, j)] + [offsets[i], offsets[j]]).tolist():
            ra, rb = find(a), find(b)
            if ra != rb and not cameras_of[ra] & cameras_of[rb]:
                parent[rb] = ra
                cameras_of[ra] |= cameras_of[rb]
    roots = np.array([find(a) for a in range(total)], dtype=int)
    size = np.bincount(roots, minlength=total)
    tracked = size[roots] >= 2
    _, track = np.unique(roots[tracked], return_inverse=True)
    ids = np.full(total, -1)
    ids[tracked] = track
    n_tracks = int(track.max()) + 1 if tracked.any() else 0
    return [ids[offsets[k] : offsets[k + 1]] for k in range(len(n_features))], n_tracks
