"""A stereo pair's disparity measured in the pair's own images of the same instant.

Each view of a point is tracked over time on its own, and its depth is made by the
difference of the two views' tracks (the disparity). A view that slips along its epipolar
line (a highlight, a repeated texture, a deforming patch) moves the point along its line of
sight by millimetres on a narrow baseline, where geometry cannot see it (the slipped view
still meets the other's epipolar line), and the template lock (template_lock.py) corrects
the pair's common drift only. Here each point's patch in the first view is matched into the
second view of the same frame (KLT from the first view's pixel, starting at the second
view's): the two eyes see the tissue at the same instant, deformed alike, so this match
does not drift with time. Its offset from the second view's track, less the same match's
offset at frame 0 (the pair's fixed appearance difference: perspective, vignetting), is the
error of the tracked disparity, and the two views are moved apart by half of it each (the
pair's mean, which the lock has set, is kept), so that the depth is the match's.

Measured (2026-12-04, real SurgT texture re-rendered with a known breathing motion at
360×288, and the simulator's stereo variants, seeds 201-205): the offsets scatter by
0.02-0.06 px (robust σ) with a heavy tail (a tenth beyond 3σ, 0.1-0.25 px, 0.4-1 mm of
depth); positions against the truth p95 1.55 -> 1.39 mm, median 0.39 -> 0.35 mm; correcting
only the tail gave about the same.
Pure OpenCV/numpy on arrays.
"""

from __future__ import annotations

import numpy as np

from ...config import TargetConfig
from .tracking import TrackingView, klt_track

STEREO_LEVELS = 1  # ours: pyramid levels above the image for the match (a slip is < 2 px)


def stereo_match(view: tuple[TrackingView, TrackingView], pixels: np.ndarray,
                 cfg: TargetConfig) -> np.ndarray:
    """Where each point's patch around its first-view pixel matches in the second view
    (M, 2) px (KLT from pixels (M, 2, 2) px, first view's to the second view's as the
    start; NaN where a pixel is missing or the match fails KLT's forward-backward, patch or
    highlight checks)."""
    matched = np.full((len(pixels), 2), np.nan)
    rows = np.flatnonzero(np.isfinite(pixels).all((1, 2)))
    if len(rows):
        found, ok = klt_track(view[0], view[1], pixels[rows, 0], pixels[rows, 1], cfg,
                              STEREO_LEVELS)
        matched[rows[ok]] = found[ok]
    return matched


def disparity_errors(view: tuple[TrackingView, TrackingView], pixels: np.ndarray,
                     anchor_pixels: np.ndarray, anchor_match: np.ndarray,
                     cfg: TargetConfig) -> np.ndarray:
    """The errors (M, 2) px of one stereo pair's tracked disparities (module docstring):
    view the pair's current images (first camera, second camera), pixels and anchor_pixels
    (M, 2, 2) px the points' current and frame-0 pixels in the two cameras (NaN = not
    found), anchor_match (M, 2) px the frame-0 `stereo_match` of the template's images.
    Per point: where the first view's patch matches in the second view, less its tracked
    pixel there, less the same at frame 0; NaN where either match is missing."""
    out = np.full((len(pixels), 2), np.nan)
    rows = np.flatnonzero(np.isfinite(anchor_match).all(1))
    now = stereo_match(view, pixels[rows], cfg)
    out[rows] = (now - pixels[rows, 1]) - (anchor_match[rows] - anchor_pixels[rows, 1])
    return out
