"""`register_pair` on colourless shapes (issue 28): landmarks bend the source first, the
transforms still carry the source onto the result, and the settings it picks without
colour leave a caller's values alone."""

from __future__ import annotations

import dataclasses

import numpy as np

from surgrecon_cli.config import RegistrationConfig
from surgrecon_cli.core.geometry.poses import compose_affines
from surgrecon_cli.core.registration.shape import (
    SHAPE_GATE_SPACINGS,
    SHAPE_OUTER,
    after_landmarks_config,
    shape_config,
)
from surgrecon_cli.registration import register_pair


def _bent_sheet(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A 1 m x 0.25 m sheet sampled every ~2 cm (source) and the same points after one half
    is folded 60 degrees about the middle line (truth = target, same order): a large,
    articulated motion, the kind the nearest matches of the unbent sheet get wrong."""
    rng = np.random.default_rng(seed)
    uv = rng.uniform([-0.5, -0.125], [0.5, 0.125], (n, 2))
    src = np.c_[uv, np.zeros(n)]
    ang = np.deg2rad(60.0)
    tgt = src.copy()
    right = src[:, 0] > 0
    x = src[right, 0]
    tgt[right, 0] = x * np.cos(ang)
    tgt[right, 2] = x * np.sin(ang)
    return src, tgt


def test_landmarks_bend_a_folded_sheet_that_nearest_matches_alone_do_not():
    src, tgt = _bent_sheet(1000, 3)
    rng = np.random.default_rng(4)
    pick = rng.choice(len(src), 30, replace=False)
    landmarks = np.c_[pick, pick]  # exact pairs: target i is where source i went
    folded = src[:, 0] > 0.1  # scored where the sheet moved
    nothing = np.median(np.linalg.norm(src - tgt, axis=1)[folded])
    with_lm = register_pair(src, tgt, landmarks=landmarks)
    without = register_pair(src, tgt)
    err_lm = np.median(np.linalg.norm(with_lm.registered - tgt, axis=1)[folded])
    err_none = np.median(np.linalg.norm(without.registered - tgt, axis=1)[folded])
    assert err_lm < 0.01 * nothing  # the fold is found, to 1 % of the motion
    assert err_lm < 0.5 * err_none
    assert with_lm.stats[0]["landmark_stage_seconds"] > 0
    assert without.stats[0]["landmark_stage_seconds"] == 0
    # the two stages' transforms compose: they carry each source point onto its result
    T = with_lm.transforms
    carried = np.einsum("nij,nj->ni", T[:, :, :3], src) + T[:, :, 3]
    assert np.allclose(carried, with_lm.registered, atol=1e-9)


def test_compose_applies_the_first_affine_then_the_second():
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(5, 3, 4)), rng.normal(size=(5, 3, 4))
    p = rng.normal(size=(5, 3))
    first = np.einsum("nij,nj->ni", a[:, :, :3], p) + a[:, :, 3]
    both = np.einsum("nij,nj->ni", b[:, :, :3], first) + b[:, :, 3]
    c = compose_affines(b, a)
    assert np.allclose(np.einsum("nij,nj->ni", c[:, :, :3], p) + c[:, :, 3], both)


def test_colourless_settings_keep_what_the_caller_set():
    default = RegistrationConfig()
    picked = shape_config(default, 0.01)
    assert picked.outer_iterations == SHAPE_OUTER and picked.reweight_mm == 10.0
    after = after_landmarks_config(picked, 0.01)
    assert after.max_correspondence_mm == SHAPE_GATE_SPACINGS * 10.0
    assert after.alpha < default.alpha and after.alpha_start == default.alpha
    own = dataclasses.replace(default, outer_iterations=3, reweight_mm=0.5,
                              max_correspondence_mm=7.0, alpha=0.2)
    assert shape_config(own, 0.01) == own
    assert after_landmarks_config(own, 0.01) == own
    # at the tissue's spacing nothing is raised
    fine = shape_config(default, 0.0005)
    assert fine.reweight_mm == default.reweight_mm
    assert after_landmarks_config(fine, 0.0005).max_correspondence_mm == \
        default.max_correspondence_mm
