"""Features of a large image are searched downscaled (template.detect_width_px) but
located in the full image: a known shift of the image is recovered in full-size pixels."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest

from surgrecon_cli.config import Config
from surgrecon_cli.core.geometry.cameras import CameraModel
from surgrecon_cli.core.template.features import UPSCALE_BIAS_PX, detect_features

SHIFT = np.array([13.0, 7.0])  # px, the second image's content moved right and down


def _texture(width: int, height: int) -> np.ndarray:
    """Smooth random RGB texture (blurred noise), mid-grey, no saturated pixels."""
    noise = np.random.default_rng(4).normal(0.0, 1.0, (height, width)).astype(np.float32)
    grey = cv2.GaussianBlur(noise, (0, 0), 4.0)
    grey = np.clip(128 + 90 * grey / grey.std(), 20, 235).astype(np.uint8)
    return np.repeat(grey[:, :, None], 3, axis=2)


def test_a_shift_is_recovered_in_full_image_pixels():
    cfg = replace(Config().template, detect_width_px=1280)
    width, height = 2 * cfg.detect_width_px + 100, 600  # searched at 1280 px wide (/2.08)
    base = _texture(width + 40, height + 40)
    first = np.ascontiguousarray(base[20:20 + height, 20:20 + width])
    dx, dy = SHIFT.astype(int)
    second = np.ascontiguousarray(base[20 - dy:20 - dy + height, 20 - dx:20 - dx + width])
    K = np.array([[1000.0, 0, width / 2], [0, 1000.0, height / 2], [0, 0, 1]])
    camera = CameraModel(K, np.zeros(5), width, height)
    a = detect_features(first, camera, cfg)
    b = detect_features(second, camera, cfg)
    assert len(a) > 100 and len(b) > 100
    matches = cv2.BFMatcher(cv2.NORM_L2, crossCheck=True).match(a.descriptors, b.descriptors)
    offsets = np.array([b.pixels[m.trainIdx] - a.pixels[m.queryIdx] for m in matches])
    near = np.linalg.norm(offsets - np.median(offsets, axis=0), axis=1) < 3.0
    assert near.sum() > 50
    np.testing.assert_allclose(np.median(offsets[near], axis=0), SHIFT, atol=0.3)


def _blobs(width: int, height: int, centres: np.ndarray, sigma_px: float) -> np.ndarray:
    """RGB image (mid-grey) of bright Gaussian blobs of `sigma_px` at sub-pixel `centres`
    (N, 2) px, sampled at the pixel centres (integer coordinates)."""
    v, u = np.mgrid[0:height, 0:width].astype(float)
    grey = np.full((height, width), 60.0)
    for cx, cy in centres:
        grey += 150.0 * np.exp(-((u - cx) ** 2 + (v - cy) ** 2) / (2 * sigma_px**2))
    return np.repeat(np.clip(grey, 0, 255).astype(np.uint8)[:, :, None], 3, axis=2)


@pytest.mark.parametrize("width", [800, 1920])
def test_features_are_located_where_the_blobs_are(width):
    """Blobs at known sub-pixel centres, searched at full size (800 px) and downscaled
    (1920 px to 1280): most blobs have a feature within 1 px (> 60 %). OpenCV's default 2x
    upsampling puts them UPSCALE_BIAS_PX right and down (x1.5 downscaled): the downscaled
    search is corrected for it (median offset < 0.05 px per axis, all within 0.15 px), the
    full-size search keeps it (features.detect_features). SIFT's keypoints alone: a few
    blobs would be topped up with corners (template.min_features)."""
    cfg = replace(Config().template, detect_width_px=1280, min_features=0)
    height = 480
    rng = np.random.default_rng(11)
    grid = np.stack(np.meshgrid(np.arange(80, width - 80, 90), np.arange(80, height - 80, 90)),
                    -1).reshape(-1, 2)
    centres = grid + rng.uniform(-0.5, 0.5, grid.shape)
    K = np.array([[1000.0, 0, width / 2], [0, 1000.0, height / 2], [0, 0, 1]])
    features = detect_features(_blobs(width, height, centres, 4.0),
                               CameraModel(K, np.zeros(5), width, height), cfg)
    gap = features.pixels[None, :, :] - centres[:, None, :]
    nearest = gap[np.arange(len(centres)), np.argmin(np.linalg.norm(gap, axis=2), axis=1)]
    found = np.linalg.norm(nearest, axis=1) < 1.0
    assert len(centres) > 20 and found.mean() > 0.6
    kept = UPSCALE_BIAS_PX if width <= cfg.detect_width_px else 0.0
    assert np.abs(np.median(nearest[found], axis=0) - kept).max() < 0.05
    assert np.abs(nearest[found] - kept).max() < 0.15


def test_a_low_texture_image_is_topped_up_with_corners_located_to_a_tenth_of_a_pixel():
    """A small, smooth image where SIFT finds few keypoints: corners bring the features up to
    template.min_features, and a sub-pixel shift of the image (13.4, 7.7) px, applied by
    resampling, is recovered from the corners matched by their descriptors within 0.1 px
    (median per axis)."""
    cfg = Config().template
    width, height = 360, 288
    noise = np.random.default_rng(9).normal(0.0, 1.0, (height + 60, width + 60))
    grey = cv2.GaussianBlur(noise.astype(np.float32), (0, 0), 6.0)
    grey = 128 + 60 * grey / grey.std()
    shift = np.array([13.4, 7.7])
    moved = cv2.warpAffine(grey, np.float32([[1, 0, shift[0]], [0, 1, shift[1]]]),
                           (width + 60, height + 60), flags=cv2.INTER_CUBIC)

    def rgb(image: np.ndarray) -> np.ndarray:
        crop = np.clip(image[30:30 + height, 30:30 + width], 0, 255).astype(np.uint8)
        return np.repeat(crop[:, :, None], 3, axis=2)

    K = np.array([[300.0, 0, width / 2], [0, 300.0, height / 2], [0, 0, 1]])
    camera = CameraModel(K, np.zeros(5), width, height)
    sift_only = detect_features(rgb(grey), camera, replace(cfg, min_features=0))
    a = detect_features(rgb(grey), camera, cfg)
    b = detect_features(rgb(moved), camera, cfg)
    assert 2 * len(sift_only) < len(a) <= cfg.min_features
    corners_a = np.arange(len(a)) >= len(sift_only)  # the corners follow SIFT's keypoints
    matches = cv2.BFMatcher(cv2.NORM_L2, crossCheck=True).match(a.descriptors[corners_a],
                                                                b.descriptors)
    offsets = np.array([b.pixels[m.trainIdx] - a.pixels[corners_a][m.queryIdx]
                        for m in matches])
    near = np.linalg.norm(offsets - shift, axis=1) < 1.0
    assert near.sum() > 200
    np.testing.assert_allclose(np.median(offsets[near], axis=0), shift, atol=0.1)
