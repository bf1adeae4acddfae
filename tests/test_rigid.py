"""Rigid pre-alignment (core/registration/rigid.py) and the rigid fit it builds on
(core/geometry.fit_rigid), against known rotations and translations: exact on noise-free
pairs, within the least-squares noise bound with noise, robust to gross outliers where a
plain least-squares fit is not; trimmed ICP without known pairs aligns a surface to within
its noise (distance to the analytic surface).
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from surgrecon_cli.core.geometry.poses import fit_rigid
from surgrecon_cli.core.registration.correspondences import KnownPairs, build_matcher
from surgrecon_cli.core.registration.graph import mean_spacing
from surgrecon_cli.core.registration.rigid import (
    MIN_KNOWN,
    PrealignSettings,
    SourcePoints,
    rigid_prealign,
)
from surgrecon_cli.sim.pairs import dome

UNIT = 5e-3  # the dome (metres) in normalised units of 5 mm, as the solver would see it


def prealign(src, tgt, target_ids=None, observed=None):
    matcher = build_matcher(tgt, len(src), None, 0.0, KnownPairs(target_ids=target_ids))
    tree = cKDTree(tgt)
    spacing = mean_spacing(src)
    return rigid_prealign(
        SourcePoints(src, None, np.ones(len(src), bool) if observed is None else observed),
        matcher, tree, PrealignSettings(
            iterations=30, keep=0.8, spacing=spacing,
            target_spacing=float(np.median(tree.query(tgt, k=2)[0][:, 1])), gate=5 * spacing))


def motion(rng, degrees: float, shift: float):
    R = Rotation.from_rotvec(np.radians(rng.uniform(-degrees, degrees, 3))).as_matrix()
    return R, rng.uniform(-shift, shift, 3)


def rms(a, b):
    return float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=1))))


def dome_height_residual(p: np.ndarray) -> np.ndarray:
    """Signed height (normalised units) of points above the analytic dome of sim.pairs."""
    x, y = p[:, 0] * UNIT * 1e3, p[:, 1] * UNIT * 1e3  # mm
    z = 8.0 * (1 - (np.hypot(x, y) / 25.0) ** 2) + 0.6 * np.sin(x / 4.0) * np.cos(y / 5.0)
    return p[:, 2] - z * 1e-3 / UNIT


# ---- the rigid fit ------------------------------------------------------------------------


def test_fit_rigid_is_exact_weighted_batched_and_proper():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(4, 30, 3))
    R = Rotation.random(4, random_state=1).as_matrix()
    t = rng.normal(size=(4, 3))
    dst = np.einsum("bij,bnj->bni", R, src) + t[:, None]
    R_est, t_est = fit_rigid(src, dst)
    np.testing.assert_allclose(R_est, R, atol=1e-12)
    np.testing.assert_allclose(t_est, t, atol=1e-12)
    # zero weights ignore points whatever they are
    bad = dst.copy()
    bad[:, :10] += 5.0
    w = np.ones((4, 30))
    w[:, :10] = 0.0
    R_w, t_w = fit_rigid(src, bad, w)
    np.testing.assert_allclose(R_w, R, atol=1e-12)
    np.testing.assert_allclose(t_w, t, atol=1e-12)
    # a mirrored target has no rotation onto it: the fit stays a rotation (det +1)
    R_m, _ = fit_rigid(src[0], src[0] * [1.0, 1.0, -1.0])
    assert np.linalg.det(R_m) == pytest.approx(1.0)
    np.testing.assert_allclose(R_m @ R_m.T, np.eye(3), atol=1e-12)


# ---- known pairs: the l1 fit --------------------------------------------------------------


@pytest.fixture(scope="module")
def pairs():
    """200 points in a 2-unit box, moved by a known motion; the target lists them shuffled
    with `target_ids` telling which source point each is."""
    rng = np.random.default_rng(2)
    src = rng.uniform(-1.0, 1.0, (200, 3))
    R, t = motion(rng, 12.0, 0.3)
    order = rng.permutation(len(src))
    return src, R, t, order, rng


def test_known_pairs_recover_the_motion_exactly(pairs):
    src, R, t, order, _ = pairs
    R_est, t_est = prealign(src, (src @ R.T + t)[order], target_ids=order)
    np.testing.assert_allclose(R_est, R, atol=1e-9)
    np.testing.assert_allclose(t_est, t, atol=1e-9)


def test_known_pairs_with_noise_and_outliers(pairs):
    """sigma = 0.01 per axis. The least-squares error of a 6-parameter fit moves the N points
    by sigma sqrt(6 / N) RMS on average; allow 3x that. With 20 % of the pairs gross
    outliers the l1 fit stays inside the same bound, a plain least-squares fit does not."""
    src, R, t, order, rng = pairs
    sigma = 0.01
    truth = src @ R.T + t
    tgt = truth[order] + rng.normal(0, sigma, src.shape)
    bound = 3 * sigma * np.sqrt(6 / len(src))
    R_est, t_est = prealign(src, tgt, target_ids=order)
    assert rms(src @ R_est.T + t_est, truth) < bound
    outliers = rng.choice(len(src), len(src) // 5, replace=False)
    tgt[outliers] += rng.normal(0, 1.0, (len(outliers), 3))
    R_est, t_est = prealign(src, tgt, target_ids=order)
    assert rms(src @ R_est.T + t_est, truth) < bound
    R_ls, t_ls = fit_rigid(src, tgt[np.argsort(order)])
    assert rms(src @ R_ls.T + t_ls, truth) > 5 * bound


def test_min_known_observed_pairs_decide_and_unobserved_ones_do_not_count(pairs):
    """MIN_KNOWN observed known pairs fix a large motion (40 deg, beyond any ICP) exactly,
    although 100 unobserved points carry wrong ids (if they counted, they would outvote the
    right ones even in an l1 fit)."""
    src, _, _, _, rng = pairs
    R = Rotation.from_rotvec(np.radians([40.0, -25.0, 10.0])).as_matrix()
    t = np.array([2.0, -1.0, 0.5])
    tgt = src @ R.T + t  # target point i is source point i
    ids = np.full(len(src), -1)
    observed = np.zeros(len(src), bool)
    right = np.arange(MIN_KNOWN)
    ids[right], observed[right] = right, True
    wrong = np.arange(50, 150)
    ids[wrong] = rng.permutation(wrong)  # unobserved points, wrong partners
    R_est, t_est = prealign(src, tgt, target_ids=ids, observed=observed)
    np.testing.assert_allclose(R_est, R, atol=1e-9)
    np.testing.assert_allclose(t_est, t, atol=1e-9)


# ---- no known pairs: trimmed point-to-plane ICP on a surface ------------------------------


@pytest.mark.parametrize("seed", [0, 1])
def test_icp_on_the_same_points_recovers_the_motion(seed):
    """Target = the source's own points moved (3 deg, 0.15 units ~ 1.5 spacings) and
    shuffled: once the nearest neighbours are the true pairs, point-to-plane steps converge
    quadratically; the result is exact to far below the point spacing."""
    rng = np.random.default_rng(seed)
    src = dome(2000, rng) / UNIT
    R, t = motion(rng, 3.0, 0.15)
    truth = src @ R.T + t
    R_est, t_est = prealign(src, truth[rng.permutation(len(src))])
    assert rms(src @ R_est.T + t_est, truth) < 1e-6
    np.testing.assert_allclose(R_est, R, atol=1e-6)


@pytest.mark.parametrize(("lifted", "height"), [(0.0, 0.0), (0.1, 1.0), (0.2, 0.1)])
def test_icp_aligns_a_resampled_noisy_surface_within_its_noise(lifted, height):
    """Target: another sampling of the moved dome with sigma = 0.02 noise (0.2 spacings), and
    optionally a fraction of it lifted off the surface by 0.5..2 x `height` units (outliers
    far off, or within the mutual gate of 3 spacings). Moved back by the true motion, the
    aligned source must lie on the analytic dome within sigma RMS (the unaligned source is
    several sigma off)."""
    rng = np.random.default_rng(5)
    src = dome(2000, rng) / UNIT
    R, t = motion(rng, 3.0, 0.15)
    tgt = (dome(2000, rng) / UNIT) @ R.T + t + rng.normal(0, 0.02, (2000, 3))
    k = int(lifted * len(tgt))
    tgt[:k] += R[:, 2] * rng.uniform(0.5, 2.0, (k, 1)) * height
    R_est, t_est = prealign(src, tgt)
    back = (src @ R_est.T + t_est - t) @ R  # the aligned source in the dome's frame
    assert np.sqrt(np.mean(dome_height_residual(back) ** 2)) < 0.02
    unaligned = (src - t) @ R
    assert np.sqrt(np.mean(dome_height_residual(unaligned) ** 2)) > 3 * 0.02


def test_too_few_observed_points_give_the_identity(pairs):
    src, R, t, *_ = pairs
    observed = np.zeros(len(src), bool)
    observed[:2] = True
    R_est, t_est = prealign(src, src @ R.T + t, observed=observed)
    np.testing.assert_array_equal(R_est, np.eye(3))
    np.testing.assert_array_equal(t_est, np.zeros(3))


def test_mutual_check_keeps_exactly_the_pairs_a_brute_force_check_keeps():
    # the matcher's mutual check skips the look-up where the triangle inequality settles it;
    # the kept pairs must be those of the plain rule (the target's nearest moved point lies
    # within the mutual distance of the querying point), here by brute force
    from surgrecon_cli.core.registration.correspondences import match

    rng = np.random.default_rng(11)
    tgt = rng.uniform(0.0, 10.0, (400, 3))
    moved = np.r_[tgt[:300] + rng.normal(0.0, 0.3, (300, 3)), rng.uniform(0.0, 10.0, (200, 3))]
    matcher = build_matcher(tgt, len(moved), None, 0.0, KnownPairs())
    every = np.ones(len(moved), bool)
    unchecked = match(matcher, moved, None, 2.0, 0.0, every)  # 0: no mutual check
    has = unchecked >= 0
    assert has.sum() > 300
    partner = tgt[np.maximum(unchecked, 0)]
    back = np.argmin(np.linalg.norm(partner[:, None] - moved[None], axis=2), axis=1)
    for mutual in (0.2, 0.6, 1.5, 4.0):
        corr = match(matcher, moved, None, 2.0, mutual, every)
        keep = has & (np.linalg.norm(moved[back] - moved, axis=1) <= mutual)
        assert keep.sum() > 0
        np.testing.assert_array_equal(corr, np.where(keep, unchecked, -1))
    # both regimes occur: pairs the triangle inequality settles, pairs the check drops
    dist = np.linalg.norm(moved - partner, axis=1)
    assert np.sum(has & (2 * dist <= 0.6)) > 50
    assert np.sum(has & (np.linalg.norm(moved[back] - moved, axis=1) > 0.6)) > 20
