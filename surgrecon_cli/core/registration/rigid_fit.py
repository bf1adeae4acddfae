"""The scene's rigid motion between two clouds with known correspondences, robustly: RANSAC
over minimal triples, then iteratively reweighted Kabsch (Tukey's biweight). Registration
takes it first, so that the non-rigid part is only the small remainder and points without
data follow the rigid motion (core/registration/frame_step.py). Pure numpy."""

from __future__ import annotations

import numpy as np

from ..geometry.poses import fit_rigid

HYPOTHESES = 128  # RANSAC triples tried
REFINE_ITERATIONS = 10  # reweighted Kabsch steps
MIN_PAIRS = 6  # fewer correspondences: no rigid motion is fitted (identity)
SCORE_PAIRS = 256  # ours: hypotheses are counted on at most this many pairs, evenly spread


def robust_rigid(src: np.ndarray, dst: np.ndarray, inlier_m: float,
                 seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rigid motion R (3, 3), t (3,) with dst ~ src @ R.T + t for pairs src, dst (K, 3) m of
    which many may not follow it (deforming tissue, mistracked points); inliers (K,) bool:
    the pairs within `inlier_m` m of it. The triple whose motion has most inliers starts
    an iteratively reweighted Kabsch fit with Tukey weights of cut-off `inlier_m` (triples
    are counted on SCORE_PAIRS evenly spread pairs: the refinement uses them all).
    Identity (and no inliers) with fewer than MIN_PAIRS pairs or no triple that explains
    MIN_PAIRS of them. Deterministic for a given `seed`."""
    k = len(src)
    identity = (np.eye(3), np.zeros(3), np.zeros(k, bool))
    if k < MIN_PAIRS:
        return identity
    rng = np.random.default_rng(seed)
    triples = np.stack([rng.choice(k, 3, replace=False) for _ in range(HYPOTHESES)])
    R, t = fit_rigid(src[triples], dst[triples])  # (H, 3, 3), (H, 3)
    score = np.linspace(0, k - 1, min(k, SCORE_PAIRS)).astype(int)
    moved = np.einsum("hij,kj->hki", R, src[score]) + t[:, None, :]
    off = moved - dst[score]
    counts = (np.einsum("hki,hki->hk", off, off) <= inlier_m**2).sum(1)
    best = int(np.argmax(counts))
    if counts[best] * k / len(score) < MIN_PAIRS:
        return identity
    R, t = R[best], t[best]
    for _ in range(REFINE_ITERATIONS):
        r = np.linalg.norm(src @ R.T + t - dst, axis=1)
        w = np.where(r < inlier_m, (1.0 - (r / inlier_m) ** 2) ** 2, 0.0)
        if (w > 0).sum() < 3:
            break
        R, t = fit_rigid(src, dst, w)
    inliers = np.linalg.norm(src @ R.T + t - dst, axis=1) <= inlier_m
    return R, t, inliers
