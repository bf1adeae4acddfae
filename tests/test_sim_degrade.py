"""Real-image difficulty of the simulator (sim/degrade.py): off changes nothing; the
localisation error moves image content by about the RMS asked for."""

from __future__ import annotations

import cv2
import numpy as np

from surgrecon_cli.sim.degrade import degrade
from surgrecon_cli.sim.variants import variant_config


def _texture(rng: np.random.Generator, h: int = 240, w: int = 320) -> np.ndarray:
    blobs = cv2.GaussianBlur(rng.uniform(0, 255, (h, w)).astype(np.float32), (0, 0), 2.0)
    blobs = cv2.normalize(blobs, None, 0, 255, cv2.NORM_MINMAX)
    return np.repeat(blobs[:, :, None], 3, 2).astype(np.uint8)


def test_all_off_returns_the_image_and_draws_nothing():
    rng = np.random.default_rng(1)
    image = _texture(rng)
    state = rng.bit_generator.state
    assert degrade(image, rng) is image
    assert rng.bit_generator.state == state


def test_warp_moves_content_by_its_rms():
    """Dense flow (Farneback, independent of the warp's construction) between the clean and
    the warped image measures the displacement; its RMS per axis is the warp asked for."""
    rng = np.random.default_rng(2)
    image = _texture(rng)
    warped = degrade(image, rng, warp_px=0.4)
    grey = [cv2.cvtColor(im, cv2.COLOR_RGB2GRAY) for im in (image, warped)]
    flow = cv2.calcOpticalFlowFarneback(grey[0], grey[1], None, 0.5, 2, 9, 5, 5, 1.1, 0)
    inner = flow[24:-24, 24:-24].reshape(-1, 2)
    rms = float(np.sqrt(np.mean(inner**2)))
    assert 0.25 <= rms <= 0.55, rms


def test_real_variants_degrade_and_stay_stereo():
    cfg = variant_config("stereo-real", seed=3)
    assert cfg.cameras == 2 and cfg.warp_px > 0 and cfg.jpeg_quality <= 85
    sweep = variant_config("stereo-sweep", seed=3, frames=12)
    assert 2.0 <= sweep.sweep_deg / (sweep.frames - 1) <= 4.0
