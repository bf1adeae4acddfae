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


def blurred_cameras(first: np.ndarray, later: np.ndarray) -> np.ndarray:
    """Cameras (indices) whose frame-0 sharpness first (C,) is below BLUR_RATIO of the
    median of the later frames' later (K, C) (NaN: no image; a camera with fewer than 2
    later images is not judged)."""
    have = np.isfinite(later).sum(0) >= 2
    with np.errstate(invalid="ignore"):
        typical = np.where(have, np.nanmedian(np.where(have, later, 0.0), axis=0), np.nan)
        return np.flatnonzero(have & np.isfinite(first) & (first < BLUR_RATIO * typical))
