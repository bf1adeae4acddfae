"""What a registration can know about its own error, per point (normalised units).

- `surface_distance`: distance of a registered point to the target's surface near it: the
  plane of its nearest usable (non-stray) target point, with the part of the along-plane
  offset beyond `PATCH_SPACINGS` target spacings added, so a point past the edge of a
  partial target measures its distance to that edge. It does not see a slide along the
  surface (nearest-neighbour residuals on a smooth surface carry no such signal).
- `along_surface`: where colour decided the correspondences, the along-surface offset of
  each point from its match, averaged over the points of its deformation node (the offsets
  of independent samplings average out; a common slide does not). NaN where there is no
  such estimate.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from .surface import TargetSurface

PATCH_SPACINGS = 2.0  # ours: radius of the local plane patch, target spacings


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
                  target_q: np.ndarray, interp_idx: np.ndarray,
                  interp_w: np.ndarray) -> np.ndarray:
    """(N,) along-surface error estimate from matches `matched_to` (N,) target index or -1:
    the along-surface offsets averaged over the points of each deformation node (a point
    belongs to its nearest node, interp_idx[:, 0]), blended back with the interpolation
    weights interp_idx / interp_w (N, k) (graph.interpolation)."""
    n = len(moved)
    out = np.full(n, np.nan)
    has = np.flatnonzero(matched_to >= 0)
    if len(has) == 0:
        return out
    c = matched_to[has]
    off = moved[has] - target_q[c]
    nrm = surf.normal[c]
    tangential = off - np.einsum("ij,ij->i", off, nrm)[:, None] * nrm
    owner = interp_idx[has, 0]
    m = int(interp_idx.max()) + 1
    count = np.bincount(owner, minlength=m).astype(float)
    sums = np.stack([np.bincount(owner, tangential[:, a], minlength=m) for a in range(3)], 1)
    mean = sums / np.maximum(count, 1.0)[:, None]
    w = interp_w[has] * (count[interp_idx[has]] > 0)
    blended = np.einsum("pk,pki->pi", w, mean[interp_idx[has]])
    out[has] = np.linalg.norm(blended, axis=1) / np.maximum(w.sum(axis=1), 1e-12)
    return out
