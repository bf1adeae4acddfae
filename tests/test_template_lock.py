"""Tracks locked to the template's images (core/target/template_lock.py) on a synthetic
texture seen again through a known perspective-like warp: the true position of every point
is known, so drifted tracks must come back to it and true tracks must stay there."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from surgrecon_cli.core.noise.frame_noise import LocalFits
from surgrecon_cli.core.target.template_lock import lock_groups, lock_to_template, shared_drift
from surgrecon_cli.core.target.tracking import tracking_view

SIZE = (480, 640)  # H, W


def texture(seed: int) -> np.ndarray:
    """An RGB tissue-like texture (H, W, 3) uint8: blobs at several scales."""
    rng = np.random.default_rng(seed)
    grey = np.zeros(SIZE, np.float32)
    for sigma, weight in ((1.5, 0.5), (4.0, 1.0), (10.0, 1.0)):
        grey += weight * cv2.GaussianBlur(rng.normal(0, 1, SIZE).astype(np.float32), (0, 0),
                                          sigma) * sigma
    grey = 128 + 40 * grey / grey.std()
    return np.repeat(np.clip(grey, 0, 255).astype(np.uint8)[..., None], 3, 2)


def warp() -> np.ndarray:
    """A homography (3, 3) of the image: 12° rotation, 8 % zoom, a perspective tilt and a
    shift (a scope turned and moved over several frames)."""
    angle = np.radians(12.0)
    c, s = np.cos(angle), np.sin(angle)
    centre = np.array([[1, 0, -320], [0, 1, -240], [0, 0, 1]], float)
    turn = np.array([[1.08 * c, -1.08 * s, 0], [1.08 * s, 1.08 * c, 0], [2e-4, 1e-4, 1]])
    back = np.array([[1, 0, 320 + 9.0], [0, 1, 240 - 6.0], [0, 0, 1]], float)
    return back @ turn @ centre


def apply(h: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Pixels (M, 2) mapped by homography h."""
    p = np.column_stack([xy, np.ones(len(xy))]) @ h.T
    return p[:, :2] / p[:, 2:]


@pytest.fixture(scope="module")
def scene():
    rgb0 = texture(3)
    h = warp()
    rgb1 = cv2.warpPerspective(rgb0, h, SIZE[::-1], flags=cv2.INTER_CUBIC)
    rng = np.random.default_rng(5)
    start = rng.uniform([80, 80], [560, 400], (400, 2))
    return tracking_view(rgb0), tracking_view(rgb1), start, apply(h, start)


def test_drifted_tracks_come_back_to_their_points(scene):
    """Tracks 0.3-1.2 px off their true positions (the drift of a chained KLT window) end
    within 0.1 px of them (median), each closer than it started."""
    view0, view1, start, truth = scene
    rng = np.random.default_rng(7)
    direction = rng.normal(size=truth.shape)
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    drift = direction * rng.uniform(0.3, 1.2, (len(truth), 1))
    correction = lock_to_template(view0, view1, start, truth + drift, 21)
    assert np.isfinite(correction).all(1).mean() > 0.95
    locked = truth + drift + np.nan_to_num(correction)
    before = np.linalg.norm(drift, axis=1)
    after = np.linalg.norm(locked - truth, axis=1)
    assert np.median(after) < 0.1
    assert np.mean(after < before) > 0.95


def test_true_tracks_stay_and_lost_ones_are_left_alone(scene):
    """Tracks at their true positions move by < 0.1 px (median); NaN tracks and points
    without a frame-0 pixel get no correction (NaN)."""
    view0, view1, start, truth = scene
    tracks = truth.copy()
    tracks[:10] = np.nan
    anchors = start.copy()
    anchors[10:20] = np.nan
    correction = lock_to_template(view0, view1, anchors, tracks, 21)
    assert np.isnan(correction[:20]).all()
    assert np.nanmedian(np.linalg.norm(correction[20:], axis=1)) < 0.1


def test_local_maps_are_the_warps_derivative(scene):
    """LocalFits.jacobians of exact tracks equal the homography's derivative at each point
    (a quadratic fit of 36 neighbours: within 1 %)."""
    _, _, start, truth = scene
    jac = LocalFits.of(start, truth, 36).jacobians()
    h, eps = warp(), 1e-3
    numeric = np.stack([(apply(h, start + eps * e) - apply(h, start - eps * e)) / (2 * eps)
                        for e in np.eye(2)], -1)
    assert np.median(np.abs(jac - numeric).max((1, 2))) < 0.01


def test_a_stereo_pair_shares_its_correction_and_keeps_its_disparity():
    """Cameras 4 mm apart at 60 mm share one correction per point (the mean of their
    views'; a view without one takes its partner's), so the pair's disparity is kept; a
    camera 40 mm away keeps its own."""
    centres = np.array([[0.0, 0, 0], [0.004, 0, 0], [0.04, 0, 0]])
    points = np.random.default_rng(0).normal([0.002, 0, 0.06], 0.005, (50, 3))
    groups = lock_groups(centres, points)
    assert sorted(map(sorted, map(list, groups))) == [[0, 1], [2]]
    drift = np.array([[[0.3, 0.1], [0.1, 0.3], [1.0, 0.0]],
                      [[0.2, 0.2], [np.nan, np.nan], [np.nan, np.nan]]])
    shared = shared_drift(drift, groups)
    np.testing.assert_allclose(shared[0], [[0.2, 0.2], [0.2, 0.2], [1.0, 0.0]])
    np.testing.assert_allclose(shared[1], [[0.2, 0.2], [0.2, 0.2], [0.0, 0.0]])
