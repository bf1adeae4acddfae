"""Colour SIFT features, topped up with corners in small or low-texture images: keypoints,
descriptors, undistorted coordinates and RGB per feature."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

from ...config import TemplateConfig
from ..geometry.cameras import CameraModel, undistort_pixels
from ..target.tracking import specular_mask, specular_zone

# OpenCV's `resize` to twice the size maps a pixel x of the result to x / 2 - 0.25 of its
# input, and SIFT reports x / 2: each keypoint 0.25 px right and down of where it is.
UPSCALE_BIAS_PX = 0.25
# ours (measured on the SurgT clips at 360x288, template.min_features): corners down to a
# thousandth of the strongest one's response (its structure tensor summed over
# CORNER_BLOCK_PX: at 3, goodFeaturesToTrack's default, the sub-pixel peaks lock to the
# pixel grid by up to 0.13 px, at 5 by up to 0.09 px, on shifted blurred noise),
# CORNER_SPACING_PX apart and from SIFT's keypoints, described at SIFT's keypoint size
# CORNER_SIZE_PX
CORNER_QUALITY = 0.001
CORNER_BLOCK_PX = 5
CORNER_SPACING_PX = 3.0
CORNER_SIZE_PX = 12.0


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

    An image where SIFT finds fewer than `cfg.min_features` keypoints (a small or
    low-texture image: 1,400 on the SurgT frames at 360x288, ~200 on d-lfd's 310x244 foam)
    gets Shi-Tomasi corners up to that count (`corner_features`; build_template asks for
    them in a stereo head's cameras only). Measured on the SurgT clips at 360x288
    (breathing, min_features 2,000 against none; docs/method.md): template 406 -> 653
    points, positions against the truth p95 1.37-1.54 -> 1.10-1.37 mm, deforming where
    truly rigid 1.3-4.5 % -> 0.6-2.7 %.
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
    pixels = np.array([k.pt for k in keypoints], dtype=np.float64).reshape(-1, 2)
    # SIFT may return one location twice with different orientations: keep the first.
    _, first = np.unique(np.round(pixels, 2), axis=0, return_index=True)
    first = np.sort(first)
    bias = UPSCALE_BIAS_PX if small is not image else 0.0
    pixels = pixels[first] - bias
    descriptors = (np.zeros((0, 128), np.float32) if descriptors is None
                   else descriptors[first].astype(np.float32))
    if len(pixels) < cfg.min_features:
        corners, corner_descriptors = corner_features(gray, mask, pixels,
                                                      cfg.min_features - len(pixels), sift)
        pixels = np.vstack([pixels, corners])
        descriptors = np.vstack([descriptors, corner_descriptors])
    if not len(pixels):
        return no_features()
    # pixel centres of the downscaled image back to the full image's
    factor = np.array([width / gray.shape[1], height / gray.shape[0]])
    pixels = (pixels + 0.5) * factor - 0.5
    return Features(pixels, undistort_pixels(pixels, camera), descriptors,
                    sample_rgb(image, pixels))


def response_peaks(response: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """Sub-pixel peaks (M, 2) px of a response map (H, W) at its integer local maxima pixels
    (M, 2) (x, y): per axis the vertex of the parabola through the peak and its two
    neighbours (within half a pixel; at the image border, the pixel itself)."""
    h, w = response.shape
    x, y = pixels[:, 0], pixels[:, 1]
    inside = (x > 0) & (x < w - 1) & (y > 0) & (y < h - 1)
    xi, yi = np.clip(x, 1, w - 2), np.clip(y, 1, h - 2)
    centre = response[yi, xi]
    offsets = []
    for before, after in ((response[yi, xi - 1], response[yi, xi + 1]),
                          (response[yi - 1, xi], response[yi + 1, xi])):
        curvature = before - 2.0 * centre + after
        peaked = curvature < 0
        step = np.where(peaked, 0.5 * (before - after) / np.where(peaked, curvature, -1.0), 0.0)
        offsets.append(np.where(inside, np.clip(step, -0.5, 0.5), 0.0))
    return pixels + np.column_stack(offsets)


def corner_features(grey: np.ndarray, mask: np.ndarray, taken: np.ndarray, count: int,
                    sift: cv2.SIFT) -> tuple[np.ndarray, np.ndarray]:
    """Up to `count` Shi-Tomasi corners of grey (H, W) uint8 where mask (H, W) uint8 is set,
    strongest first, at least CORNER_SPACING_PX from each other and from the pixels `taken`
    (K, 2) (the SIFT keypoints), located to sub-pixel at the peak of the corner response
    (`response_peaks` of the log of cv2.cornerMinEigenVal, what goodFeaturesToTrack ranks
    by: the parabola of a Gaussian peak; a corner of smooth tissue texture is no crossing
    of edges, which cv2.cornerSubPix assumes: measured on blurred noise, it stays put or
    wanders 2-7 px), with upright SIFT descriptors of CORNER_SIZE_PX (orientation 0: they
    match between views that are the same way up, as a stereo head's; views rolled far
    apart match by SIFT's own keypoints): pixels (M, 2) px of grey, descriptors (M, 128)
    float32."""
    none = np.zeros((0, 2)), np.zeros((0, 128), np.float32)
    if count <= 0:
        return none
    found = cv2.goodFeaturesToTrack(grey, maxCorners=count + len(taken),
                                    qualityLevel=CORNER_QUALITY, minDistance=CORNER_SPACING_PX,
                                    mask=mask, blockSize=CORNER_BLOCK_PX)
    if found is None:
        return none
    response = np.log(np.maximum(cv2.cornerMinEigenVal(grey, CORNER_BLOCK_PX), 1e-12))
    corners = response_peaks(response, found.reshape(-1, 2).astype(int))
    if len(taken):
        corners = corners[cKDTree(taken).query(corners)[0] > CORNER_SPACING_PX]
    corners = corners[:count]
    wanted = [cv2.KeyPoint(float(x), float(y), CORNER_SIZE_PX, 0.0) for x, y in corners]
    described, descriptors = sift.compute(grey, wanted)
    if not described:
        return none
    return (np.array([k.pt for k in described], dtype=np.float64).reshape(-1, 2),
            descriptors.astype(np.float32))
