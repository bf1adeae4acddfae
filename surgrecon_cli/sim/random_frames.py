"""Random per-frame classify outputs, for measuring what the streaming stages (label
writing, the report) cost and hold at any number of frames, without registering them."""

from __future__ import annotations

import numpy as np

from ..core.classify.labels import SHIFTING, STATIC, UNKNOWN
from ..io.run.atomic import write_npz
from ..io.run.layout import RunLayout


def write_random_classified(layout: RunLayout, n_frames: int, n_points: int,
                            rng: np.random.Generator) -> None:
    """Frames 1..n_frames-1 of `layout` as classify writes them (random labels among static,
    shifting and unknown; random displacement, deformation and deformation floor, mm)."""
    for k in range(1, n_frames):
        write_npz(layout.classified(k),
                  raw_labels=rng.choice([STATIC, SHIFTING, UNKNOWN], n_points).astype(np.uint8),
                  displacement_mm=rng.random(n_points, np.float32),
                  deformation_mm=rng.random(n_points, np.float32),
                  floor_mm=rng.random(n_points, np.float32),
                  status=np.zeros(n_points, np.uint8))
