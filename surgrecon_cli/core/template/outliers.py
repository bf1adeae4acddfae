"""Outlier points of a sampled surface: points far from the local plane of their neighbours.

A wrong two-view match along an epipolar line triangulates to a point with a small
reprojection error but off the tissue surface. Its neighbours (excluding itself) define a
local plane; the point's distance to that plane, compared with the typical distance of
the cloud, tells it apart.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


def local_plane_distance(points: np.ndarray, k: int = 12) -> np.ndarray:
    """Distance (N,) m of each point to the least-squares plane of its k nearest neighbours."""
    n = len(points)
    if n <= 3:
        return np.zeros(n)
    k = min(k, n - 1)
    _, idx = cKDTree(points).query(points, k=k + 1)
    nb = points[idx[:, 1:]]
    centre = nb.mean(1)
    d = nb - centre[:, None]
    cov = np.einsum("nki,nkj->nij", d, d)
    _, vecs = np.linalg.eigh(cov)
    normal = vecs[:, :, 0]
    return np.abs(((points - centre) * normal).sum(1))


def surface_outliers(
    points: np.ndarray, k: int = 12, factor: float = 6.0, floor: float = 3e-4, rounds: int = 2
) -> np.ndarray:
    """(N,) bool: points farther than max(floor, factor * median) from their local plane.

    `floor` (m) keeps noise-level scatter (tenths of a mm) from being cut on clean clouds;
    factor and floor are ours. Repeated `rounds` times, since an outlier tilts its
    neighbours' planes.
    """
    outlier = np.zeros(len(points), bool)
    for _ in range(rounds):
        inside = np.flatnonzero(~outlier)
        dist = local_plane_distance(points[inside], k)
        limit = max(floor, factor * float(np.median(dist)))
        bad = dist > limit
        if not bad.any():
            break
        outlier[inside[bad]] = True
    return outlier
