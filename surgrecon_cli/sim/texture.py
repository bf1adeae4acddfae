"""Procedural tissue texture: pink mucosa with colour variation, branching vessels, fat blobs.

The texture is an RGB image over material coordinates (the frame-0 x, y of a surface
point, metres), so a material point keeps its colour as the tissue moves.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class Texture:
    """RGB float32 image (S, S, 3) in [0, 1] covering [-half_extent, half_extent]² metres."""

    image: np.ndarray
    half_extent: float

    def sample(self, material_xy: np.ndarray) -> np.ndarray:
        """Bilinear colour (N, 3) in [0, 1] at material coordinates (N, 2) in metres."""
        size = self.image.shape[0]
        scale = (size - 1) / (2 * self.half_extent)
        n = len(material_xy)
        if n == 0:  # a camera that sees no tissue
            return np.zeros((0, 3), self.image.dtype)
        rows = -(-n // 1024)  # remap wants 2D maps under 32767 on a side: pad to rows x 1024
        maps: np.ndarray = np.zeros((rows * 1024, 2), np.float32)
        maps[:n] = (material_xy + self.half_extent) * scale
        maps = maps.reshape(rows, 1024, 2)
        out = cv2.remap(
            self.image,
            maps[..., 0],
            maps[..., 1],
            interpolation=cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REFLECT,
        )
        return out.reshape(-1, 3)[:n]


def _value_noise(rng: np.random.Generator, size: int, cells: int) -> np.ndarray:
    """Smooth noise in [0, 1]: a random (cells x cells) grid upsampled bicubically."""
    grid = rng.random((cells + 1, cells + 1)).astype(np.float32)
    return cv2.resize(grid, (size, size), interpolation=cv2.INTER_CUBIC).clip(0, 1)


def _vessel_polyline(rng: np.random.Generator, size: int, length: int) -> np.ndarray:
    """A random smooth curve (random walk of the heading) as int pixel coordinates (L, 2)."""
    start = rng.uniform(0, size, 2)
    heading = rng.uniform(0, 2 * np.pi)
    turns = np.cumsum(rng.normal(0, 0.08, length)) + heading
    step = size / 400.0
    pts = start + np.cumsum(np.stack([np.cos(turns), np.sin(turns)], 1) * step, axis=0)
    return np.round(pts).astype(np.int32)


def make_texture(seed: int, half_extent: float = 0.055, size: int = 2048) -> Texture:
    """Deterministic tissue texture for a seed (about 0.05 mm per texel by default)."""
    rng = np.random.default_rng(seed)
    base = np.array([0.80, 0.38, 0.34], np.float32)
    low = _value_noise(rng, size, 8)
    mid = _value_noise(rng, size, 40)
    fine = _value_noise(rng, size, 300)
    shade = (
        0.75
        + 0.25 * low[..., None]
        + 0.12 * (mid[..., None] - 0.5)
        + 0.10 * (fine[..., None] - 0.5)
    )
    tint = np.stack([np.zeros_like(low), 0.08 * (mid - 0.5), 0.06 * (low - 0.5)], -1)
    image = (base * shade + tint).astype(np.float32)

    # Vessels: dark red branching curves of varying width, mostly thin.
    vessels: np.ndarray = np.zeros((size, size), np.float32)
    for _ in range(90):
        pts = _vessel_polyline(rng, size, int(rng.integers(80, 400)))
        width = int(rng.choice([1, 2, 2, 3, 4, 6]))
        cv2.polylines(
            vessels,
            [pts.reshape(-1, 1, 2)],
            False,
            float(rng.uniform(0.5, 1.0)),
            width,
            lineType=cv2.LINE_AA,
        )
        for branch_at in rng.integers(0, len(pts), 2):
            twig = _vessel_polyline(rng, size, int(rng.integers(30, 120))) - pts[0] + pts[branch_at]
            cv2.polylines(
                vessels,
                [twig.reshape(-1, 1, 2)],
                False,
                float(rng.uniform(0.4, 0.9)),
                max(1, width - 1),
                lineType=cv2.LINE_AA,
            )
    vessels = cv2.GaussianBlur(vessels, (0, 0), 1.0)[..., None]
    vessel_rgb = np.array([0.45, 0.06, 0.10], np.float32)
    image = image * (1 - vessels) + vessel_rgb * vessels

    # Blobs: yellowish fat and darker spots, elliptical, blurred.
    blobs = np.zeros((size, size), np.float32)
    spots = np.zeros((size, size), np.float32)
    for target in [blobs] * 250 + [spots] * 350:
        centre = tuple(int(c) for c in rng.integers(0, size, 2))
        axes = tuple(int(a) for a in rng.integers(4, 28, 2))
        cv2.ellipse(
            target,
            centre,
            axes,
            float(rng.uniform(0, 180)),
            0,
            360,
            float(rng.uniform(0.4, 1.0)),
            -1,
            lineType=cv2.LINE_AA,
        )
    blobs = cv2.GaussianBlur(blobs, (0, 0), 2.0).clip(0, 1)[..., None]
    spots = cv2.GaussianBlur(spots, (0, 0), 1.5).clip(0, 1)[..., None]
    image = image * (1 - 0.8 * blobs) + np.array([0.93, 0.80, 0.52], np.float32) * 0.8 * blobs
    image = image * (1 - 0.5 * spots)
    return Texture(image=image.clip(0, 1).astype(np.float32), half_extent=half_extent)
