"""Stray-colour tissue pairs (issue 28): a held-back tissue whose target carries strays that
lie ON the surface (within 1 mm) with random colours, so the geometric stray test keeps them
and only their colour gives them away.

The surface, its motion and its texture are those of `tissue_scene` / `tissue_texture` at
`seed + HOLD_BACK`: no stray-colour pair shares its tissue with a `tissue` family seed (the
ones the registration was tuned on before). Lengths in metres.
"""

from __future__ import annotations

import numpy as np

from .pairs import MM, Pair, finish_pair, keep_side, tissue_scene, tissue_texture, unit_vectors

HOLD_BACK = 7000  # seed offset of the held-back tissue
RGB_LEVEL = 1.0 / 255.0


def stray_colour_pair(n: int = 5000, seed: int = 0, *, partial: float = 0.0,
                      strays: float = 0.2, noise_mm: float = 0.2,
                      colour_levels: float = 4.0) -> Pair:
    """Source n noise-free points of the held-back tissue; target an independent resample of
    n points of the deformed surface with `noise_mm` Gaussian noise per axis, `partial` of it
    cut away (one contiguous side), plus `strays` x its size points on the deformed surface
    pushed 0-1 mm off it with uniformly random colours. Colours: the tissue's texture plus
    `colour_levels` RGB levels (of 255) of Gaussian noise per channel on both clouds."""
    rng = np.random.default_rng(seed)
    scene = tissue_scene(seed + HOLD_BACK)
    tex = tissue_texture(seed + HOLD_BACK)
    sigma_c = colour_levels * RGB_LEVEL
    src = scene.surface(n, rng)
    rest = scene.surface(n, rng)
    if partial > 0:
        angle = rng.uniform(0, 2 * np.pi)
        rest = rest[keep_side(rest, np.array([np.cos(angle), np.sin(angle), 0.0]), partial)]
    tgt = scene.warp(rest) + rng.normal(0, noise_mm * MM, rest.shape)
    k = round(strays * len(tgt))
    on = scene.warp(rest[rng.integers(0, len(rest), k)])
    stray_xyz = on + unit_vectors(rng, k) * rng.uniform(0, 1 * MM, (k, 1))
    srgb = np.clip(tex.sample(src[:, :2]) + rng.normal(0, sigma_c, src.shape), 0, 1)
    trgb = np.clip(tex.sample(rest[:, :2]) + rng.normal(0, sigma_c, rest.shape), 0, 1)
    outlier = np.r_[np.zeros(len(tgt), bool), np.ones(k, bool)]
    name = "stray_colour" + ("_partial" if partial > 0 else "")
    return finish_pair(name, src, scene.warp(src), np.r_[tgt, stray_xyz], outlier, rng,
                       srgb, np.r_[trgb, rng.uniform(0, 1, (k, 3))])
