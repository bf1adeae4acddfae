"""Pyramidal KLT tracking of template points between two images of one camera, checked
forward-backward and photometrically (Su et al. 2019, section II.B: the target cloud's
2D tracks). Pure OpenCV/numpy on arrays."""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from ..config import TargetConfig

NCC_PATCH_PX = 9  # ours: side of the patch compared after tracking (px)
SHADING_SIGMA_PX = 6.0  # ours: shading scale removed before tracking (px), ~ half a KLT window


def tracking_image(image: np.ndarray) -> np.ndarray:
    """The image KLT tracks: grey with the slowly varying shading removed (grey minus its
    Gaussian blur, re-centred on 128). Tissue that tilts under the tool changes its shading
    over a KLT window; brightness constancy then fails the same way in every view, and the
    tracks slide consistently (measured: dent targets 0.3-0.5 mm off with a 0.1 mm sigma)."""
    grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY).astype(np.float32)
    shading = cv2.GaussianBlur(grey, (0, 0), SHADING_SIGMA_PX)
    return np.clip(2.0 * (grey - shading) + 128.0, 0, 255).astype(np.uint8)


def klt_track(
    prev_gray: np.ndarray,
    cur_gray: np.ndarray,
    start: np.ndarray,
    guess: np.ndarray,
    cfg: TargetConfig,
) -> tuple[np.ndarray, np.ndarray]:
    """Track pixels (M, 2) from prev to cur starting from `guess`; forward-backward and
    photometrically checked (`patch_ncc` at least `cfg.min_ncc`). Returns tracked pixels
    (M, 2) and ok (M,)."""
    if len(start) == 0:
        return np.zeros((0, 2)), np.zeros(0, bool)
    params: dict[str, Any] = dict(
        winSize=(cfg.klt_window_px, cfg.klt_window_px),
        maxLevel=cfg.klt_levels,
        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01),
    )
    p0 = start.astype(np.float32).reshape(-1, 1, 2)
    p1: np.ndarray = guess.astype(np.float32).reshape(-1, 1, 2).copy()
    p1, st1, _ = cv2.calcOpticalFlowPyrLK(
        prev_gray, cur_gray, p0, p1, flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **params
    )
    back: np.ndarray = p0.copy()
    back, st2, _ = cv2.calcOpticalFlowPyrLK(
        cur_gray, prev_gray, p1, back, flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **params
    )
    fb = np.linalg.norm((back - p0).reshape(-1, 2), axis=1)
    tracked = p1.reshape(-1, 2).astype(np.float64)
    ok = (st1.ravel() == 1) & (st2.ravel() == 1) & (fb <= cfg.klt_fb_px)
    ok[ok] &= patch_ncc(prev_gray, start[ok], cur_gray, tracked[ok], NCC_PATCH_PX) >= cfg.min_ncc
    return tracked, ok


def patch_ncc(image_a: np.ndarray, pixels_a: np.ndarray, image_b: np.ndarray,
              pixels_b: np.ndarray, size: int) -> np.ndarray:
    """Normalised cross-correlation (M,) of the size x size patches around pixels_a (M, 2)
    in image_a and pixels_b (M, 2) in image_b (bilinear, sub-pixel); -1 where a patch is
    flat. A drifted track that KLT still reports lands on a patch that no longer looks like
    the one it left."""
    if len(pixels_a) == 0:
        return np.zeros(0)
    offsets = np.arange(size, dtype=np.float32) - (size - 1) / 2.0

    def patches(image: np.ndarray, pixels: np.ndarray) -> np.ndarray:
        px = pixels.astype(np.float32)
        map_x = (px[:, 0, None, None] + offsets[None, None, :]).repeat(size, 1)
        map_y = (px[:, 1, None, None] + offsets[None, :, None]).repeat(size, 2)
        flat_x = map_x.reshape(-1, size)
        flat_y = map_y.reshape(-1, size)
        out = cv2.remap(image.astype(np.float32), flat_x, flat_y, cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_REPLICATE)
        p = out.reshape(len(pixels), size * size).astype(np.float64)
        return p - p.mean(1, keepdims=True)

    a, b = patches(image_a, pixels_a), patches(image_b, pixels_b)
    denom = np.sqrt((a * a).sum(1) * (b * b).sum(1))
    return np.where(denom > 1e-9, (a * b).sum(1) / np.maximum(denom, 1e-9), -1.0)
