"""The named registration pair families and the seeds they are tuned and accepted on.

Seeds: TUNING_SEEDS (0-4) are for developing and tuning the registration; ACCEPTANCE_SEEDS
(100-104) are for the figures reported against the goals of issue 14, and must not be
tuned on. `make_pair(family, n, seed)` builds one pair; every family takes any seed.

Families (all lengths in metres; see sim/pairs.py and sim/pairs_shapes.py for the truth):
- tissue, tissue_partial (30 % of the target cut away), tissue_noisy (0.5 mm noise, 40 %
  strays): coloured dome ~50 mm across, independent resampling, 20 % strays 1-5 mm off;
- blob, torus, body, limb: colourless scans, motion up to 10 % of the diagonal, noise
  0.1 % of the diagonal, 2 % spikes; blob_partial, body_partial: single-view target scans;
- blob_noisy, body_noisy: noise 0.5 % of the diagonal and 10 % spikes;
- stray_colour, stray_colour_partial (30 % cut away): a held-back tissue (sim/pairs_stray.py),
  0.2 mm noise, 4 RGB levels of colour noise, 20 % strays ON the surface with random colours;
  stray_colour_30: the same with 30 % strays, at 1k and 2k points;
- rotation: the body turned 90 degrees about a random axis, scaled 0.8, plus 3 % non-rigid.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from .pairs import Pair, tissue_pair
from .pairs_shapes import rotation_pair, shape_pair
from .pairs_stray import stray_colour_pair

TUNING_SEEDS = (0, 1, 2, 3, 4)
ACCEPTANCE_SEEDS = (100, 101, 102, 103, 104)


@dataclass(frozen=True)
class Family:
    """A pair family: build(n, seed) -> Pair; the sizes it is benchmarked at; coloured?"""

    build: Callable[[int, int], Pair]
    sizes: tuple[int, ...]
    coloured: bool


def _shape(shape: str, **kw: float | bool) -> Callable[[int, int], Pair]:
    return lambda n, seed: shape_pair(shape, n, seed, **kw)  # type: ignore[arg-type]


FAMILIES: dict[str, Family] = {
    "tissue": Family(lambda n, s: tissue_pair(n, s), (2000, 5000, 20000), True),
    "tissue_partial": Family(lambda n, s: tissue_pair(n, s, partial=0.3), (5000,), True),
    "tissue_noisy": Family(lambda n, s: tissue_pair(n, s, noise_mm=0.5, outliers=0.4),
                           (5000,), True),
    "stray_colour": Family(lambda n, s: stray_colour_pair(n, s), (2000, 5000, 20000), True),
    "stray_colour_partial": Family(lambda n, s: stray_colour_pair(n, s, partial=0.3), (5000,),
                                   True),
    "stray_colour_30": Family(lambda n, s: stray_colour_pair(n, s, strays=0.3), (1000, 2000),
                              True),
    "blob": Family(_shape("blob"), (5000,), False),
    "torus": Family(_shape("torus"), (5000,), False),
    "body": Family(_shape("body"), (5000,), False),
    "limb": Family(_shape("limb"), (5000,), False),
    "blob_partial": Family(_shape("blob", partial=True), (5000,), False),
    "body_partial": Family(_shape("body", partial=True), (5000,), False),
    "blob_noisy": Family(_shape("blob", noise=0.005, spikes=0.1), (5000,), False),
    "body_noisy": Family(_shape("body", noise=0.005, spikes=0.1), (5000,), False),
    "rotation": Family(lambda n, s: rotation_pair(n, s), (5000,), False),
}


def make_pair(family: str, n: int, seed: int) -> Pair:
    """The pair of a named family (FAMILIES) with n source points, for a seed."""
    return FAMILIES[family].build(n, seed)
