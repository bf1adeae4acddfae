"""A stereo pair's disparity measured in the pair's images of one instant
(core/target/stereo_check.py), on a synthetic texture seen by two eyes through a known
disparity field: the tracked second view's slips along the epipolar line are what the check
returns, and true tracks get (almost) no correction."""

from __future__ import annotations

import cv2
import numpy as np
from test_template_lock import SIZE, texture

from surgrecon_cli.config import TargetConfig
from surgrecon_cli.core.target.stereo_check import disparity_errors, stereo_match
from surgrecon_cli.core.target.tracking import tracking_view

MOTION_PX = np.array([3.3, -2.1])  # the scene's image motion from frame 0 (both eyes)


def disparity(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The true disparity (px) at left pixels (x, y): a surface that bulges and tilts."""
    return 7.0 + 2.0 * np.sin(x / 90.0) + 1.5 * np.cos(y / 70.0)


def right_pixels(left: np.ndarray) -> np.ndarray:
    """Where left pixels (M, 2) are in the right eye: x − d(x, y), same row."""
    return left - np.column_stack([disparity(left[:, 0], left[:, 1]), np.zeros(len(left))])


def eyes(rgb: np.ndarray, shift: np.ndarray):
    """Left and right `TrackingView`s of the texture moved by `shift` (px): the right eye
    sees the left's texture at x + d(x, y)."""
    h, w = SIZE
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    left = cv2.remap(rgb, xs - np.float32(shift[0]), ys - np.float32(shift[1]),
                     cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    # the right eye's pixel (x, y) shows the left eye's (x + d, y), d taken at that point
    lx = xs.copy()
    for _ in range(4):  # fixed point of lx = x + d(lx, y): the left pixel it shows
        lx = xs + disparity(lx - shift[0], ys - shift[1]).astype(np.float32)
    right = cv2.remap(left, lx, ys, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    return tracking_view(left), tracking_view(right)


def test_slips_along_the_epipolar_line_are_measured_and_true_tracks_left():
    rgb = texture(11)
    anchor, now = eyes(rgb, np.zeros(2)), eyes(rgb, MOTION_PX)
    rng = np.random.default_rng(3)
    left0 = rng.uniform([90, 60], [550, 420], (300, 2))
    anchor_pixels = np.stack([left0, right_pixels(left0)], 1)
    pixels = anchor_pixels + MOTION_PX
    slipped = np.arange(len(left0)) % 5 == 0
    slip = np.where(slipped, rng.choice([-1.0, 1.0], len(left0)) * rng.uniform(0.4, 1.0,
                    len(left0)), 0.0)
    pixels[:, 1, 0] += slip
    pixels[-5:] = np.nan  # not found now: no error
    cfg = TargetConfig()
    anchor_match = stereo_match(anchor, anchor_pixels, cfg)
    # at frame 0 the match finds the true right pixels
    assert np.nanmedian(np.linalg.norm(anchor_match - anchor_pixels[:, 1], axis=1)) < 0.05
    errors = disparity_errors(now, pixels, anchor_pixels, anchor_match, cfg)
    assert np.isnan(errors[-5:]).all()
    ok = np.isfinite(errors).all(1)
    assert ok[:-5].mean() > 0.9
    # the error is the slip, undone
    miss = np.linalg.norm(errors + np.column_stack([slip, np.zeros_like(slip)]), axis=1)
    assert np.median(miss[ok & slipped]) < 0.05
    assert np.mean(miss[ok & slipped] < 0.15) > 0.9
    # true tracks: corrections far below the slips
    assert np.median(np.linalg.norm(errors[ok & ~slipped], axis=1)) < 0.05
