"""`register_pair`: `register` as `surgrecon register-pair` runs it (issue 28).

Around the shared `register` (also the frame pipeline's), without changing it:
1. colour decided robustly (colour.py): target points whose colour disagrees with their
   neighbourhood (random-coloured strays, even on the surface) are left out of the target,
   and the colour weight is measured on the agreeing points only; with colour off the call
   gets no colours (so `register`'s own automatic weight is never consulted);
2. partial overlap (overlap.py): a source point left without target surface (not
   `supported`) takes the median displacement of its `FOLLOW_NEIGHBOURS` nearest supported
   points, i.e. it moves rigidly (a translation) with its supported neighbourhood, so
   beside a static supported part it stays put; farther (FOLLOW_REACH) it keeps
   `register`'s own motion (smoothness plus a weak pull towards not moving), or, with
   colour used, it does not move (FOLLOW_REACH_COLOURED: nothing measured its motion);
3. with colour used, each supported point keeps the share of its motion (1, 1/2 or 0,
   averaged over its neighbours) under which its neighbourhood's colour and surface
   misfit is lowest (`stay_where_better`): static tissue next to moving tissue, which the
   smoothness drags and the nearest-match step then holds there, goes back to not moving;
   a hypothesis at the rim of the target (`target_rim`), where the true partner may lie
   past it, is left out; then a point does not move at all where that explains its
   neighbourhood's data within a margin over the measured noises (`explained_by_identity`,
   points at the target's rim left out of the neighbourhood, the colour misfit counted
   robustly), a point whose deformation node it shares with a cut-away part
   (`coupled_to_unsupported`) keeps only its motion across the target's surface
   (`across_only`) unless its slide along it explains its neighbourhood's data better by
   the same margin, and a point matched onto the rim of a cut target (`matched_onto_cut`)
   follows as in 2; on a cut pair, before those tests, the motion's part along the surface
   is refined from the colour pooled over `register`'s nodes (`colour_flow`; the tests
   judge `register`'s own motion, the share kept applies to the refined one);
4. with colour used, solver settings of its own (`pair_config`) in place of the fields the
   caller left at their defaults;
5. an error estimate that says what it can see (`error_estimate_mm`);
6. without colour, settings of its own and, with landmarks, a landmark stage first
   (shape.py).
Inputs and outputs in metres, like `register`.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from ...config import RegistrationConfig
from ..geometry.poses import compose_affines
from .colour import ColourDecision, decide_colour
from .colour_flow import colour_flow
from .graph import NodeBlend, node_blend
from .overlap import (
    FOLLOW_REACH_COLOURED,
    ColouredPoints,
    MotionTest,
    across_only,
    coupled_to_unsupported,
    explained_by,
    explained_by_identity,
    follow_supported,
    matched_onto_cut,
    stay_where_better,
)
from .register import RegistrationResult, _colours, _points, register
from .shape import (
    after_landmarks_config,
    landmark_stage,
    shape_config,
    target_spacing_m,
    uses_landmark_stage,
)

# ours, tuned on stray_colour / stray_colour_partial / stray_colour_30 seeds 0-4, 1k-20k
# points (benchmarks/registration.py --variant): with colour deciding the matches, 250 nodes
# and 10 rigid ICP steps (the colour-decided outer steps find what the rigid step does not)
# cut the 5k time from 0.36 to 0.26 s; a mutual check 5 spacings wide instead of 3 keeps
# the matches that slide along the texture (worst seed at 5k 0.195 -> 0.175 mm, at 20k 0.161
# -> 0.096 mm; 1.5 spacings: 0.26 / 0.56 mm) while still dropping matches onto the rim of a
# cut target (with no mutual check the cut 5k pair goes from 0.18-0.28 to 0.20-0.29 mm and
# the 2k one from 0.31-0.52 to 0.38-0.56 mm), and never narrower than MUTUAL_GATE_FRACTION
# of the correspondence gate (1.25 mm, what 5 target spacings are at 20k points: 2 mm at 5k;
# at 100k points 5 spacings are 0.73 mm and leave tuning seeds 0 / 1 at 0.162 / 0.081 mm,
# the floor at 0.069 / 0.050 mm); above PAIR_DENSE_POINTS, 8 outer steps instead of 6 let
# the matches slide further (20k worst seed 0.096 -> 0.083 mm). The last outer step stops
# after 25 ADMM iterations instead of running to convergence (300 at most): on full pairs it
# converges in 5-24 (stray_colour 2k-20k, tissue, tissue_noisy, tuning seeds 0-4), on cut
# pairs the long tail (38-95 iterations) is the weak pull on the points without target
# surface, whose positions `register_pair` replaces anyway (they follow their supported
# neighbours or stay); stray_colour_partial 5k seeds 0-9 and 200-209: medians within
# +-0.004 mm, worst cells the same or lower, ~0.05 s less per cut pair
PAIR_SETTINGS: dict[str, float] = {"max_nodes": 250, "rigid_iterations": 10,
                                   "mutual_spacings": 5.0, "final_admm_iterations": 25}
MUTUAL_GATE_FRACTION = 0.25
PAIR_DENSE_POINTS = 5000
PAIR_DENSE_OUTER = 8


def pair_config(cfg: RegistrationConfig, n_source: int,
                target_spacing_m: float = 0.0) -> RegistrationConfig:
    """`cfg` with `register_pair`'s settings for colour-decided matches (PAIR_SETTINGS, the
    mutual check at least MUTUAL_GATE_FRACTION x max_correspondence_mm wide given the
    target's median nearest-neighbour spacing in metres (`register` counts the mutual
    check in the larger of it and the source's spacing; 0 = unknown: no floor), and
    PAIR_DENSE_OUTER outer steps above PAIR_DENSE_POINTS source points) in place of the
    fields left at their defaults; a field the caller set to another value is kept."""
    default = RegistrationConfig()
    settings = dict(PAIR_SETTINGS)
    if target_spacing_m > 0:
        floor_m = MUTUAL_GATE_FRACTION * cfg.max_correspondence_mm * 1e-3
        settings["mutual_spacings"] = max(settings["mutual_spacings"],
                                          floor_m / target_spacing_m)
    changes: dict[str, Any] = {
        key: type(getattr(default, key))(value) for key, value in settings.items()
        if getattr(cfg, key) == getattr(default, key)}
    if n_source > PAIR_DENSE_POINTS and cfg.outer_iterations == default.outer_iterations:
        changes["outer_iterations"] = PAIR_DENSE_OUTER
    return dataclasses.replace(cfg, **changes)


def _known_sources(n: int, target_ids: Any, landmarks: Any) -> np.ndarray:
    """(n,) bool: source points with a known pair (template ids, landmarks)."""
    known = np.zeros(n, bool)
    if target_ids is not None:
        ids = np.asarray(target_ids)
        known[ids[(ids >= 0) & (ids < n)]] = True
    if landmarks is not None and len(landmarks):
        known[np.asarray(landmarks)[:, 0]] = True
    return known


def _keep_targets(n_target: int, decision: ColourDecision | None, target_ids: Any,
                  landmarks: Any) -> np.ndarray:
    """Target indices passed on: all but the colour strays (points with a known pair stay)."""
    keep = np.ones(n_target, bool)
    if decision is not None:
        keep = decision.agree.copy()
    if target_ids is not None:
        keep |= np.asarray(target_ids) >= 0
    if landmarks is not None and len(landmarks):
        keep[np.asarray(landmarks)[:, 1]] = True
    return np.flatnonzero(keep)


def _flowed(result: RegistrationResult, test: MotionTest, target: ColouredPoints,
            decision: ColourDecision, nodes: NodeBlend | None,
            cut: bool) -> RegistrationResult:
    """result with its supported points (test.supported) shifted along the target's surface
    by `colour_flow` over `register`'s deformation nodes, their transforms gaining the
    shift, when cut (part of the source without target surface spans nodes,
    `coupled_to_unsupported`); else result as it is. On full pairs the matches reach every
    partner and the step's 0.07-0.1 s (5k) would break the time goal."""
    if not cut or nodes is None:
        return result
    moved = colour_flow(test, target, decision, nodes)
    transforms = result.transforms.copy()
    transforms[:, :, 3] += moved - result.registered
    return dataclasses.replace(result, registered=moved, transforms=transforms)


def register_pair(
    source_xyz: np.ndarray,
    target_xyz: np.ndarray,
    source_rgb: np.ndarray | None = None,
    target_rgb: np.ndarray | None = None,
    config: RegistrationConfig | None = None,
    **extras: Any,
) -> RegistrationResult:
    """`register` with the colour decided robustly, its own solver settings when colour is
    used (`pair_config`) and unsupported points following their supported neighbours
    (module docstring). extras: register's target_ids, weights,
    landmarks, callback. stats[0] gains colour_reason, colour_strays (target points left
    out), colour_gradient_per_mm, colour_noise, followed (points that followed: without
    target surface, or matched onto the rim of a cut target) and stayed
    (supported points keeping less than half their motion) and landmark_stage_seconds (0: no
    landmark stage). Residuals and along-surface
    estimates are `register`'s, at its positions."""
    cfg = config or RegistrationConfig()
    src = _points("source_xyz", source_xyz)
    tgt = _points("target_xyz", target_xyz)
    s_rgb = _colours("source_rgb", source_rgb, len(src))
    t_rgb = _colours("target_rgb", target_rgb, len(tgt))
    decision = None
    if s_rgb is not None and t_rgb is not None and len(tgt) >= 3:
        # every target point takes part: a geometric stray (off the surface) that agrees
        # with its neighbourhood's colour is left to `register`'s own stray test, and
        # leaving geometric strays out first changes the weight by < 15 % on the stray and
        # noisy tissues (1k-20k points) for a second surface analysis (0.02 s at 5k)
        decision = decide_colour(tgt, t_rgb, cfg.max_correspondence_mm * 1e-3)
        keep = _keep_targets(len(tgt), decision, extras.get("target_ids"),
                             extras.get("landmarks"))
    else:
        keep = np.arange(len(tgt))
    ids, lm = extras.get("target_ids"), extras.get("landmarks")
    remap = np.full(len(tgt), -1, np.int64)
    remap[keep] = np.arange(len(keep))
    if ids is not None:
        extras["target_ids"] = np.asarray(ids)[keep]
    if lm is not None and len(lm):
        extras["landmarks"] = np.c_[np.asarray(lm)[:, 0], remap[np.asarray(lm)[:, 1]]]
    colour_on = decision is not None and (cfg.color_weight_mm > 0 or decision.weight_mm > 0)
    if colour_on and cfg.color_weight_mm <= 0:
        assert decision is not None
        cfg = dataclasses.replace(cfg, color_weight_mm=decision.weight_mm)
    if colour_on:
        assert decision is not None
        cfg = pair_config(cfg, len(src), decision.spacing_m)
    start, pre = src, None
    if not colour_on:  # colourless: gates tied to the sampling, landmarks first (shape.py)
        spacing = target_spacing_m(tgt[keep])
        cfg = shape_config(cfg, spacing)
        if uses_landmark_stage(extras.get("landmarks")):
            pre = landmark_stage(src, tgt[keep], cfg, extras["landmarks"])
            start, cfg = pre.registered, after_landmarks_config(cfg, spacing)
    result = register(start, tgt[keep], s_rgb if colour_on else None,
                      t_rgb[keep] if colour_on and t_rgb is not None else None, cfg, **extras)
    supported = (result.supported if result.supported is not None
                 else np.ones(len(src), bool))
    transforms = result.transforms.copy()
    registered = result.registered
    share = np.ones(len(src))
    # only where the texture was found to carry the motion (a colour weight forced on a flat
    # texture would let the test undo true motion); points with a known pair keep theirs
    if (colour_on and decision is not None and decision.weight_mm > 0 and s_rgb is not None
            and t_rgb is not None):
        agree = decision.agree
        target = ColouredPoints.analysed(tgt[agree], t_rgb[agree], decision.neighbours)
        known = _known_sources(len(src), ids, lm)
        # `register`'s nodes, wanted only where part of the source lacks target surface and
        # the nodes are fewer than the points (`coupled_to_unsupported`'s cases)
        nodes = (node_blend(src, cfg.max_nodes, cfg.interp_neighbors, cfg.k_neighbors)
                 if 0 < supported.sum() < len(src) and 0 < cfg.max_nodes < len(src) else None)
        coupled = coupled_to_unsupported(src, supported, cfg.max_nodes, cfg.interp_neighbors,
                                         cfg.k_neighbors, nodes)
        # at a cut, `register`'s smoothness drags tissue along the surface by motions
        # nothing measured: the along-surface part is refined from the colour pooled over
        # the nodes (`colour_flow`). The shares below judge `register`'s own motion
        # (registered) against not moving; the share kept applies to the refined motion
        result = _flowed(result, MotionTest(src, registered, supported & ~known, s_rgb),
                         target, decision, nodes, bool(coupled.any()))
        transforms = result.transforms.copy()
        share = stay_where_better(src, registered, supported, s_rgb, target, decision)
        share[known] = 1.0
        registered = src + share[:, None] * (registered - src)
        share[explained_by_identity(src, registered, supported, s_rgb, target, decision)
              & ~known] = 0.0
        registered = src + share[:, None] * (result.registered - src)
        identity = np.concatenate([np.eye(3), np.zeros((3, 1))], axis=1)
        transforms = share[:, None, None] * transforms + (1 - share[:, None, None]) * identity
        # next to points without target surface, `register`'s along-surface slide is coupled
        # to motions nothing measured: it is dropped unless it explains the data better
        near_lost = coupled & (share > 0) & ~known
        if near_lost.any():
            across = across_only(src, registered, target)
            near_lost &= explained_by(MotionTest(src, registered, supported, s_rgb, across,
                                                 robust=False, only=near_lost),
                                      target, decision)
            registered[near_lost] = across[near_lost]
            transforms[near_lost] = np.concatenate(
                [np.broadcast_to(np.eye(3), (int(near_lost.sum()), 3, 3)),
                 (across[near_lost] - src[near_lost])[:, :, None]], axis=2)
        # nothing measured the motion of a point without target surface, or matched onto
        # the rim of a cut target: beyond its supported neighbours' reach it does not move
        lost = ~supported | (matched_onto_cut(src, registered, supported, target,
                                              decision.spacing_m) & ~known)
        registered = follow_supported(start, registered, ~lost, FOLLOW_REACH_COLOURED,
                                      beyond=start)
    else:
        registered = follow_supported(start, registered, supported)
        lost = ~supported
    transforms[lost] = np.concatenate([np.broadcast_to(np.eye(3), (int(lost.sum()), 3, 3)),
                                       (registered[lost] - start[lost])[:, :, None]], axis=2)
    if pre is not None:
        transforms = compose_affines(transforms, pre.transforms)
    corr = np.where(result.correspondences >= 0, keep[np.maximum(result.correspondences, 0)],
                    -1)
    stats = [dict(s) for s in result.stats]
    stats[0].update({
        "colour_reason": "no colour on both clouds" if decision is None else decision.reason,
        "colour_strays": int(len(tgt) - len(keep)),
        "colour_gradient_per_mm": 0.0 if decision is None else decision.gradient,
        "colour_noise": 0.0 if decision is None else decision.noise,
        "followed": int(lost.sum()),
        "stayed": int((share[supported] < 0.5).sum()),
        "landmark_stage_seconds": 0.0 if pre is None else pre.stats[-1]["total_seconds"],
    })
    if pre is not None:
        stats[-1]["total_seconds"] += pre.stats[-1]["total_seconds"]
    return dataclasses.replace(result, registered=registered, transforms=transforms,
                               correspondences=corr, stats=stats)


def error_estimate_mm(result: RegistrationResult,
                      source: np.ndarray) -> tuple[float, float, str]:
    """(median, p95 mm, what it sees) of the per-point error estimate (hypot of two parts):
    across the surface, the distance to the target's surface (`residuals`); along it, where
    colour decided the matches, the along-surface offset from them (`along_surface`), and
    without colour nothing measures a slide along the surface, so the estimate takes the
    only bound there is: how far each point moved (registered - source (N, 3) m; on the
    benchmark's colourless shapes the true median error is 0.01-0.6x this estimate's, and
    2-40x the across part's alone). NaN without supported points."""
    est = result.residuals * 1e3
    along = result.along_surface
    if along is not None and np.isfinite(along).any():
        est = np.hypot(est, np.nan_to_num(along) * 1e3)
        sees = ("across the surface, and along it from colour (a slide where the texture "
                "is flat, or onto a look-alike texture, cannot be seen)")
    else:
        est = np.hypot(est, np.linalg.norm(result.registered - source, axis=1) * 1e3)
        sees = ("across the surface; along it (no colour) a slide cannot be seen, so it "
                "counts how far each point moved")
    ok = np.isfinite(est)
    if not ok.any():
        return float("nan"), float("nan"), sees
    return float(np.median(est[ok])), float(np.percentile(est[ok], 95)), sees
