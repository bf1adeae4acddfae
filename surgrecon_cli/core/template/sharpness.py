"""Is the template's frame blurred? Its sharpness against the frames after it.

The template is built from frame 0 alone; a recording that starts on a blurred image
(the endoscope moving or fogged as it is switched on) gives a sparse, imprecise template
and everything after it inherits that. Sharpness here is the variance of the Laplacian
of the grey image resized to SHARPNESS_WIDTH_PX (so that it does not depend on the image
size) over its intensity variance (so that it does not depend on exposure), a standard
focus measure. Pure numpy/OpenCV on arrays.
"""

from __future__ import annotations

import cv2
import numpy as np

SHARPNESS_WIDTH_PX = 320  # ours: the width the measure is taken at
BLUR_RATIO = 0.5  # ours: frame 0 below this share of the later frames' median is blurred


def sharpness(image: np.ndarray) -> float:
    """Focus measure of an image (H, W, 3) or (H, W) uint8: Laplacian variance over
    intensity variance of its grey image at SHARPNESS_WIDTH_PX wide (NaN for a flat image)."""
    grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image
    scale = SHARPNESS_WIDTH_PX / grey.shape[1]
    small = cv2.resize(grey, (SHARPNESS_WIDTH_PX, max(1, round(grey.shape[0] * scale))),
                       interpolation=cv2.INTER_AREA).astype(np.float32)
    spread = float(small.var())
    if spread <= 0:
        return float("nan")
    return float(cv2.Laplacian(small, cv2.CV_32F).var() / spread)


def decode_reduction(width_px: int) -> int:
    """The largest of 1, 2, 4, 8 that keeps an image of width_px at least SHARPNESS_WIDTH_PX
    wide: it can be decoded that much smaller (a JPEG's cheaper decode) for `sharpness`."""
    return int(min(8, 2 ** np.floor(np.log2(max(width_px / SHARPNESS_WIDTH_PX, 1.0)))))


def typical_sharpness(later: np.ndarray) -> np.ndarray:
    """Each camera's median sharpness (C,) over later frames' later (K, C) (NaN: no image);
    NaN for a camera with fewer than 2 later images (not judged)."""
    have = np.isfinite(later).sum(0) >= 2
    with np.errstate(invalid="ignore"):
        return np.where(have, np.nanmedian(np.where(have, later, 0.0), axis=0), np.nan)


def blurred_cameras(first: np.ndarray, later: np.ndarray) -> np.ndarray:
    """Cameras (indices) whose frame-0 sharpness first (C,) is below BLUR_RATIO of their
    `typical_sharpness` over the later frames' later (K, C)."""
    typical = typical_sharpness(later)
    with np.errstate(invalid="ignore"):
        return np.flatnonzero(np.isfinite(typical) & np.isfinite(first)
                              & (first < BLUR_RATIO * typical))


def first_sharp(later: np.ndarray, cameras: np.ndarray) -> int | None:
    """The first of the later frames' later (K, C) at which every one of `cameras` is
    sharp again (not below BLUR_RATIO of its `typical_sharpness`), or None."""
    typical = typical_sharpness(later)[cameras]
    with np.errstate(invalid="ignore"):
        sharp = (later[:, cameras] >= BLUR_RATIO * typical).all(1)
    return int(np.argmax(sharp)) if sharp.any() else None
