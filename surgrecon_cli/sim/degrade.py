"""Real-image difficulty for simulated images: what a clinical endoscope's video adds to a
clean rendering (all off by default; `SimConfig` fields, `sim/variants.py` names presets).

- `warp_px`: a localisation error, the RMS (px, per axis) of a smooth random displacement
  field drawn afresh for every image (cells of `WARP_CELL_PX`). Real images move a feature's
  apparent position by a few tenths of a pixel (compression blocks, demosaicing, rolling
  shutter, lens and focus breathing) while their intensity noise alone bounds it near
  0.01 px: this is the gap between the Cramér-Rao bound and the true error.
- `blur_px`: Gaussian blur σ (px), a defocused or moving endoscope.
- `vignetting`: the share of brightness lost at the image corners (cos⁴-like falloff).
- `interlace_px`: odd rows shifted horizontally by this many px (the second field of an
  interlaced camera, captured while the view moved).
Compression (`jpeg_quality`, or H.264 with `--video`) and specular highlights that move
with the light (at the camera) are the renderer's and the log writer's.
"""

from __future__ import annotations

import cv2
import numpy as np

# Correlation length of the localisation error field (px): on the real SurgT clip the
# across-epipolar residuals of template matches correlate 0.11 within 10 px and <= 0.03
# beyond; 8 px cells (a compression block) give 0.1-0.2 within 10 px.
WARP_CELL_PX = 8


def degrade(image: np.ndarray, rng: np.random.Generator, warp_px: float = 0.0,
            blur_px: float = 0.0, vignetting: float = 0.0,
            interlace_px: float = 0.0) -> np.ndarray:
    """The RGB uint8 image (H, W, 3) with the given difficulties applied (unchanged, and no
    random draw, when all are 0)."""
    if not (warp_px > 0 or blur_px > 0 or vignetting > 0 or interlace_px != 0):
        return image
    out: np.ndarray = image.astype(np.float32)
    h, w = out.shape[:2]
    if warp_px > 0:
        coarse = rng.normal(0.0, warp_px, (2, h // WARP_CELL_PX + 2, w // WARP_CELL_PX + 2))
        # Cubic upsampling smooths the draws: rescale so that the field's RMS is warp_px.
        field = [cv2.resize(c.astype(np.float32), (w, h), interpolation=cv2.INTER_CUBIC)
                 for c in coarse]
        field = [f * (warp_px / max(float(np.sqrt(np.mean(f**2))), 1e-9)) for f in field]
        u, v = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
        out = cv2.remap(out, u + field[0], v + field[1], cv2.INTER_CUBIC,
                        borderMode=cv2.BORDER_REFLECT)
    if blur_px > 0:
        out = cv2.GaussianBlur(out, (0, 0), blur_px)
    if interlace_px != 0:
        shift = np.array([[1, 0, interlace_px], [0, 1, 0]], np.float32)
        moved = cv2.warpAffine(out, shift, (w, h), flags=cv2.INTER_LINEAR,
                               borderMode=cv2.BORDER_REFLECT)
        out[1::2] = moved[1::2]
    if vignetting > 0:
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
        r2 = ((xx - (w - 1) / 2) ** 2 + (yy - (h - 1) / 2) ** 2) / ((w / 2) ** 2 + (h / 2) ** 2)
        out *= (1.0 - vignetting * r2**2)[:, :, None]
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)
