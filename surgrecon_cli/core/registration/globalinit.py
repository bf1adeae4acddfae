"""Global initialisation for clouds that start far apart: coarse rotations and a scale.

The clouds' principal axes (PCA of the positions) give two proper rotations (the sign of
the least-spread axis, a surface's normal); each is combined with `SPINS` turns about the
target's least-spread axis, because a surface such as a dome spreads equally in two
directions and its in-plane axes are arbitrary. The
scale is the ratio of the clouds' spreads in their two main directions (the extent of a
surface, unaffected by its thickness/noise). Every candidate is refined by a few trimmed
point-to-point ICP steps on a small subsample; the best few by the trimmed mean distance
are refined further; the best one is returned if it clearly beats the ICP from the identity.
All lengths in the solver's units.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..geometry.poses import fit_rigid

SPINS = 12  # ours: turns about the least-spread axis (30 degrees apart)
COARSE_STEPS = 4  # ours: ICP steps per candidate
KEEP_BEST = 3  # ours: candidates refined further
FINE_STEPS = 20  # ours: ICP steps of the refinement
# ours: a turned start must fit clearly better (trimmed mean distance) than the ICP from the
# identity: a partial view or a symmetric shape fits a wrong turn about as well
GLOBAL_MARGIN = 0.5

# moved points (P, 3) -> index into the target (P,) and distance (P,) of each one's nearest
Nearest = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]


def _axes(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean (3,), principal axes (3, 3) as columns (least spread first) and variances (3,)."""
    c = x.mean(axis=0)
    var, vecs = np.linalg.eigh(np.cov((x - c).T))
    return c, vecs, np.maximum(var, 0.0)


def _spin(axis: np.ndarray, angle: float) -> np.ndarray:
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * (K @ K)


def candidates(source: np.ndarray, target: np.ndarray) -> tuple[list[np.ndarray], float]:
    """Coarse rotations (each (3, 3)) taking the source's axes onto the target's, and the
    scale s (target ~ s R source + t)."""
    _, vs, var_s = _axes(source)
    _, vt, var_t = _axes(target)
    scale = float(np.sqrt(var_t[1:].sum() / max(var_s[1:].sum(), 1e-300)))
    out = []
    for signs in ([1.0, 1.0, 1.0], [-1.0, 1.0, -1.0]):  # the spins cover the other two
        base = vt @ np.diag(signs) @ vs.T
        if np.linalg.det(base) < 0:
            base = vt @ np.diag([signs[0], signs[1], -signs[2]]) @ vs.T
        out += [_spin(vt[:, 0], 2 * np.pi * k / SPINS) @ base for k in range(SPINS)]
    return out, scale


@dataclass(frozen=True)
class _Clouds:
    """What every ICP run aligns: source points `pts` (P, 3), target points `target` (M, 3),
    `nearest` looking moved points up in the target, and the fraction `keep` of the closest
    pairs fitted (trimming)."""

    pts: np.ndarray
    target: np.ndarray
    nearest: Nearest
    keep: float


def _icp(clouds: _Clouds, A: np.ndarray, t: np.ndarray,
         steps: int) -> tuple[np.ndarray, np.ndarray, float]:
    """Trimmed point-to-point ICP of the similarity x -> A x + t (A = s R, s fixed)."""
    pts, target, nearest, keep = clouds.pts, clouds.target, clouds.nearest, clouds.keep
    scale = float(np.cbrt(np.linalg.det(A)))
    for _ in range(steps):
        idx, d = nearest(pts @ A.T + t)
        sel = d <= np.quantile(d, keep)
        R, t = fit_rigid(scale * pts[sel], target[idx[sel]])
        A = scale * R
    _, d = nearest(pts @ A.T + t)
    return A, t, float(np.mean(np.sort(d)[: max(int(keep * len(d)), 1)]))


def global_align(pts: np.ndarray, target: np.ndarray, nearest: Nearest,
                 keep: float) -> tuple[np.ndarray, np.ndarray]:
    """Similarity (A = s R (3, 3), t (3,)) with target ~ pts @ A.T + t from the coarse
    candidates; `nearest(moved)` looks the moved points up in the target."""
    rotations, scale = candidates(pts, target)
    cs, ct = pts.mean(axis=0), target.mean(axis=0)
    clouds = _Clouds(pts, target, nearest, keep)
    tried = []
    for R in rotations:
        A = scale * R
        tried.append(_icp(clouds, A, ct - A @ cs, COARSE_STEPS))
    tried.sort(key=lambda item: item[2])
    refined = [_icp(clouds, A, t, FINE_STEPS) for A, t, _ in tried[:KEEP_BEST]]
    A, t, cost = min(refined, key=lambda item: item[2])
    A0, t0, cost0 = _icp(clouds, np.eye(3), np.zeros(3), FINE_STEPS)
    return (A, t) if cost < GLOBAL_MARGIN * cost0 else (A0, t0)
