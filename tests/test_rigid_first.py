"""Registration that keeps up with a scene moving rigidly (issue 24, item 3): the robust
rigid fit, and unobserved points following the rigid motion instead of staying behind."""

from __future__ import annotations

import numpy as np

from surgrecon_cli.config import Config
from surgrecon_cli.core.classify.labels import INTER, UNOBSERVED
from surgrecon_cli.core.noise.model import NoiseModel
from surgrecon_cli.core.registration.frame_step import DataTerm, data_weights, register_rigid_first
from surgrecon_cli.core.registration.rigid_fit import robust_rigid
from surgrecon_cli.core.target.cloud import TargetCloud
from surgrecon_cli.sim.motion import _rotation


def _patch(n_side: int = 36, size: float = 0.04) -> np.ndarray:
    """A gently curved tissue patch (n_side², 3) m, `size` m across, 40 mm in front."""
    g = np.linspace(-size / 2, size / 2, n_side)
    x, y = np.meshgrid(g, g)
    z = 0.04 + 0.004 * np.cos(x / size * 3) * np.cos(y / size * 2)
    return np.column_stack([x.ravel(), y.ravel(), z.ravel()])


def _motion(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A camera sweep seen from the rig: 4 deg about a tilted axis through a point 20 mm in
    front of the camera, i.e. ~1.4 mm of motion at the tissue, plus 2 mm sideways."""
    R = _rotation(np.radians(4.0) * np.array([0.2, 0.97, 0.1]) / np.linalg.norm([0.2, 0.97, 0.1]))
    pivot = np.array([0.0, 0.0, 0.02])
    t = pivot - R @ pivot + np.array([0.002, 0.0, 0.0])
    return points @ R.T + t, R, t


def test_robust_rigid_finds_the_scene_motion_among_deforming_points():
    src = _patch()
    dst, R, t = _motion(src)
    rng = np.random.default_rng(1)
    dst = dst + rng.normal(0, 5e-5, dst.shape)
    bad = rng.random(len(src)) < 0.4  # 40 % pushed 2-8 mm away (a tool, mistracks)
    dst[bad] += rng.uniform(0.002, 0.008, (bad.sum(), 1)) * rng.normal(size=(bad.sum(), 3))
    R_fit, t_fit, inliers = robust_rigid(src, dst, inlier_m=5e-4)
    good = ~bad
    moved = src @ R_fit.T + t_fit
    truth = src @ R.T + t
    assert np.abs(moved - truth).max() < 1e-4  # every point, not only the inliers
    assert inliers[good].mean() > 0.99
    assert inliers[bad].mean() < 0.2


def test_robust_rigid_without_enough_pairs_is_the_identity():
    R, t, inliers = robust_rigid(np.zeros((3, 3)), np.ones((3, 3)), inlier_m=1e-3)
    assert np.allclose(R, np.eye(3)) and np.allclose(t, 0) and not inliers.any()


def test_unobserved_points_follow_the_scene_rigid_motion():
    # Only a 12 mm corner of the 40 mm patch is observed (the rest briefly out of view):
    # the rest must move with the scene, not stay where it was.
    source = _patch()
    truth, _, _ = _motion(source)
    n = len(source)
    observed = (source[:, 0] < -0.008) & (source[:, 1] < -0.008)
    rng = np.random.default_rng(2)
    positions = np.where(observed[:, None], truth + rng.normal(0, 5e-5, truth.shape), source)
    status = np.where(observed, INTER, UNOBSERVED).astype(np.uint8)
    sigma = np.where(observed, 1e-4, np.nan)
    target = TargetCloud(
        positions=positions, status=status, views=np.where(observed, 2, 0),
        pixels=np.full((n, 2, 2), np.nan), covariance=np.full((n, 3, 3), np.nan),
        pose_covariance=np.zeros((n, 3, 3)), sigma=sigma,
        noise=NoiseModel(0.2, 0.2, 0.0, 0.0))
    ids = np.flatnonzero(observed)
    rgb = np.full((n, 3), 128, np.uint8)
    data = DataTerm(positions[ids], rgb[ids], ids, data_weights(target, has_new=False))
    result, _ = register_rigid_first(source, rgb, target, data, np.full((4, 4), np.nan),
                                     Config())
    error = np.linalg.norm(result.registered - truth, axis=1)
    assert observed.mean() < 0.15
    assert np.percentile(error[~observed], 95) < 3e-4  # motion: 1.4-3.4 mm
    # The transforms carry the rigid part too: source -> registered.
    carried = np.einsum("nij,nj->ni", result.transforms[:, :, :3], source)
    assert np.abs(carried + result.transforms[:, :, 3] - result.registered).max() < 1e-9
