"""Colour SIFT features: keypoints, descriptors, undistorted coordinates and RGB per feature."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ...config import TemplateConfig
from ..geometry.cameras import CameraModel, undistort_pixels
from ..target.tracking import specular_mask, specular_zone


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


SIFT_OFFSET_PX = 0.25  # OpenCV's SIFT location minus the extremum's (px, both axes)
REFINE_LEVELS_PER_OCTAVE = 3  # SIFT's scale sampling (its default octave layers)
REFINE_BASE_SIGMA = 1.6  # SIFT's base scale (px)
REFINE_REACH_SCALES = 2.0  # ours: keypoints up to this many times `reach` px (σ) are relocated


def refine_extrema(gray: np.ndarray, pixels: np.ndarray, sigma: np.ndarray,
                   reach: float) -> np.ndarray:
    """Keypoints found on a downscaled image, located again at full resolution: pixels
    (N, 2) px and scales sigma (N,) px in the grey image (H, W) uint8; returns (N, 2) px.

    Each keypoint takes the difference of Gaussians at the nearest of SIFT's sampled
    scales (σ_l = 1.6 · 2^(l/3), D = G(σ_(l+1)) - G(σ_l), on the full image) and one
    Newton step of its quadratic model from the nearest pixel (SIFT's own sub-pixel fit,
    2-D), repeated once if the step leaves the pixel. Points coarser than the largest
    scale sampled (2 · `reach` px, where the downscaling no longer limits precision),
    points whose model is not an extremum, and steps farther than `reach` px (one pixel of
    the downscaled image) from the detected location keep the detected location."""
    out = pixels.copy()
    if len(pixels) == 0:
        return out
    height, width = gray.shape
    n_levels = max(1, int(np.ceil(REFINE_LEVELS_PER_OCTAVE
                                  * np.log2(REFINE_REACH_SCALES * reach / REFINE_BASE_SIGMA))) + 1)
    level = np.round(REFINE_LEVELS_PER_OCTAVE
                     * np.log2(np.maximum(sigma, 1e-6) / REFINE_BASE_SIGMA)).astype(int)
    level = np.maximum(level, 0)
    image = gray.astype(np.float32)
    blurred = None
    for lv in range(n_levels):
        rows = np.flatnonzero(level == lv)
        s0 = REFINE_BASE_SIGMA * 2.0 ** (lv / REFINE_LEVELS_PER_OCTAVE)
        s1 = s0 * 2.0 ** (1.0 / REFINE_LEVELS_PER_OCTAVE)
        if len(rows) == 0:
            blurred = None
            continue
        # the image's own blur: 0.5 px (SIFT's assumption)
        g0 = blurred if blurred is not None else cv2.GaussianBlur(
            image, (0, 0), np.sqrt(s0**2 - 0.25))
        g1 = cv2.GaussianBlur(image, (0, 0), np.sqrt(s1**2 - 0.25))
        blurred = g1
        dog = g1 - g0
        start = pixels[rows]
        at = np.clip(np.round(start), 1, [width - 2, height - 2]).astype(int)
        offset = np.zeros((len(rows), 2))
        ok = np.zeros(len(rows), bool)
        for _ in range(2):
            x, y = at[:, 0], at[:, 1]
            c = dog[y, x]
            dx = 0.5 * (dog[y, x + 1] - dog[y, x - 1])
            dy = 0.5 * (dog[y + 1, x] - dog[y - 1, x])
            dxx = dog[y, x + 1] + dog[y, x - 1] - 2 * c
            dyy = dog[y + 1, x] + dog[y - 1, x] - 2 * c
            dxy = 0.25 * (dog[y + 1, x + 1] - dog[y + 1, x - 1]
                          - dog[y - 1, x + 1] + dog[y - 1, x - 1])
            det = dxx * dyy - dxy * dxy
            with np.errstate(divide="ignore", invalid="ignore"):
                ox = -(dyy * dx - dxy * dy) / det
                oy = -(dxx * dy - dxy * dx) / det
            offset = np.column_stack([ox, oy])
            ok = (det > 0) & np.isfinite(offset).all(1)
            move = ok & (np.abs(offset) > 0.5).any(1)
            if not move.any():
                break
            stepped = np.clip(at + np.round(np.nan_to_num(offset)).astype(int), 1,
                              [width - 2, height - 2])
            at = np.where(move[:, None], stepped, at)
        found = at + offset
        ok &= (np.abs(offset) <= 0.6).all(1) & (np.linalg.norm(found - start, axis=1) <= reach)
        out[rows[ok]] = found[ok]
    return out


def detect_features(image: np.ndarray, camera: CameraModel, cfg: TemplateConfig,
                    exclude: np.ndarray | None = None) -> Features:
    """SIFT on an RGB image (H, W, 3) uint8; `exclude` (H, W) bool masks pixels out (tool),
    and so do saturated specular highlights (core/tracking.specular_zone): they move with
    the light, so a feature there triangulates to no point of the tissue and is not tracked.

    The contrast threshold is a fifth of OpenCV's default: endoscopic tissue is low-contrast
    and we want thousands of features per image (our choice, not the paper's). Images wider
    than `cfg.detect_width_px` are searched downscaled to exactly that width, by a factor
    s = width / detect_width_px (area average, aspect kept; SIFT's finest octave, the image
    upsampled 2x, then has 4/s² of the full image's pixels instead of 4x); the pixels are
    given in the full image, and with `cfg.refine_subpixel` the keypoints fine enough for
    the downscaling to limit their precision are located again in the full image
    (`refine_extrema`). `cfg.max_features`, `cfg.contrast_threshold`: SIFT's.
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
    sift = cv2.SIFT.create(nfeatures=cfg.max_features, contrastThreshold=cfg.contrast_threshold)
    keypoints, descriptors = sift.detectAndCompute(gray, mask)
    if not keypoints:
        return no_features()
    # OpenCV's SIFT doubles the image without the half-pixel shift, so its locations are
    # 0.25 px (of the searched image) right of and below the extrema: measured +0.25 px on
    # blobs at known positions
    pixels = np.array([k.pt for k in keypoints], dtype=np.float64) - SIFT_OFFSET_PX
    sigmas = np.array([k.size for k in keypoints], dtype=np.float64) / 2.0
    # SIFT may return one location twice with different orientations: keep the first.
    _, first = np.unique(np.round(pixels, 2), axis=0, return_index=True)
    first = np.sort(first)
    # pixel centres of the downscaled image back to the full image's
    factor = np.array([width / gray.shape[1], height / gray.shape[0]])
    pixels = (pixels[first] + 0.5) * factor - 0.5
    if small is not image and cfg.refine_subpixel:
        full = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
        pixels = refine_extrema(full, pixels, sigmas[first] * factor.mean(), factor.mean())
    return Features(
        pixels,
        undistort_pixels(pixels, camera),
        descriptors[first].astype(np.float32),
        sample_rgb(image, pixels),
    )
