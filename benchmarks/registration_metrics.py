"""Error figures of a registered source against its truth (benchmarks/registration.py).

All errors in mm. The normal / tangential split uses the normals of the truth surface,
estimated by local PCA over the 12 nearest truth points (the true moved source, noise-free).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree
from scipy.stats import spearmanr

MM = 1e-3


def pca_normals(points: np.ndarray, k: int = 12) -> np.ndarray:
    """Unit normals (N, 3): smallest-variance direction of each point's k nearest points."""
    nb = points[cKDTree(points).query(points, k=k)[1]]
    centred = nb - nb.mean(1, keepdims=True)
    return np.linalg.eigh(np.einsum("nki,nkj->nij", centred, centred))[1][:, :, 0]


@dataclass(frozen=True)
class Errors:
    """Figures of one registration: median / p95 error, median normal and tangential error
    (mm), median error as % of the bounding-box diagonal, Spearman rank correlation of the
    method's per-point residuals with the true error (NaN without residuals)."""

    median: float
    p95: float
    normal: float
    tangential: float
    percent_diag: float
    spearman: float
    per_point: np.ndarray  # (N,) mm


def errors(registered: np.ndarray, truth: np.ndarray, normals: np.ndarray, diagonal_m: float,
           residuals: np.ndarray | None = None) -> Errors:
    """The figures of registered (N, 3) m against truth (N, 3) m with truth normals (N, 3)."""
    d = (registered - truth) / MM
    e = np.linalg.norm(d, axis=1)
    en = np.abs((d * normals).sum(1))
    et = np.sqrt(np.maximum(e**2 - en**2, 0))
    rho = np.nan
    if residuals is not None:
        ok = np.isfinite(residuals)
        if ok.sum() > 10:
            rho = float(spearmanr(residuals[ok], e[ok]).statistic)
    return Errors(float(np.median(e)), float(np.percentile(e, 95)), float(np.median(en)),
                  float(np.median(et)), float(100 * np.median(e) * MM / diagonal_m), rho, e)


def worst_region_excess(source: np.ndarray, ours: np.ndarray, nothing: np.ndarray,
                        cell_m: float, min_points: int = 10) -> float:
    """Largest excess (mm) of our median error over doing nothing's, among cubic cells of
    `cell_m` of the source holding >= min_points points: > 0 means worse than doing nothing
    somewhere."""
    keys = np.floor(source / cell_m).astype(np.int64)
    _, cell = np.unique(keys, axis=0, return_inverse=True)
    cell = cell.ravel()
    worst = -np.inf
    for c in np.flatnonzero(np.bincount(cell) >= min_points):
        inside = cell == c
        worst = max(worst, float(np.median(ours[inside]) - np.median(nothing[inside])))
    return worst
