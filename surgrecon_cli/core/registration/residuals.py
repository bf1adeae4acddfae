"""What a registration can know about its own error, per point (normalised units).

- `surface_distance`: distance of a registered point to the target's surface near it: the
  plane of its nearest usable (non-stray) target point, with the part of the along-plane
  offset beyond `PATCH_SPACINGS` target spacings added, so a point past the edge of a
  partial target measures its distance to that edge. It does not see a slide along the
  surface (nearest-neighbour residuals on a smooth surface carry no such signal).
- `along_surface`: where colour decided the correspondences, the along-surface offset of
  each point from its match, averaged over its `ALONG_NEIGHBOURS` nearest source points
  (the offsets of independent samplings average out; a common slide does not). NaN where
  there is no such estimate.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from .surface import TargetSurface

PATCH_SPACINGS = 2.0  # ours: radius of the local plane patch, target spacings
ALONG_NEIGHBOURS = 16  # ours: source points averaged in the along-surface estimate


def surface_distance(moved: np.ndarray, surf: TargetSurface, usable_idx: np.ndarray,
                     usable_tree: cKDTree) -> np.ndarray:
    """(N,) distance of `moved` (N, 3) to the local target surface (module docstring);
    `usable_tree` indexes the target points `usable_idx`."""
    d, local = usable_tree.query(moved, k=1)
    j = usable_idx[local]
    nrm = surf.normal[j]
    normal = np.einsum("ij,ij->i", moved - surf.centroid[j], nrm)
    # along-plane offset from the nearest point itself (a centroid sits inward at an edge)
    off_normal = np.einsum("ij,ij->i", moved - usable_tree.data[local], nrm)
    along = np.sqrt(np.maximum(d**2 - off_normal**2, 0.0))
    return np.hypot(normal, np.maximum(along - PATCH_SPACINGS * surf.spacing, 0.0))


def along_surface(moved: np.ndarray, matched_to: np.ndarray, surf: TargetSurface,
                  target_q: np.ndarray, source_tree: cKDTree) -> np.ndarray:
    """(N,) along-surface error estimate from matches `matched_to` (N,) target index or -1;
    `source_tree` indexes the source points (neighbourhoods in the material)."""
    n = len(moved)
    out = np.full(n, np.nan)
    has = np.flatnonzero(matched_to >= 0)
    if len(has) == 0:
        return out
    c = matched_to[has]
    off = moved[has] - target_q[c]
    nrm = surf.normal[c]
    tangential = np.zeros((n, 3))
    tangential[has] = off - np.einsum("ij,ij->i", off, nrm)[:, None] * nrm
    counted = np.zeros(n)
    counted[has] = 1.0
    k = min(ALONG_NEIGHBOURS, n)
    _, nn = source_tree.query(source_tree.data[has], k=k)
    nn = nn.reshape(len(has), k)
    total = counted[nn].sum(axis=1)
    mean = tangential[nn].sum(axis=1) / np.maximum(total, 1.0)[:, None]
    out[has] = np.linalg.norm(mean, axis=1)
    return out
