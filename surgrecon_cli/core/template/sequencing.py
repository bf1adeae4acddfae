"""Pair sequencing that grows the template (Su et al. 2019 ref. [3]; CoSLAM's inter-camera
mapping in the group's camera order).

Instead of matching all C(C-1)/2 candidate pairs, cameras join one at a time in the order
of a maximum spanning tree of the *predicted* pair weights (shared view x conditioning,
core/template/pairing.py): only the tree's C-1 pairs are matched across the epipolar band. Before a
camera joins through its tree pair, the tracks built so far are triangulated and projected
into it; a track is matched to a feature of the new camera within `gate_px` of its
projection (a point gate, tighter than an epipolar segment), with the same ratio and
mutual tests as pair matching. So a new camera extends the multi-view tracks of every
camera already joined, not only those of its tree partner, and the other pairs add little.

A tree pair that fails verification (fewer verified matches than its `min_matches`) is
replaced by the camera's next best predicted link, the tree re-planned with the verified
pairs preferred.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..geometry.cameras import CameraModel
from ..geometry.poses import invert_pose
from ..geometry.triangulate import Observations, triangulate
from .features import Features
from .matching import build_tracks, ratio_mutual_matches
from .pairing import PairPlan, PairPrediction, plan_pairs

# ours: a track's projection misses its feature by its triangulation error (2-view depth
# errors of ~1-2 px measured at 640 px; 2x, 4x and 8x the epipolar tolerance gave the same
# template) plus the pose errors of the cameras (the tracker's jitter projected, ∝ focal
# length: 3 sigma of two views; at 1920 px a 4 px gate lost a third of the accuracy)
GATE_EPIPOLAR, GATE_POSE_SIGMAS = 2.0, 3.0 * np.sqrt(2.0)

Merge = tuple[int, int, np.ndarray]
"""(camera a, camera b, (M, 2) feature indices in a and b): matches to merge into tracks."""


@dataclass(frozen=True)
class TrackObservations:
    """The tracked features as observations (`observations.point` = track id) and each
    observation's feature index (M,) in its camera's `Features`."""

    observations: Observations
    feature: np.ndarray


def track_observations(features: list[Features], track_ids: list[np.ndarray]
                       ) -> TrackObservations:
    """Observations of the tracked features of every camera (track_ids[c] (N_c,), -1 =
    untracked), camera by camera in feature order."""
    index = [np.flatnonzero(ids >= 0) for ids in track_ids]
    obs = Observations(
        point=np.concatenate([ids[i] for ids, i in zip(track_ids, index, strict=True)]),
        camera=np.concatenate([np.full(len(i), c) for c, i in enumerate(index)]),
        pixels=np.concatenate([f.pixels[i] for f, i in zip(features, index, strict=True)]),
        normalized=np.concatenate([f.normalized[i]
                                   for f, i in zip(features, index, strict=True)]),
        rgb=np.concatenate([f.rgb[i] for f, i in zip(features, index, strict=True)]),
    )
    return TrackObservations(obs, np.concatenate(index).astype(int))


@dataclass(frozen=True)
class RigFeatures:
    """Per camera c: its `features[c]`, camera-to-world pose `poses[c]` (4, 4) and model
    `models[c]`."""

    features: list[Features]
    poses: np.ndarray
    models: list[CameraModel]


@dataclass(frozen=True)
class SequenceGates:
    """What sequencing requires: `min_matches` (C, C) verified matches a pair needs to link;
    Lowe's `ratio`; `epipolar_px` (px) the pair matching's epipolar tolerance; each camera's
    pose error `pose_px` (C,) px (with `epipolar_px`, the point gate of matching to tracks);
    `max_reprojection_px` (px) a track's views must reproject within to be matched to."""

    min_matches: np.ndarray
    ratio: float
    epipolar_px: float
    pose_px: np.ndarray
    max_reprojection_px: float


def track_gate_px(gates: SequenceGates, camera: int) -> float:
    """The point gate (px) matching tracks to `camera`: GATE_EPIPOLAR x `epipolar_px` +
    GATE_POSE_SIGMAS x the camera's pose error."""
    return float(GATE_EPIPOLAR * gates.epipolar_px + GATE_POSE_SIGMAS * gates.pose_px[camera])


def match_to_tracks(rig: RigFeatures, merges: list[Merge], new: int, angle_deg: np.ndarray,
                    gates: SequenceGates) -> list[Merge]:
    """Matches of camera `new`'s features to the tracks the `merges` build, as merges from
    each track's view in the camera looking most like `new` (smallest view angle,
    angle_deg (C, C)). Tracks are triangulated (kept when every view reprojects within
    `gates.max_reprojection_px`), projected into `new` and matched within
    `track_gate_px(gates, new)` (px) of the projection by descriptor (ratio test against
    all of `new`'s features, mutual best)."""
    features, poses, models = rig.features, rig.poses, rig.models
    ratio, max_reprojection_px = gates.ratio, gates.max_reprojection_px
    gate_px = track_gate_px(gates, new)
    track_ids, n_tracks = build_tracks([len(f) for f in features], merges)
    tracked = track_observations(features, track_ids)
    obs = tracked.observations
    fk = features[new]
    if n_tracks == 0 or len(fk) < 2:
        return []
    tri = triangulate(obs, poses, models, n_tracks)
    seen = np.zeros(n_tracks, bool)
    seen[obs.point[obs.camera == new]] = True
    usable = (np.isfinite(tri.points).all(1) & tri.in_front
              & (tri.max_error_px <= max_reprojection_px) & ~seen)
    order = np.lexsort((angle_deg[obs.camera, new], obs.point))
    first = np.ones(len(order), bool)
    first[1:] = obs.point[order][1:] != obs.point[order][:-1]
    view = order[first]  # per track (ascending id), its view seen most like `new`
    view = view[usable[obs.point[view]]]
    T = invert_pose(poses[new])
    local = tri.points[obs.point[view]] @ T[:3, :3].T + T[:3, 3]
    view = view[local[:, 2] > 0]
    local = local[local[:, 2] > 0]
    if len(view) == 0:
        return []
    near = cKDTree(local[:, :2] / local[:, 2:]).sparse_distance_matrix(
        cKDTree(fk.normalized), gate_px / models[new].K[0, 0], output_type="ndarray")
    near = np.sort(near, order=("i", "j"))
    offsets = np.cumsum([0] + [len(f) for f in features])
    descriptors = np.concatenate([f.descriptors for f in features])
    found = ratio_mutual_matches(descriptors[offsets[obs.camera[view]] + tracked.feature[view]],
                                 fk.descriptors, near["i"].astype(int), near["j"].astype(int),
                                 ratio)
    cams = obs.camera[view[found[:, 0]]]
    return [(int(c), new, np.column_stack([tracked.feature[view[found[cams == c, 0]]],
                                           found[cams == c, 1]]))
            for c in np.unique(cams)]


MatchPairs = Callable[[list[tuple[int, int]]], list[np.ndarray]]
"""Pose-guided matches (M, 2) of each camera pair (i, j) of a list (possibly in parallel)."""


@dataclass(frozen=True)
class MatchPlan:
    """The merges building the tracks, in order; the pair plan; the matches (M, 2) of each
    verified pair; the number of pairs matched (verified or not) and of camera-to-template
    matchings; `counts` the verified matches of every pair matched (linked or not)."""

    merges: list[Merge]
    plan: PairPlan
    verified: dict[tuple[int, int], np.ndarray]
    pairs_matched: int
    guided: int
    counts: dict[tuple[int, int], int]


def _verified_weights(found: dict[tuple[int, int], np.ndarray], conditioning: np.ndarray,
                      min_matches: np.ndarray) -> np.ndarray:
    """Edge weights (C, C): verified matches x conditioning of the pairs with at least
    `min_matches[i, j]` matches, 0 elsewhere."""
    w = np.zeros_like(conditioning)
    for (i, j), m in found.items():
        if len(m) >= min_matches[i, j]:
            w[i, j] = w[j, i] = len(m) * conditioning[i, j]
    return w


def all_pairs(pairs: list[tuple[int, int]], match_pairs: MatchPairs, conditioning: np.ndarray,
              min_matches: np.ndarray) -> MatchPlan:
    """Every candidate pair matched; the verified ones merged in the order of `plan_pairs`
    (spanning tree of the verified weights, then the other pairs): the comparison."""
    found = dict(zip(pairs, match_pairs(pairs), strict=True))
    weights = _verified_weights(found, conditioning, min_matches)
    plan = plan_pairs(weights)
    verified = {p: m for p, m in found.items() if weights[p] > 0}
    return MatchPlan([(i, j, verified[(i, j)]) for i, j in plan.pairs], plan, verified,
                     len(found), 0, {p: len(m) for p, m in found.items()})


def sequenced(rig: RigFeatures, pairs: list[tuple[int, int]], prediction: PairPrediction,
              match_pairs: MatchPairs, gates: SequenceGates) -> MatchPlan:
    """Only a spanning tree over the candidate `pairs` is matched (failed tree pairs, fewer
    than `gates.min_matches`, replaced, re-planning with the verified pairs first); cameras
    join in the tree's order, each first matched to the tracks so far (`match_to_tracks`;
    gate `track_gate_px`), then merged with its tree partner; a closing pass matches every
    camera to the tracks made after it joined.

    The tree maximises the predicted weight of a pair, shared view x conditioning (the
    matches expected; `plan_pairs` weighs verified pairs by matches x conditioning).
    Weighing pairs by parallax as well (baseline/depth) gave a more precise template of a
    third of the points (measured, seeds 11, 21, 22): rejected."""
    predicted = prediction.overlap * prediction.conditioning
    conditioning, angle_deg = prediction.conditioning, prediction.angle_deg
    min_matches = gates.min_matches
    found: dict[tuple[int, int], np.ndarray] = {}
    candidate = np.zeros_like(predicted)
    for i, j in pairs:
        candidate[i, j] = candidate[j, i] = predicted[i, j]
    while True:
        weights = candidate.copy()
        for (i, j), m in found.items():
            weights[i, j] = weights[j, i] = (1.0 + candidate[i, j]
                                             if len(m) >= min_matches[i, j] else 0.0)
        plan = plan_pairs(weights)
        trees = [seq[: len(g) - 1] for g, seq in zip(plan.groups, plan.sequences, strict=True)]
        todo = [e for tree in trees for e in tree if e not in found]
        if not todo:
            break
        found.update(zip(todo, match_pairs(todo), strict=True))
    merges: list[Merge] = []
    guided = 0
    def to_tracks(camera: int) -> list[Merge]:
        return match_to_tracks(rig, merges, camera, angle_deg, gates)

    for tree in trees:
        joined: list[int] = []
        for i, j in tree:
            if joined:
                merges += to_tracks(j if i in joined else i)
            merges.append((i, j, found[(i, j)]))
            joined += [c for c in (i, j) if c not in joined]
        guided += max(len(joined) - 2, 0)
        for camera in joined:  # closing pass: the tracks made after a camera joined
            merges += to_tracks(camera)
        guided += len(joined)
    weights = _verified_weights(found, conditioning, min_matches)
    verified = {p: m for p, m in found.items() if weights[p] > 0}
    return MatchPlan(merges, PairPlan(plan.groups, trees, weights), verified, len(found), guided,
                     {p: len(m) for p, m in found.items()})
