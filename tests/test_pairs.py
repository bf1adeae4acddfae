"""The registration pair generators (sim/pairs*.py) against their own geometry: targets lie
on the truly moved surface within their noise (strays and spikes do not), the truth lies on
that surface too, source and target are independent samples, a partial target loses its
share, the rotation pair's truth is the similarity s R x + t, and seeds reproduce."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from surgrecon_cli.sim.pairs import MM, tissue_pair, tissue_scene
from surgrecon_cli.sim.pairs_catalog import ACCEPTANCE_SEEDS, FAMILIES, TUNING_SEEDS, make_pair
from surgrecon_cli.sim.pairs_shapes import rotation_pair, shape_motion, shape_pair, shape_sampler


def surface_distance(points: np.ndarray, dense: np.ndarray) -> np.ndarray:
    return cKDTree(dense).query(points)[0]


def plane_distance(points: np.ndarray, dense: np.ndarray) -> np.ndarray:
    """Distance (N,) from points to the plane fitted (PCA) to their 10 nearest dense points:
    a surface distance that does not need a fine dense sample."""
    nb = dense[cKDTree(dense).query(points, k=10)[1]]
    centred = nb - nb.mean(1, keepdims=True)
    normal = np.linalg.eigh(np.einsum("nki,nkj->nij", centred, centred))[1][:, :, 0]
    return np.abs(((points - nb.mean(1)) * normal).sum(1))


def test_tissue_target_on_the_warped_surface_within_noise_strays_off_it():
    pair = tissue_pair(3000, seed=5)
    scene = tissue_scene(5)
    dense = scene.warp(scene.surface(300_000, np.random.default_rng(99)))  # ~0.08 mm spacing
    d = surface_distance(pair.target, dense) / MM
    inl = ~pair.target_outlier
    # 0.2 mm per axis: the distance to the surface is |normal noise|, median 0.13 mm
    assert 0.08 < np.median(d[inl]) < 0.2 and np.percentile(d[inl], 99) < 0.7
    assert pair.target_outlier.sum() == round(0.2 * 3000) and np.median(d[~inl]) > 1.0
    # the truth of every source point lies on the same moved surface
    assert np.percentile(surface_distance(pair.truth, dense) / MM, 99) < 0.15
    assert 1.0 < np.median(np.linalg.norm(pair.truth - pair.source, axis=1) / MM) < 2.5
    assert pair.source_rgb is not None and pair.target_rgb is not None
    assert pair.source_rgb.shape == pair.source.shape and pair.target_rgb.shape == pair.target.shape


def test_tissue_source_and_target_are_independent_samples():
    pair = tissue_pair(3000, seed=6, noise_mm=0.0, outliers=0.0)
    gap = surface_distance(pair.truth, pair.target) / MM
    assert (gap < 1e-6).sum() == 0 and np.median(gap) > 0.1  # no moved source point reappears


def test_tissue_partial_cuts_a_contiguous_side():
    full, part = tissue_pair(4000, seed=7), tissue_pair(4000, seed=7, partial=0.3)
    kept = part.target[~part.target_outlier]
    assert len(kept) == pytest.approx(0.7 * 4000, abs=2)
    assert part.target_outlier.sum() == round(0.2 * len(kept))
    # the missing third is one side: many source points have no target within 3 mm
    far = surface_distance(part.truth, kept) > 3 * MM
    assert 0.2 < far.mean() < 0.4
    assert (surface_distance(full.truth, full.target[~full.target_outlier]) > 3 * MM).mean() == 0


@pytest.mark.parametrize("shape", ["blob", "torus", "limb"])
def test_shape_scan_on_the_moved_surface(shape):
    pair = shape_pair(shape, 2000, seed=3)
    sampler = shape_sampler(shape, 3)
    motion = shape_motion(shape, 3, sampler, 0.1)
    dense = motion(sampler(30_000, np.random.default_rng(98))[0])
    diag = pair.diagonal_m
    inl = ~pair.target_outlier
    d = plane_distance(pair.target[inl], dense) / diag
    assert 0.0004 < np.median(d) < 0.001  # noise 0.1 % per axis: median |normal noise| 0.067 %
    assert np.median(surface_distance(pair.target[~inl], dense)) / diag > 0.015  # spikes 2-8 %
    assert 0.005 < pair.target_outlier.mean() < 0.04
    on = plane_distance(pair.truth, dense) / diag  # exact up to the plane fit's curvature error
    assert np.median(on) < 3e-4 and np.percentile(on, 95) < 1e-3  # noise alone: 6.7e-4
    motion_size = np.linalg.norm(pair.truth - pair.source, axis=1).max() / diag
    assert 0.07 < motion_size < 0.14  # motion up to ~10 % of the size


def test_single_view_scan_keeps_about_half():
    pair = shape_pair("blob", 2000, seed=4, partial=True)
    assert 0.35 < len(pair.target) / 2000 < 0.65


def fit_similarity(a: np.ndarray, b: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares b ~ s R a + t (Umeyama): scale, rotation, residuals (N,)."""
    ca, cb = a - a.mean(0), b - b.mean(0)
    u, sv, vt = np.linalg.svd(cb.T @ ca)
    d = np.diag([1, 1, np.sign(np.linalg.det(u @ vt))])
    rot = u @ d @ vt
    s = float((sv * np.diag(d)).sum() / (ca**2).sum())
    return s, rot, np.linalg.norm(s * ca @ rot.T - cb, axis=1)


def test_rotation_truth_is_a_similarity():
    pair = rotation_pair(1500, seed=8, shape="blob", nonrigid=0.0)
    s, rot, res = fit_similarity(pair.source, pair.truth)
    angle = np.degrees(np.arccos((np.trace(rot) - 1) / 2))
    assert s == pytest.approx(0.8, abs=1e-9) and angle == pytest.approx(90, abs=1e-6)
    assert res.max() < 1e-9
    mild = rotation_pair(1500, seed=8, shape="blob")  # plus 3 % non-rigid
    s, rot, res = fit_similarity(mild.source, mild.truth)
    assert s == pytest.approx(0.8, abs=0.03) and np.median(res) / mild.diagonal_m < 0.03


def test_seeds_reproduce_and_differ():
    a, b, c = (make_pair("torus", 1000, s) for s in (2, 2, 3))
    for x, y in ((a.source, b.source), (a.target, b.target), (a.truth, b.truth)):
        np.testing.assert_array_equal(x, y)
    assert not np.allclose(a.target[:10], c.target[:10])
    assert not set(TUNING_SEEDS) & set(ACCEPTANCE_SEEDS)
    assert {"tissue", "tissue_partial", "rotation", "body", "blob_noisy"} <= set(FAMILIES)
