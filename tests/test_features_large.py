"""Features of a large image are searched downscaled (template.detect_width_px) but
located in the full image: a known shift of the image is recovered in full-size pixels, and
blobs at known centres are found there."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np

from surgrecon_cli.config import Config
from surgrecon_cli.core.geometry.cameras import CameraModel
from surgrecon_cli.core.template.features import detect_features

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


def _blobs(width: int, height: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    """A grey RGB image of n Gaussian blobs (σ 1.5-3 px) at known sub-pixel centres (n, 2)."""
    rng = np.random.default_rng(7)
    grid = np.stack(np.meshgrid(np.arange(40, width - 40, 40), np.arange(40, height - 40, 40)),
                    -1).reshape(-1, 2)
    centres = grid[rng.choice(len(grid), n, replace=False)] + rng.uniform(-5, 5, (n, 2))
    sigmas = rng.uniform(1.5, 3.0, n)
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float32)
    grey = np.full((height, width), 60.0, np.float32)
    for (x, y), s in zip(centres, sigmas, strict=True):
        window = (slice(int(y) - 15, int(y) + 16), slice(int(x) - 15, int(x) + 16))
        grey[window] += 150 * np.exp(-((xx[window] - x) ** 2 + (yy[window] - y) ** 2)
                                     / (2 * s * s))
    return np.repeat(grey.astype(np.uint8)[:, :, None], 3, axis=2), centres


def _location_errors(cfg, image: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """Per found blob (nearest keypoint within 1.5 px), the keypoint minus the centre (px)."""
    height, width = image.shape[:2]
    K = np.array([[1000.0, 0, width / 2], [0, 1000.0, height / 2], [0, 0, 1]])
    pixels = detect_features(image, CameraModel(K, np.zeros(5), width, height), cfg).pixels
    offsets = pixels[:, None, :] - centres[None]
    nearest = np.argmin((offsets**2).sum(2), axis=0)
    found = offsets[nearest, np.arange(len(centres))]
    return found[np.linalg.norm(found, axis=1) < 1.5]


def test_blob_centres_are_located_at_full_resolution():
    """Blobs at known centres are found where they are (no SIFT offset: it would be 0.25 px
    at full size, 0.5 px searched at half size), searched at full size and searched at
    half size then relocated in the full image."""
    image, centres = _blobs(1920, 1080, 200)
    cfg = Config().template
    for detect_width in (0, 960):
        errors = _location_errors(replace(cfg, detect_width_px=detect_width,
                                          refine_subpixel=True), image, centres)
        assert len(errors) > 90  # σ 1.5 px blobs are below a half-size search's finest scale
        bias = np.abs(np.median(errors, axis=0))
        spread = np.median(np.linalg.norm(errors, axis=1))
        assert (bias < 0.05).all() and spread < 0.05, (detect_width, bias, spread)
