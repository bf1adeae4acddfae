"""Issue 14: colour weight from the data, a rigid step that does no harm, partial overlap,
global rotation + scale, residuals that follow the true error.

Pairs from sim/pairs_catalog.py (independent resampling, noise, strays; truth known), small
sizes so that each test runs in about a second. Expected numbers come from the truth.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial import cKDTree
from scipy.stats import spearmanr

from surgrecon_cli.config import RegistrationConfig
from surgrecon_cli.core.registration.surface import analyse_target, colour_weight
from surgrecon_cli.registration import register
from surgrecon_cli.sim.pairs import MM, dome, warp
from surgrecon_cli.sim.pairs_catalog import make_pair


def err_mm(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.linalg.norm(a - b, axis=1) / MM


def _weight(xyz: np.ndarray, rgb: np.ndarray) -> float:
    q = xyz / MM  # millimetres: the weight comes out in mm per RGB unit
    tree = cKDTree(q)
    return colour_weight(q, rgb, tree, ~analyse_target(q, tree).stray, reach=5.0)


def test_colour_weight_follows_the_texture_contrast_and_leaves_flat_colour_out():
    pair = make_pair("tissue", 3000, 0)
    keep = ~pair.target_outlier
    tgt, rgb = pair.target[keep], pair.target_rgb[keep]
    textured = _weight(tgt, rgb)
    # the same texture at half the contrast: colour must weigh twice as much per RGB unit
    halved = _weight(tgt, 0.5 + 0.5 * (rgb - 0.5))
    assert textured > 0 and 1.6 < halved / textured < 2.4
    # flat colour plus 0.02 RGB noise per channel: nothing to decide with, colour stays out
    rng = np.random.default_rng(1)
    assert _weight(tgt, np.clip(0.6 + rng.normal(0, 0.02, rgb.shape), 0, 1)) == 0.0
    # end to end: the automatic weight is what register uses (stats), flat colour gives 0
    res = register(pair.source, pair.target, pair.source_rgb, pair.target_rgb)
    assert res.stats[0]["colour_weight_mm"] > 0
    flat = np.full_like(pair.target_rgb, 0.6)
    res_flat = register(pair.source, pair.target, np.full_like(pair.source_rgb, 0.6), flat)
    assert res_flat.stats[0]["colour_weight_mm"] == 0.0


def test_rigid_step_is_not_worse_than_identity_on_a_static_pair():
    """Target: an independent resampling of the same, unmoved surface with 0.2 mm noise and
    20 % strays; the rigid step must leave the source where it is (truth: identity)."""
    rng = np.random.default_rng(3)
    src = dome(3000, rng)
    tgt = dome(3000, rng)
    tgt = tgt + rng.normal(0, 0.2 * MM, tgt.shape)
    k = 600
    d = rng.normal(size=(k, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    tgt = np.r_[tgt, tgt[rng.integers(0, len(tgt), k)] + d * rng.uniform(1, 5, (k, 1)) * MM]
    res = register(src, tgt)
    rigid = res.stats[0]
    moved = src @ (rigid["scale"] * rigid["rotation"]).T + rigid["translation_m"]
    assert np.median(err_mm(moved, src)) < 0.05  # the noise is 0.2 mm
    assert np.median(err_mm(res.registered, src)) < 0.2  # no colour: some slide remains


def test_partial_pair_leaves_unsupported_points_unobserved():
    pair = make_pair("tissue_partial", 3000, 1)
    res = register(pair.source, pair.target, pair.source_rgb, pair.target_rgb)
    surface = pair.target[~pair.target_outlier]
    gap = cKDTree(surface).query(pair.truth)[0] / MM  # truth to the true target surface
    beyond, inside = gap > 3.0, gap < 0.5
    assert beyond.sum() > 300  # the cut leaves a part of the source without target
    assert (~res.supported[beyond]).mean() > 0.9 and res.supported[inside].mean() > 0.9
    assert np.all(np.isnan(res.residuals[~res.supported]))
    matched = res.correspondences[res.correspondences >= 0]
    assert pair.target_outlier[matched].mean() < 0.01  # strays are not matched
    e, e0 = err_mm(res.registered, pair.truth), err_mm(pair.source, pair.truth)
    assert np.median(e) < 0.4 and np.percentile(e, 95) < 2.0
    # past the cut the points are not worse than doing nothing (within the 0.2 mm noise)
    assert np.median(e[beyond]) < np.median(e0[beyond]) + 0.2


def test_large_rotation_and_scale_are_recovered():
    pair = make_pair("rotation", 2000, 2)
    res = register(pair.source, pair.target)
    assert abs(res.stats[0]["scale"] - 0.8) < 0.05
    assert np.median(err_mm(res.registered, pair.truth)) < 0.02 * pair.diagonal_m / MM


def test_residual_follows_the_true_error():
    """A sharp 4 mm dent the stiff setting cannot follow: the points that miss it are the
    ones whose residual (distance to the target's local surface) is large."""
    rng = np.random.default_rng(4)
    src = dome(2500, rng)

    def moved(p: np.ndarray) -> np.ndarray:
        x, y = p[:, 0] / MM, p[:, 1] / MM
        out = warp(p)
        out[:, 2] -= 4.0 * MM * np.exp(-((x - 5) ** 2 + (y + 3) ** 2) / (2 * 2.5**2))
        return out

    truth = moved(src)
    tgt = moved(dome(2500, rng)) + rng.normal(0, 0.1 * MM, src.shape)
    stiff = dataclasses.replace(RegistrationConfig(), alpha=1.0, alpha_start=1.0)
    res = register(src, tgt, config=stiff)
    e = err_mm(res.registered, truth)
    ok = np.isfinite(res.residuals)
    assert ok.mean() > 0.9 and e.max() > 1.0  # the dent is missed somewhere
    r, e = res.residuals[ok], e[ok]
    assert spearmanr(r, e)[0] > 0.4  # slides along the surface stay invisible to it
    failed, fine = e > 1.0, e < 0.3
    assert np.median(r[failed]) > 5 * np.median(r[fine])
