"""Sparse non-rigid registration on seeded synthetic surfaces with known ground truth.

Surface: a bumpy dome ~50 mm across (metres); motion: a breathing-like smooth shift plus a
5 mm Gaussian indentation; 0.2 mm noise. The target holds the same material points as the
source (shuffled), so each registered point has a true position. Tolerances are ours.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from surgrecon_cli.config import ConfigError, RegistrationConfig, from_dict
from surgrecon_cli.core.geometry.poses import quat_to_matrix
from surgrecon_cli.errors import GeometryError
from surgrecon_cli.registration import apply_transforms, register
from surgrecon_cli.sim.pairs import MM, dome, texture, warp


def make(n: int = 2500, seed: int = 0, noise_mm: float = 0.2):
    """source, target (shuffled), colours, truth (true moved source), order (target -> source)."""
    rng = np.random.default_rng(seed)
    src = dome(n, rng)
    truth = warp(src)
    order = rng.permutation(n)
    tgt = (truth + rng.normal(0, noise_mm * MM, truth.shape))[order]
    return src, tgt, texture(src), texture(src)[order], truth, order


def err_mm(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.linalg.norm(a - b, axis=1) / MM


def test_recovers_known_smooth_warp_with_indentation():
    src, tgt, srgb, trgb, truth, _ = make()
    res = register(src, tgt, srgb, trgb)
    e = err_mm(res.registered, truth)
    assert np.median(e) < 0.15 and np.percentile(e, 95) < 0.4  # noise is 0.2 mm per axis
    dent = np.linalg.norm(src[:, :2] / MM - [-6, 4], axis=1) < 3  # the indentation's core
    assert np.median(e[dent]) < 0.4
    # every output is consistent: transforms applied to the source give `registered`
    moved = np.einsum("nij,nj->ni", res.transforms[:, :, :3], src) + res.transforms[:, :, 3]
    np.testing.assert_allclose(moved, res.registered, atol=1e-9)
    assert res.transforms.shape == (len(src), 3, 4) and res.residuals.shape == (len(src),)
    assert len(res.stats) == RegistrationConfig().outer_iterations + 1


def test_geometry_only_recovers_warp():
    src, tgt, *_, truth, _ = make(seed=1)
    e = err_mm(register(src, tgt).registered, truth)
    assert np.median(e) < 0.3


def test_identity_when_source_equals_target():
    rng = np.random.default_rng(2)
    src = dome(1500, rng)
    res = register(src, src.copy())
    assert err_mm(res.registered, src).max() < 0.01
    eye = np.concatenate([np.eye(3), np.zeros((3, 1))], axis=1)
    assert np.abs(res.transforms - eye).max() < 1e-3
    assert not res.outliers.any() and np.all(res.correspondences == np.arange(len(src)))


def test_independent_of_point_order():
    src, tgt, srgb, trgb, _, _ = make(2000, seed=3)
    a = register(src, tgt, srgb, trgb)
    rng = np.random.default_rng(9)
    ps, pt = rng.permutation(len(src)), rng.permutation(len(tgt))
    b = register(src[ps], tgt[pt], srgb[ps], trgb[pt])
    assert err_mm(b.registered, a.registered[ps]).max() < 1e-3
    mapped = np.where(b.correspondences >= 0, pt[b.correspondences], -1)
    assert np.array_equal(mapped, a.correspondences[ps])


def test_gross_outliers_l1_robust_l2_not():
    """20 % of known correspondences displaced 3-8 mm: l1 data term shrugs, l2 is dragged."""
    src, tgt, *_, truth, order = make(2000, seed=4)
    rng = np.random.default_rng(5)
    bad = rng.random(len(tgt)) < 0.2
    d = rng.normal(size=(bad.sum(), 3))
    tgt = tgt.copy()
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    tgt[bad] += d * rng.uniform(3, 8, (bad.sum(), 1)) * MM
    cfg = dataclasses.replace(RegistrationConfig(), reweight_mm=0.0)  # pure l1 vs pure l2
    e1 = err_mm(register(src, tgt, config=cfg, target_ids=order).registered, truth)
    e2 = err_mm(register(src, tgt, config=dataclasses.replace(cfg, data_penalty="l2"),
                         target_ids=order).registered, truth)
    assert np.median(e1) < 0.25  # bound for l1
    assert np.median(e2) > 0.5 and np.median(e2) > 3 * np.median(e1)  # l2 does not meet it
    outlier_ids = order[bad]
    res = register(src, tgt, target_ids=order)  # default: l1 + reweighting
    assert res.outliers[outlier_ids].mean() > 0.9 and res.outliers.mean() < 0.3


def test_unobserved_points_follow_neighbours():
    src, tgt, srgb, trgb, truth, _ = make(2500, seed=6)
    hole = np.linalg.norm(src[:, :2] / MM - [10, -8], axis=1) < 5
    w = np.where(hole, 0.0, 1.0)
    res = register(src, tgt, srgb, trgb, weights=w)
    e = err_mm(res.registered, truth)
    moved_mm = err_mm(truth, src)
    assert moved_mm[hole].mean() > 1.0  # they did move...
    assert np.median(e[hole]) < 0.4  # ...and followed their neighbours
    assert np.all(res.correspondences[hole] == -1) and np.all(np.isnan(res.residuals[hole]))


def test_partial_overlap():
    src, tgt, *_, truth, _ = make(3000, seed=7)
    keep = tgt[:, 0] > np.quantile(tgt[:, 0], 0.3)
    res = register(src, tgt[keep])
    e = err_mm(res.registered, truth)
    seen = truth[:, 0] > np.quantile(tgt[:, 0], 0.3) + 2 * MM
    assert np.median(e[seen]) < 0.3 and np.median(e) < 1.0


def test_rotated_and_shifted_target_with_colour():
    src, tgt, srgb, trgb, truth, _ = make(2000, seed=8)
    axis = np.array([1.0, 2.0, 0.5]) / np.sqrt(5.25)
    R = quat_to_matrix(np.r_[axis * np.sin(0.17), np.cos(0.17)])  # 19.5 degrees
    c, t = src.mean(axis=0), np.array([8.0, -4.0, 3.0]) * MM
    res = register(src, (tgt - c) @ R.T + c + t, srgb, trgb)
    assert np.median(err_mm(res.registered, (truth - c) @ R.T + c + t)) < 0.2


def test_landmarks_and_per_point_model():
    """max_nodes = 0 is the paper's one-affine-per-point model; landmarks keep their pairs."""
    src, tgt, *_, truth, order = make(600, seed=9, noise_mm=0.0)
    inv = np.argsort(order)  # source i is target inv[i]
    lm = np.c_[np.arange(0, 600, 50), inv[np.arange(0, 600, 50)]]
    cfg = dataclasses.replace(RegistrationConfig(), max_nodes=0)
    res = register(src, tgt, config=cfg, landmarks=lm)
    assert np.array_equal(res.correspondences[lm[:, 0]], lm[:, 1])
    assert np.median(err_mm(res.registered, truth)) < 0.3


def test_apply_transforms_to_other_points():
    src, tgt, srgb, trgb, _, _ = make(2000, seed=10)
    res = register(src, tgt, srgb, trgb)
    np.testing.assert_allclose(apply_transforms(res, src, src), res.registered, atol=1e-12)
    rng = np.random.default_rng(11)
    others = dome(300, rng)
    assert np.median(err_mm(apply_transforms(res, src, others), warp(others))) < 0.3


def test_callback_and_stats():
    src, tgt, *_ = make(800, seed=12)
    seen = []
    res = register(src, tgt, callback=lambda i, state: seen.append((i, state["stage"])))
    n_outer = RegistrationConfig().outer_iterations
    assert [i for i, _ in seen] == list(range(n_outer + 1)) and seen[0][1] == "rigid"
    assert all("median_residual_mm" in s for s in res.stats[1:])


def test_inputs_are_validated_and_not_mutated():
    src, tgt, *_ = make(500, seed=13)
    before = src.copy()
    register(src, tgt)
    assert np.array_equal(src, before)
    with pytest.raises(GeometryError, match="source_xyz"):
        register(src[:, :2], tgt)
    bad = tgt.copy()
    bad[3, 1] = np.nan
    with pytest.raises(GeometryError, match="non-finite"):
        register(src, bad)
    with pytest.raises(GeometryError, match="weights"):
        register(src, tgt, weights=-np.ones(len(src)))
    with pytest.raises(GeometryError, match="target_ids"):
        register(src, tgt, target_ids=np.full(len(tgt), len(src)))
    with pytest.raises(GeometryError, match="landmarks"):
        register(src, tgt, landmarks=np.array([[0, len(tgt)]]))


def test_config_validation():
    with pytest.raises(ConfigError, match="data_penalty"):
        from_dict({"registration": {"data_penalty": "huber"}})
    with pytest.raises(ConfigError, match="alpha"):
        from_dict({"registration": {"alpha": 5.0, "alpha_start": 1.0}})
    with pytest.raises(ConfigError, match="relaxation"):
        from_dict({"registration": {"relaxation": 2.5}})


def test_scale_invariant_when_mm_thresholds_scale_too():
    src, tgt, srgb, trgb, _, _ = make(1200, seed=14)
    cfg = RegistrationConfig()
    a = register(src, tgt, srgb, trgb, cfg)
    s = 4.0
    scaled = dataclasses.replace(
        cfg, **{k: getattr(cfg, k) * s for k in (
            "tolerance_mm", "color_weight_mm", "max_correspondence_mm", "reweight_mm",
            "outlier_mm")})
    b = register(src * s, tgt * s, srgb, trgb, scaled)
    assert err_mm(b.registered / s, a.registered).max() < 1e-3
    np.testing.assert_allclose(b.transforms[:, :, :3], a.transforms[:, :, :3], atol=1e-6)
