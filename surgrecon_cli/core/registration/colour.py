"""A colour weight that strays cannot decide (issue 28), for `register_pair`.

On the target cloud (metres, RGB 0..1):
1. colour strays: a point whose colour is far from the per-channel median colour of its
   `AGREE_NEIGHBOURS` nearest neighbours (farther than `AGREE_FACTOR` x the median such
   distance) does not agree with its neighbourhood; random-coloured strays, even lying on
   the surface, fail this test, textured tissue passes it (its neighbours share its colour
   up to noise and a small texture change);
2. on the agreeing points only, the squared colour difference between neighbours grows with
   their distance r as c(r)^2 ~ 2 s^2 + g^2 r^2 (colour noise s per point, texture gradient
   g per metre): a least-squares line through the medians of c^2 against those of r^2 per
   neighbour rank (ranks whose median distance is within `FIT_REACH_SPACINGS` spacings, at
   least `MIN_RANKS`) gives s and g at any density (1k to 100k points on the same tissue
   measure the same texture);
3. colour is used when the texture changes by more than `COLOUR_SNR` x its noise over the
   correspondence gate (g reach > COLOUR_SNR sqrt(2) s); the weight is COLOUR_GAIN / g
   (a slide d along the texture costs COLOUR_GAIN d in the matcher, as in surface.py).
Medians throughout: up to half of the points may be strays before they decide anything.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

# ours, tuned on stray_colour seeds 0-4 (benchmarks/registration.py): a slide d along the
# texture costs COLOUR_GAIN d in the matcher (4: medians 0.14-0.20 mm at 5k against
# 0.15-0.21 at 7.5, surface.py's gain, and 0.16-0.22 at a fixed 120 mm); colour is used when
# the texture changes by more than its noise over the gate (SNR 1: at 1k points the
# unresolved fine texture counts as noise, and colour still brings the median from 0.9 to
# 0.6 mm there; 2, surface.py's threshold, turns it off)
COLOUR_GAIN = 4.0
COLOUR_SNR = 1.0
AGREE_NEIGHBOURS = 8  # ours: neighbourhood whose median colour a point must agree with
AGREE_FACTOR = 3.0  # ours: disagreeing = colour farther than this x the median distance
FIT_RANKS = 16  # neighbour ranks the texture line is fitted over (at most)
FIT_REACH_SPACINGS = 4.0  # ours: ranks farther than this (median spacings) are left out
MIN_RANKS = 4
SAMPLES = 3000  # points the medians are taken over (a spread subset)
# neighbour lists kept for every agreeing point (itself first): the texture line's ranks, and
# overlap.py's rim and local planes (its RIM_NEIGHBOURS + 1), so one query serves both
NEIGHBOURS_KEPT = FIT_RANKS + 1


@dataclass(frozen=True)
class Neighbourhoods:
    """The agreeing target points' k-d tree (metres) and each one's nearest points, itself
    first: distances (A, k) m and indices (A, k) into the agreeing points (k =
    min(NEIGHBOURS_KEPT, A)). Measured once by `decide_colour`, shared with overlap.py."""

    tree: cKDTree
    distances: np.ndarray
    indices: np.ndarray

    @classmethod
    def of(cls, xyz: np.ndarray) -> Neighbourhoods:
        """The tree and neighbour lists of points xyz (M, 3) m."""
        tree = cKDTree(xyz)
        d, nn = tree.query(xyz, k=min(NEIGHBOURS_KEPT, len(xyz)))
        return cls(tree, d.reshape(len(xyz), -1), nn.reshape(len(xyz), -1))


@dataclass(frozen=True)
class ColourDecision:
    """weight_mm: mm per RGB unit (0 = colour not used); gradient (RGB units per mm) and
    noise s (RGB units per point) of the texture measured on the agreeing points; agree (M,)
    bool: target points whose colour agrees with their neighbourhood; reason: one phrase;
    spacing_m: median nearest-neighbour distance of the agreeing points (m, 0 = unknown);
    neighbours: their k-d tree and neighbour lists (None = not measured)."""

    weight_mm: float
    gradient: float
    noise: float
    agree: np.ndarray
    reason: str
    spacing_m: float = 0.0
    neighbours: Neighbourhoods | None = None


def _spread(idx: np.ndarray) -> np.ndarray:
    return idx[:: max(len(idx) // SAMPLES, 1)]


def colour_agreement(xyz: np.ndarray, rgb: np.ndarray) -> np.ndarray:
    """(M,) bool: points whose colour agrees with their neighbourhood (step 1)."""
    k = AGREE_NEIGHBOURS + 1
    if len(xyz) < 2 * k:
        return np.ones(len(xyz), bool)
    nn = cKDTree(xyz, balanced_tree=False).query(xyz, k=k)[1][:, 1:]
    # the per-channel median of the AGREE_NEIGHBOURS (even) colours: the mean of the middle
    # two of each sorted channel (as np.median, which is ~2x slower on this layout)
    ranked = np.sort(rgb[nn], axis=1)
    middle = AGREE_NEIGHBOURS // 2
    e = np.linalg.norm(rgb - 0.5 * (ranked[:, middle - 1] + ranked[:, middle]), axis=1)
    return e <= AGREE_FACTOR * max(float(np.median(e)), 1e-6)


def texture_line(xyz: np.ndarray, rgb: np.ndarray,
                 near: Neighbourhoods | None = None) -> tuple[float, float, float]:
    """(g RGB units per metre, s RGB units per point, median nearest-neighbour distance m)
    of clean points (step 2); near: their neighbour lists (None: measured here)."""
    k = min(FIT_RANKS + 1, len(xyz))
    pts = _spread(np.arange(len(xyz)))
    if near is not None and near.indices.shape[1] >= k:
        d, nn = near.distances[pts, :k], near.indices[pts, :k]
    else:
        d, nn = cKDTree(xyz).query(xyz[pts], k=k)
    r2 = np.median(d[:, 1:] ** 2, axis=0)
    c2 = np.median(np.sum((rgb[pts, None, :] - rgb[nn[:, 1:]]) ** 2, axis=2), axis=0)
    spacing = float(np.sqrt(r2[0]))
    ranks = max(MIN_RANKS, int(np.sum(r2 <= (FIT_REACH_SPACINGS**2) * r2[0])))
    r2, c2 = r2[:ranks], c2[:ranks]
    if not r2[-1] > r2[0]:  # coincident points: no distances to fit over
        return 0.0, 0.0, spacing
    slope, intercept = np.polyfit(r2, c2, 1)
    return (float(np.sqrt(max(slope, 0.0))), float(np.sqrt(max(intercept, 0.0) / 2.0)),
            spacing)


def decide_colour(xyz: np.ndarray, rgb: np.ndarray, reach_m: float) -> ColourDecision:
    """The colour decision for target points xyz (M, 3) m with colours rgb (M, 3) 0..1 (every
    point measured: strays are told apart by their colour, step 1); reach_m: correspondence
    gate."""
    agree = colour_agreement(xyz, rgb)
    if agree.sum() < 2 * MIN_RANKS + 2:
        return ColourDecision(0.0, 0.0, 0.0, agree, "too few points to measure the texture")
    near = Neighbourhoods.of(xyz[agree])
    g, s, h = texture_line(xyz[agree], rgb[agree], near)
    if g <= 0 or g * reach_m <= COLOUR_SNR * np.sqrt(2.0) * s:
        return ColourDecision(0.0, g * 1e-3, s, agree,
                              "the texture changes less than its noise over the gate", h, near)
    return ColourDecision(float(COLOUR_GAIN / g) * 1e3, g * 1e-3, s, agree,
                          "the texture changes by more than its noise over the gate", h, near)
