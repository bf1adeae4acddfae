"""Colour SIFT features: keypoints, descriptors, undistorted coordinates and RGB per feature."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ...config import TemplateConfig
from ..geometry.cameras import CameraModel, undistort_pixels
from ..target.tracking import specular_mask, specular_zone

# OpenCV's `resize` to twice the size maps a pixel x of the result to x / 2 - 0.25 of its
# input, and SIFT reports x / 2: each keypoint 0.25 px right and down of where it is.
UPSCALE_BIAS_PX = 0.25


@dataclass(frozen=True)
class Features:
    """Features of one image: pixels (N, 2) distorted px, normalised (N, 2) undistorted,
    descriptors (N, 128) float32, rgb (N, 3) uint8."""

    pixels: np.ndarray
    normalized: np.ndarray
    descriptors: np.ndarray
    rgb: np.ndarray

    def __len__(self) -> int:
        return len(self.pixels)

    def subset(self, keep: np.ndarray) -> Features:
        return Features(
            self.pixels[keep], self.normalized[keep], self.descriptors[keep], self.rgb[keep]
        )


def no_features() -> Features:
    """The features of an image without any (or of an unusable camera)."""
    return Features(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros((0, 128), np.float32),
                    np.zeros((0, 3), np.uint8))


def sample_rgb(image: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """Bilinear RGB (N, 3) uint8 of an image (H, W, 3) at pixels (N, 2)."""
    if len(pixels) == 0:
        return np.zeros((0, 3), np.uint8)
    maps = pixels.astype(np.float32).reshape(-1, 1, 2)
    out = cv2.remap(
        image, maps[..., 0], maps[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
    )
    return out.reshape(-1, 3)


def detect_features(image: np.ndarray, camera: CameraModel, cfg: TemplateConfig,
                    exclude: np.ndarray | None = None) -> Features:
    """SIFT on an RGB image (H, W, 3) uint8; `exclude` (H, W) bool masks pixels out (tool),
    and so do saturated specular highlights (core/tracking.specular_zone): they move with
    the light, so a feature there triangulates to no point of the tissue and is not tracked.

    The contrast threshold is half OpenCV's default: endoscopic tissue is low-contrast and we
    want hundreds to thousands of features per image (our choice, not the paper's). Images
    wider than `cfg.detect_width_px` are searched downscaled to exactly that width, by a
    factor s = width / detect_width_px (area average, aspect kept); the pixels are given in
    the full image. `cfg.max_features`, `cfg.contrast_threshold`: SIFT's.

    OpenCV's SIFT detects on the image upsampled 2x (its first octave, -1): a search at
    width W builds the pyramid of a 2W-wide image, about 3/4 of its cost, and that octave
    holds a quarter to a half of the kept features. Its upsampling by `resize` (the
    default; `enable_precise_upscale` upsamples otherwise and finds other features) reports
    every keypoint UPSCALE_BIAS_PX right and down of where it is in the image searched
    (measured on blobs at known sub-pixel centres, `tests/test_features_large.py`). The
    keypoints of a downscaled search are moved back by it (there it grows by s, and unbiased
    they are as accurate as a full-size search: docs/frame-step-cost.md). A full-size search
    keeps it: removed there, the simulator's indentation and contact-area errors moved by
    -0.09 to +0.15 mm and -6 to +7 points per seed (201-206, mean 0.348 -> 0.371 mm) for a
    reason not found, and the measurement tests' fixtures crossed their goals.
    """
    height, width = image.shape[:2]
    small = image
    if 0 < cfg.detect_width_px < width:
        size = (cfg.detect_width_px, max(1, round(height * cfg.detect_width_px / width)))
        small = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
        if exclude is not None:  # a pixel touching an excluded one is excluded
            exclude = cv2.resize(exclude.astype(np.uint8), size, interpolation=cv2.INTER_AREA) > 0
    gray = cv2.cvtColor(small, cv2.COLOR_RGB2GRAY)
    highlight = specular_zone(specular_mask(small))
    exclude = highlight if exclude is None else exclude | highlight
    mask = (~exclude).astype(np.uint8) * 255
    sift = cv2.SIFT.create(nfeatures=cfg.max_features, contrastThreshold=cfg.contrast_threshold,
                           enable_precise_upscale=False)
    keypoints, descriptors = sift.detectAndCompute(gray, mask)
    if not keypoints:
        return no_features()
    pixels = np.array([k.pt for k in keypoints], dtype=np.float64)
    # SIFT may return one location twice with different orientations: keep the first.
    _, first = np.unique(np.round(pixels, 2), axis=0, return_index=True)
    first = np.sort(first)
    # pixel centres of the downscaled image back to the full image's
    factor = np.array([width / gray.shape[1], height / gray.shape[0]])
    bias = UPSCALE_BIAS_PX if small is not image else 0.0
    pixels = (pixels[first] - bias + 0.5) * factor - 0.5
    return Features(
        pixels,
        undistort_pixels(pixels, camera),
        descriptors[first].astype(np.float32),
        sample_rgb(image, pixels),
    )
