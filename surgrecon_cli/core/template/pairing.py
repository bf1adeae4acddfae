"""Camera grouping and pair sequencing (Su et al. 2019 ref. [3]; CoSLAM's camera groups).

The rule, and why:
1. *Prediction from the tracked poses* (cheap, before any matching): for cameras i, j we
   back-project a grid of i's pixels to its working depth (where the optical axes of the
   cameras converge) and count the fraction that lands inside j's image -> shared view.
   Pairs that share little view, or whose viewing directions differ by more than
   `max_angle` (SIFT descriptors stop matching under large viewpoint change), or whose
   baseline is tiny relative to depth (ill-conditioned triangulation), are not matched.
2. *Verification*: candidate pairs are matched; the edge weight is the number of
   epipolar-verified matches times the angle factor. Edges under `min_pair_matches` go.
3. *Groups* are the connected components of the verified graph: cameras that see nothing
   in common end up in separate groups (their points cannot share one frame of reference
   through matches, although the tracker gives them one).
4. *Sequence*: within a group, a maximum spanning tree grown from the best pair (Prim):
   each new camera joins through its best-conditioned, best-matched link, so every camera
   is connected by well-conditioned pairs; the remaining verified pairs follow in order of
   weight (they lengthen tracks and add redundancy). Track building uses this order.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse.csgraph import connected_components

from ..geometry.cameras import CameraModel, in_image, pixel_rays, project

MAX_ANGLE_DEG = 75.0  # ours: beyond this SIFT matching across views is hopeless
FULL_ANGLE_DEG = 30.0  # ours: up to this a pair is fully trusted
MIN_BASELINE_RATIO = 0.05  # ours: baseline/depth below this gives < ~3 deg of parallax


@dataclass(frozen=True)
class PairPrediction:
    """Per-pair predictions (C, C): shared-view fraction, baseline/depth, view angle (deg),
    the angle/conditioning factor in [0, 1] and the working depth (C,) of each camera (m)."""

    overlap: np.ndarray
    baseline_ratio: np.ndarray
    angle_deg: np.ndarray
    conditioning: np.ndarray
    depth: np.ndarray


@dataclass(frozen=True)
class PairPlan:
    """Groups of camera indices and, per group, the ordered pairs to match/merge."""

    groups: list[list[int]]
    sequences: list[list[tuple[int, int]]]
    weights: np.ndarray

    @property
    def pairs(self) -> list[tuple[int, int]]:
        return [p for seq in self.sequences for p in seq]


def working_depths(poses: np.ndarray, usable: np.ndarray, fallback: float) -> np.ndarray:
    """Per camera, the median depth (m) along its optical axis where it converges with the
    other cameras' axes (closest approach in front of both); `fallback` if none."""
    n = len(poses)
    centres = poses[:, :3, 3]
    axes = poses[:, :3, 2]
    depths: list[list[float]] = [[] for _ in range(n)]
    for i in range(n):
        for j in range(i + 1, n):
            if not (usable[i] and usable[j]):
                continue
            w0 = centres[i] - centres[j]
            b = float(axes[i] @ axes[j])
            d, e = float(axes[i] @ w0), float(axes[j] @ w0)
            denom = 1 - b * b
            if denom < 1e-6:
                continue
            si, sj = (b * e - d) / denom, (e - b * d) / denom
            if si > 0 and sj > 0:
                depths[i].append(si)
                depths[j].append(sj)
    return np.array([np.median(d) if d else fallback for d in depths])


def predict_pairs(
    models: list[CameraModel],
    poses: np.ndarray,
    usable: np.ndarray,
    fallback_depth: float,
    grid: int = 12,
) -> PairPrediction:
    """Shared-view and conditioning predictions for all camera pairs from poses alone."""
    n = len(models)
    depth = working_depths(poses, usable, fallback_depth)
    overlap = np.zeros((n, n))
    for i in range(n):
        if not usable[i]:
            continue
        m = models[i]
        u, v = np.meshgrid(np.linspace(0, m.width - 1, grid), np.linspace(0, m.height - 1, grid))
        origin, dirs = pixel_rays(np.stack([u.ravel(), v.ravel()], 1), m, poses[i])
        z = dirs @ poses[i][:3, 2]
        points = origin + dirs * (depth[i] / z)[:, None]
        for j in range(n):
            if j != i and usable[j]:
                uv, zj = project(points, poses[j], models[j])
                overlap[i, j] = float((in_image(uv, models[j]) & (zj > 0)).mean())
    overlap = np.minimum(overlap, overlap.T)
    centres = poses[:, :3, 3]
    baseline = np.linalg.norm(centres[:, None] - centres[None], axis=2)
    ratio = baseline / np.maximum(np.minimum(depth[:, None], depth[None]), 1e-9)
    cos = (poses[:, None, :3, 2] * poses[None, :, :3, 2]).sum(-1).clip(-1, 1)
    angle = np.degrees(np.arccos(cos))
    factor = ((MAX_ANGLE_DEG - angle) / (MAX_ANGLE_DEG - FULL_ANGLE_DEG)).clip(0, 1)
    factor = np.where(ratio >= MIN_BASELINE_RATIO, factor, 0.0)
    np.fill_diagonal(factor, 0.0)
    return PairPrediction(overlap, ratio, angle, factor, depth)


def candidate_pairs(prediction: PairPrediction, min_overlap: float) -> list[tuple[int, int]]:
    """Pairs (i < j) predicted to share enough, well-conditioned view."""
    ok = (prediction.overlap >= min_overlap) & (prediction.conditioning > 0)
    i, j = np.nonzero(np.triu(ok, 1))
    return list(zip(i.tolist(), j.tolist(), strict=True))


def plan_pairs(weights: np.ndarray) -> PairPlan:
    """Groups and pair sequences from verified edge weights (C, C) (0 = no link)."""
    w = np.maximum(weights, weights.T)
    n_groups, member = connected_components(w > 0, directed=False)
    groups = [np.flatnonzero(member == g).tolist() for g in range(n_groups)]
    groups.sort(key=lambda g: (-len(g), g[0]))
    sequences: list[list[tuple[int, int]]] = []
    for group in groups:
        if len(group) < 2:
            sequences.append([])
            continue
        sub = w[np.ix_(group, group)]
        a, b = np.unravel_index(np.argmax(sub), sub.shape)
        tree = [(group[min(a, b)], group[max(a, b)])]
        joined = {int(a), int(b)}
        while len(joined) < len(group):  # Prim: best edge from the tree to a new camera
            inside = sorted(joined)
            outside = [k for k in range(len(group)) if k not in joined]
            cut = sub[np.ix_(inside, outside)]
            r, c = np.unravel_index(np.argmax(cut), cut.shape)
            p, q = group[inside[r]], group[outside[c]]
            tree.append((min(p, q), max(p, q)))
            joined.add(outside[c])
        rest = [
            (group[r], group[c])
            for r in range(len(group))
            for c in range(r + 1, len(group))
            if sub[r, c] > 0 and (group[r], group[c]) not in tree
        ]
        rest.sort(key=lambda e: -w[e])
        sequences.append(tree + rest)
    return PairPlan(groups, sequences, w)
