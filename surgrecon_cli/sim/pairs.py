"""Synthetic registration pairs with known truth (tests and benchmarks/registration.py).

A bumpy dome ~50 mm across (metres), a smooth breathing-like shift (<= 3 mm) plus a 5 mm
Gaussian indentation, and a colour pattern painted on the material points.
"""

from __future__ import annotations

import numpy as np

MM = 1e-3


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
