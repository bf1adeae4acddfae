"""The tracking-noise estimator (core/noise/frame_noise.local_motion_noise_px) on synthetic
tracks whose localisation noise is injected, so the expected σ is known exactly; and the
registration artefact that carries its shared part."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from surgrecon_cli.core.noise.frame_noise import PixelNeighbours, local_motion_noise_px
from surgrecon_cli.core.noise.model import robust_sigma
from surgrecon_cli.io.run.artefacts import (
    FrameRegistration,
    read_registration,
    write_registration,
)
from surgrecon_cli.io.run.layout import RunLayout


def smooth_motion(xy: np.ndarray, amplitude_px: float) -> np.ndarray:
    """A smooth non-rigid image motion (M, 2) px at pixels (M, 2): a translation, a small
    rotation and a wave of one image width (tissue bulging)."""
    x, y = xy[:, 0], xy[:, 1]
    wave = amplitude_px * np.sin(2 * np.pi * x / 640.0) * np.cos(2 * np.pi * y / 480.0)
    rot = 0.01 * np.column_stack([-(y - 240.0), x - 320.0])
    return np.column_stack([6.0 + wave, -4.0 + 0.5 * wave]) + rot


def synthetic_tracks(sigma_px: float, amplitude_px: float, frames: int = 3,
                     seed: int = 0, lost: float = 0.0):
    """Template pixels (N, 2, 2) for two cameras and tracked pixels (F, N, 2, 2): the smooth
    motion plus Gaussian noise sigma_px per axis; `lost` a share of tracks thrown 5-30 px."""
    rng = np.random.default_rng(seed)
    n = 700
    ref = np.stack([rng.uniform([0, 0], [640, 480], (n, 2)) for _ in range(2)], axis=1)
    cur = np.empty((frames, n, 2, 2))
    for f in range(frames):
        for c in range(2):
            cur[f, :, c] = (ref[:, c] + smooth_motion(ref[:, c], amplitude_px * (f + 1))
                            + rng.normal(0.0, sigma_px, (n, 2)))
            bad = rng.random(n) < lost
            throw = rng.uniform(5, 30, (int(bad.sum()), 2))
            cur[f, bad, c] += throw * rng.choice([-1, 1], throw.shape)
    return ref, cur, np.ones((frames, n, 2), bool)


@pytest.mark.parametrize("sigma", [0.1, 0.2, 0.5])
def test_recovers_injected_sigma(sigma: float):
    ref, cur, found = synthetic_tracks(sigma, amplitude_px=0.5)
    assert local_motion_noise_px(ref, cur, found)[0] == pytest.approx(sigma, rel=0.15)


def global_affine_sigma(ref: np.ndarray, cur: np.ndarray) -> float:
    """What one affine motion fitted to all of a camera's tracks leaves (px): how far the
    synthetic motion is from rigid-like."""
    X = np.column_stack([ref, np.ones(len(ref))])
    d = cur - ref
    coef, *_ = np.linalg.lstsq(X, d, rcond=None)
    return robust_sigma(d - X @ coef)


def test_not_fooled_by_smooth_non_rigid_motion():
    """A smooth deformation (a wave of up to 3 px on top of a rotation and translation) that
    a global affine fit leaves > 1 px of: without noise the local fits see < 0.1 px of it,
    and with noise the injected σ is still found."""
    ref, cur, found = synthetic_tracks(0.0, amplitude_px=1.0)
    assert global_affine_sigma(ref[:, 0], cur[-1, :, 0]) > 1.0
    assert local_motion_noise_px(ref, cur, found)[0] < 0.1
    ref, cur, found = synthetic_tracks(0.3, amplitude_px=1.0, seed=2)
    assert local_motion_noise_px(ref, cur, found)[0] == pytest.approx(0.3, rel=0.15)


def test_robust_to_lost_tracks_and_missing_points():
    ref, cur, found = synthetic_tracks(0.2, amplitude_px=0.5, lost=0.05, seed=1)
    found[:, ::7, 1] = False
    cur[:, ::11, 0] = np.nan
    assert local_motion_noise_px(ref, cur, found)[0] == pytest.approx(0.2, rel=0.15)


def test_neighbours_among_found_tracks_are_the_k_d_tree_s():
    """PixelNeighbours.among gives each found track's nearest found tracks as a k-d tree of
    the found tracks alone does (order included), with duplicate pixels, tracks without a
    reference pixel and sparse subsets (queried then); the noise is the same with them."""
    rng = np.random.default_rng(3)
    pixels = rng.uniform(0, 640, (900, 2))
    pixels[5] = pixels[6]  # a tie: left to the tree
    pixels[::50] = np.nan
    held = PixelNeighbours.of(pixels)
    for share in (0.2, 0.8, 1.0):
        rows = np.flatnonzero((rng.uniform(size=900) < share) & np.isfinite(pixels).all(1))
        for k in (12, 36):
            expected = cKDTree(pixels[rows]).query(pixels[rows], k=k + 1)[1]
            np.testing.assert_array_equal(held.among(rows, pixels, k), expected)
    ref, cur, found = synthetic_tracks(0.2, amplitude_px=0.5, lost=0.05, seed=1)
    found[:, ::7, 1] = False
    candidates = [PixelNeighbours.of(ref[:, c]) for c in range(2)]
    assert (local_motion_noise_px(ref, cur, found, candidates=candidates)
            == local_motion_noise_px(ref, cur, found))


def test_shared_part_of_the_error_is_separated():
    """An error common to a point's two views (the same shift in each) is the shared part;
    each view's own error is not: both injected, both recovered."""
    rng = np.random.default_rng(4)
    ref, cur, found = synthetic_tracks(0.1, amplitude_px=0.5, seed=5)
    sigma, shared = local_motion_noise_px(ref, cur, found)
    assert shared < 0.3 * sigma
    common = rng.normal(0.0, 0.3, (cur.shape[0], cur.shape[1], 1, 2))
    sigma, shared = local_motion_noise_px(ref, cur + common, found)
    assert sigma == pytest.approx(np.hypot(0.1, 0.3), rel=0.15)
    assert shared == pytest.approx(0.3, rel=0.15)


def test_registration_written_without_the_shared_part_reads_as_zero(tmp_path):
    """Run folders registered before tracking_shared_px existed still read."""
    n = 5
    f32 = np.float32
    reg = FrameRegistration(
        transforms=np.tile(np.eye(3, 4, dtype=f32), (n, 1, 1)),
        registered=np.zeros((n, 3), f32), target=np.zeros((n, 3), f32),
        status=np.zeros(n, np.uint8), views=np.full(n, 2, np.uint8),
        residual=np.zeros(n, f32), sigma=np.zeros(n, f32), target_sigma=np.zeros(n, f32),
        target_covariance=np.zeros((n, 3, 3), f32),
        target_pose_covariance=np.zeros((n, 3, 3), f32), support_mm=np.ones(n, f32),
        pixels=np.zeros((n, 2, 2), f32), tracking_px=0.2, base=0, converged=True,
        failed=False, error="", seconds_target=0.1, seconds_register=0.1, new_points=0,
        contact_points=0, tracking_shared_px=0.15)
    layout = RunLayout(tmp_path)
    layout.registration(1).parent.mkdir(parents=True, exist_ok=True)
    write_registration(layout, 1, reg)
    assert read_registration(layout, 1, n).tracking_shared_px == pytest.approx(0.15)
    with np.load(layout.registration(1)) as z:
        old = {k: z[k] for k in z.files if k != "tracking_shared_px"}
    np.savez(layout.registration(1), **old)
    back = read_registration(layout, 1, n)
    assert back.tracking_shared_px == 0.0 and back.tracking_px == pytest.approx(0.2)
