"""Correspondences c(i): known ids first, then gated nearest neighbours in position + colour.

All lengths are in the solver's normalised units (see graph.Normalisation).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

# ours: approximate nearest neighbours, within (1 + MATCH_EPS) x the nearest distance; in
# position + colour this about thirds the search time and changes ~4 % of the matches
MATCH_EPS = 1.0


@dataclass(frozen=True)
class Matcher:
    """Nearest-neighbour matcher over the target points that have no known correspondence.

    `candidates` (K,) target indices searched; `tree` indexes [xyz, colour_scale * rgb]
    (or xyz alone) of those points. `known` (N,) target index fixed per source point or -1.
    """

    target_q: np.ndarray
    candidates: np.ndarray
    tree: cKDTree | None
    colour_scale: float
    target_rgb: np.ndarray | None
    known: np.ndarray


@dataclass(frozen=True)
class KnownPairs:
    """Correspondences known before matching: `target_ids` (M,) int, the source index each
    target point is (-1 = unknown), and `landmarks` (L, 2) int (source, target) pairs; None =
    none of that kind. Landmarks override template ids."""

    target_ids: np.ndarray | None = None
    landmarks: np.ndarray | None = None


def build_matcher(
    target_q: np.ndarray,
    n_source: int,
    target_rgb: np.ndarray | None,
    colour_scale: float,
    known_pairs: KnownPairs,
    usable: np.ndarray | None = None,
) -> Matcher:
    """Known pairs (landmarks override template ids) and a KD-tree over the other targets;
    `usable` (M,) bool: targets free matches may use (None = all; strays are left out)."""
    target_ids, landmarks = known_pairs.target_ids, known_pairs.landmarks
    known = np.full(n_source, -1, np.int64)
    free = np.ones(len(target_q), bool) if usable is None else usable.copy()
    if target_ids is not None:
        has = target_ids >= 0
        # the first target point carrying an id wins; later duplicates are ignored
        ids, first = np.unique(target_ids[has], return_index=True)
        known[ids] = np.flatnonzero(has)[first]
        free &= ~has
    if landmarks is not None and len(landmarks):
        known[landmarks[:, 0]] = landmarks[:, 1]
        free[landmarks[:, 1]] = False
    candidates = np.flatnonzero(free)
    tree = None
    use_rgb = target_rgb is not None and colour_scale > 0
    if len(candidates):
        feats = target_q[candidates]
        if use_rgb and target_rgb is not None:
            feats = np.concatenate([feats, colour_scale * target_rgb[candidates]], axis=1)
        tree = cKDTree(feats)
    return Matcher(target_q=target_q, candidates=candidates, tree=tree,
                   colour_scale=colour_scale if use_rgb else 0.0,
                   target_rgb=target_rgb if use_rgb else None, known=known)


def match(
    matcher: Matcher,
    moved_q: np.ndarray,
    source_rgb: np.ndarray | None,
    max_distance: float,
    mutual_distance: float,
    allowed: np.ndarray,
) -> np.ndarray:
    """Target index per source point (-1 = none) for the current moved source `moved_q`.

    Free points (no known pair, `allowed`) take the nearest free target in position + colour,
    kept only if (a) its distance in position is at most `max_distance` and (b) the target's
    nearest moved source point lies within `mutual_distance` of the querying point (a loose
    mutual check that drops matches onto the rim of a partial target and onto stray points).
    """
    corr = matcher.known.copy()
    free = np.flatnonzero((corr < 0) & allowed)
    if matcher.tree is None or len(free) == 0:
        return corr
    feats = moved_q[free]
    if matcher.target_rgb is not None and source_rgb is not None:
        feats = np.concatenate([feats, matcher.colour_scale * source_rgb[free]], axis=1)
    _, j = matcher.tree.query(feats, k=1, eps=MATCH_EPS)
    tgt = matcher.candidates[j]
    dist = np.linalg.norm(moved_q[free] - matcher.target_q[tgt], axis=1)
    ok = dist <= max_distance
    # the target's nearest moved point b is no farther from it than the querying point i, so
    # |b - i| <= 2 |target - i|: a match within half the mutual distance passes unlooked
    # (with a margin for rounding); only the others are looked up
    sel = np.flatnonzero(ok & (2.0 * dist > mutual_distance * (1.0 - 1e-9)))
    if mutual_distance > 0 and len(sel):
        _, back = cKDTree(moved_q, balanced_tree=False).query(matcher.target_q[tgt[sel]], k=1)
        ok[sel] = np.linalg.norm(moved_q[back] - moved_q[free[sel]], axis=1) <= mutual_distance
    corr[free[ok]] = tgt[ok]
    return corr
