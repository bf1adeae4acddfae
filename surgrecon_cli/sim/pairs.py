"""Synthetic registration pairs with known truth (tests and benchmarks/registration.py).

Two layers:
- the fixed bumpy dome of the early tests (`dome`, `warp`, `texture`): ~50 mm across
  (metres), a smooth breathing-like shift (<= 3 mm) plus a 5 mm Gaussian indentation, an
  analytic colour pattern painted on the material points;
- `Pair` and the seeded pair families (`tissue_pair` here, the colourless scanned shapes in
  `sim/pairs_shapes.py`, the catalogue of named families and seeds in `sim/pairs_catalog.py`).

In a seeded family the source and the target are sampled INDEPENDENTLY from the surface
(no target point is a moved source point), so the truth of a source point is where the
true motion takes it: truth = warp(source). All generators are pure functions of their
arguments (a seed in, arrays out).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from .texture import Texture, make_texture

MM = 1e-3


@dataclass(frozen=True)
class Pair:
    """One registration problem with its truth (metres).

    source (N, 3), target (M, 3); source_rgb (N, 3) / target_rgb (M, 3) in 0..1 or None
    (geometry only); truth (N, 3): the true moved position of every source point;
    target_outlier (M,) bool: gross outliers (strays, spikes) that lie off the true surface;
    diagonal_m: the source's bounding-box diagonal (m), the scale of the shape.
    """

    name: str
    source: np.ndarray
    target: np.ndarray
    source_rgb: np.ndarray | None
    target_rgb: np.ndarray | None
    truth: np.ndarray
    target_outlier: np.ndarray
    diagonal_m: float


def diagonal(points: np.ndarray) -> float:
    """Bounding-box diagonal (m) of points (N, 3)."""
    return float(np.linalg.norm(points.max(0) - points.min(0)))


def unit_vectors(rng: np.random.Generator, k: int) -> np.ndarray:
    """k random unit vectors (k, 3), uniform on the sphere."""
    d = rng.normal(size=(k, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def keep_side(points: np.ndarray, direction: np.ndarray, cut: float) -> np.ndarray:
    """Mask (N,) keeping all but the `cut` share of points lowest along `direction`: the
    removed part is one contiguous side of the cloud."""
    h = points @ direction
    return h > np.quantile(h, cut)


def finish_pair(name: str, source: np.ndarray, truth: np.ndarray, target: np.ndarray,
                outlier: np.ndarray, rng: np.random.Generator,
                source_rgb: np.ndarray | None = None,
                target_rgb: np.ndarray | None = None) -> Pair:
    """Shuffle the target (and its colours and outlier flags) and wrap everything in a Pair."""
    order = rng.permutation(len(target))
    return Pair(name, source, target[order], source_rgb,
                None if target_rgb is None else target_rgb[order], truth, outlier[order],
                diagonal(source))


# ----------------------------------------------------------------------------- fixed dome
def dome(n: int, rng: np.random.Generator) -> np.ndarray:
    """n points (n, 3) m on a bumpy dome: radius 25 mm, 8 mm high, 0.6 mm bumps."""
    r = 25.0 * np.sqrt(rng.uniform(0, 1, n))
    th = rng.uniform(0, 2 * np.pi, n)
    x, y = r * np.cos(th), r * np.sin(th)
    z = 8.0 * (1 - (r / 25.0) ** 2) + 0.6 * np.sin(x / 4.0) * np.cos(y / 5.0)
    return np.c_[x, y, z] * MM


def warp(p: np.ndarray) -> np.ndarray:
    """True motion of points (n, 3) m: smooth breathing shift + 5 mm Gaussian indentation."""
    x, y = p[:, 0] / MM, p[:, 1] / MM
    breath = 3.0 * np.exp(-((x - 8) ** 2 + y**2) / (2 * 15.0**2))
    u = np.c_[0.3 * breath, 0.1 * breath, breath]
    u[:, 2] -= 5.0 * np.exp(-((x + 6) ** 2 + (y - 4) ** 2) / (2 * 4.0**2))
    return p + u * MM


def texture(p: np.ndarray) -> np.ndarray:
    """Colour (n, 3) in 0..1 painted on the material points: a blob/vessel-like pattern."""
    x, y = p[:, 0] / MM, p[:, 1] / MM
    r = 0.55 + 0.35 * np.sin(x / 2.1 + 0.7 * np.sin(y / 3.3))
    g = 0.45 + 0.35 * np.cos(y / 1.7 - 0.5 * np.cos(x / 2.9))
    b = 0.5 + 0.35 * np.sin((x + y) / 2.6)
    return np.clip(np.c_[r, g, b], 0, 1)


# ----------------------------------------------------------------------------- tissue family
TISSUE_RADIUS_MM = 25.0


@dataclass(frozen=True)
class TissueScene:
    """The seeded tissue surface and its motion (all lengths mm).

    Surface: a dome (radius 25 mm, `height` high) plus Gaussian bumps (cx, cy, amp, sigma);
    motion: the part of the dome beyond a line (normal `edge_dir`, offset `edge`) shifts
    rigidly by `breath` (a smooth-step transition 8 mm wide: about half the points do not
    move), plus a tool indentation of `dent_depth` (Gaussian, sigma `dent_sigma`) at
    `dent_xy` along `dent_dir`.
    """

    height: float
    bumps: np.ndarray
    edge_dir: np.ndarray
    edge: float
    breath: np.ndarray
    dent_xy: np.ndarray
    dent_dir: np.ndarray
    dent_depth: float
    dent_sigma: float

    def surface(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """n points (n, 3) m sampled uniformly over the disk from the rest surface."""
        r = TISSUE_RADIUS_MM * np.sqrt(rng.uniform(0, 1, n))
        th = rng.uniform(0, 2 * np.pi, n)
        x, y = r * np.cos(th), r * np.sin(th)
        z = self.height * (1 - (r / TISSUE_RADIUS_MM) ** 2)
        z += 0.5 * np.sin(x / 4.0) * np.cos(y / 5.0)
        for cx, cy, amp, sig in self.bumps:
            z += amp * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * sig**2))
        return np.c_[x, y, z] * MM

    def warp(self, p: np.ndarray) -> np.ndarray:
        """True moved position (n, 3) m of rest points p (n, 3) m."""
        xy = p[:, :2] / MM
        s = np.clip((xy @ self.edge_dir - self.edge) / 8.0 + 0.5, 0, 1)
        u = (s * s * (3 - 2 * s))[:, None] * self.breath
        dent = np.exp(-((xy - self.dent_xy) ** 2).sum(1) / (2 * self.dent_sigma**2))
        u = u + (self.dent_depth * dent)[:, None] * self.dent_dir
        return p + u * MM


def tissue_scene(seed: int) -> TissueScene:
    """The tissue surface and motion of a seed: breathing of 2-3 mm, about as much sideways
    (sliding along the surface, which only colour can tell) as along the dome's axis, and a
    4-6 mm indentation."""
    rng = np.random.default_rng(seed + 31)
    bumps = np.c_[rng.uniform(-18, 18, (5, 2)), rng.uniform(-1.0, 1.0, 5), rng.uniform(3, 7, 5)]
    edge_angle = rng.uniform(0, 2 * np.pi)
    edge_dir = np.array([np.cos(edge_angle), np.sin(edge_angle)])
    side = rng.uniform(0.8, 1.2) * np.array([np.cos(edge_angle + rng.uniform(-1, 1)),
                                             np.sin(edge_angle + rng.uniform(-1, 1)), 0.0])
    up = side + np.array([0, 0, 1.0])
    breath = rng.uniform(2.0, 3.0) * up / np.linalg.norm(up)
    dent_xy = -edge_dir * rng.uniform(4, 10) + rng.uniform(-4, 4, 2)
    tilt = np.r_[rng.uniform(-0.3, 0.3, 2), -1.0]
    return TissueScene(height=rng.uniform(6, 10), bumps=bumps, edge_dir=edge_dir,
                       edge=rng.uniform(-4, 4), breath=breath, dent_xy=dent_xy,
                       dent_dir=tilt / np.linalg.norm(tilt), dent_depth=rng.uniform(4, 6),
                       dent_sigma=rng.uniform(3.5, 5))


@lru_cache(maxsize=4)
def tissue_texture(seed: int) -> Texture:
    """The procedural tissue texture of a seed (sim/texture.py), 0.06 mm per texel."""
    return make_texture(seed + 57, half_extent=0.031, size=1024)


def strays(base: np.ndarray, k: int, rng: np.random.Generator, lo: float,
           hi: float) -> np.ndarray:
    """k gross outliers (k, 3) m: random points of `base` pushed lo..hi m in random directions."""
    pick = base[rng.integers(0, len(base), k)]
    return pick + unit_vectors(rng, k) * rng.uniform(lo, hi, (k, 1))


def tissue_pair(n: int = 5000, seed: int = 0, *, partial: float = 0.0,
                outliers: float = 0.2, noise_mm: float = 0.2, colour_noise: float = 0.02,
                source_noise_mm: float = 0.0) -> Pair:
    """A coloured tissue pair: source and target each n points drawn independently from the
    seeded dome (`tissue_scene`), the target moved by the true warp, with Gaussian noise of
    `noise_mm` per axis, `partial` of it cut away (one contiguous side, a random direction
    in the dome's plane), then `outliers` * (its size) strays 1-5 mm off the surface with
    random colours. Colours: the procedural tissue texture at each point's material
    position, plus `colour_noise` per channel on both clouds. The source is noise-free by
    default (a template); truth = warp(source)."""
    rng = np.random.default_rng(seed)
    scene = tissue_scene(seed)
    tex = tissue_texture(seed)
    src = scene.surface(n, rng)
    src = src + rng.normal(0, source_noise_mm * MM, src.shape)
    rest = scene.surface(n, rng)
    tgt = scene.warp(rest) + rng.normal(0, noise_mm * MM, rest.shape)
    if partial > 0:
        angle = rng.uniform(0, 2 * np.pi)
        keep = keep_side(rest, np.array([np.cos(angle), np.sin(angle), 0.0]), partial)
        rest, tgt = rest[keep], tgt[keep]
    k = round(outliers * len(tgt))
    tgt = np.r_[tgt, strays(tgt, k, rng, 1 * MM, 5 * MM)]
    srgb = np.clip(tex.sample(src[:, :2]) + rng.normal(0, colour_noise, src.shape), 0, 1)
    trgb = np.clip(tex.sample(rest[:, :2]) + rng.normal(0, colour_noise, rest.shape), 0, 1)
    trgb = np.r_[trgb, rng.uniform(0, 1, (k, 3))]
    outlier = np.r_[np.zeros(len(rest), bool), np.ones(k, bool)]
    name = "tissue" + ("_partial" if partial > 0 else "")
    return finish_pair(name, src, scene.warp(src), tgt, outlier, rng, srgb, trgb)
