"""Sub-pixel refinement of the template's matches by the tracker's own KLT.

A SIFT keypoint is located in each image on its own, to a few tenths of a pixel on real,
compressed endoscope images; the two errors of a stereo match add up in its disparity, and
at a 4 mm baseline 0.2 px of disparity is ~0.7 mm of depth at 70 mm (measured on a real
SurgT frame at 360x288: template disparities 0.20 px (median) / 0.80 px (p95) from an NCC
search on the rectified pair). Here every view of a track is re-located where the patch
around the track's first view appears in it: one Lucas-Kanade alignment (no pyramid, the
keypoint is within a pixel or two), checked forward-backward and photometrically exactly as
the target's tracks are (core/target/tracking.klt_track). The registration later tracks
the same patches from these pixels, so the template and its targets measure one point.
"""

from __future__ import annotations

import numpy as np

from ...config import TargetConfig
from ..geometry.cameras import CameraModel, undistort_pixels
from ..geometry.triangulate import Observations
from ..target.tracking import TrackingView, klt_track

REFINE_MAX_BASELINE_RATIO = 0.18  # ours: baseline / depth of pairs refined (`refinable_pairs`)


def refinable_pairs(baseline_ratio: np.ndarray) -> np.ndarray:
    """Camera pairs (C, C) bool whose views of a patch differ little enough for KLT's
    translated window: baseline / working depth (C, C) at most REFINE_MAX_BASELINE_RATIO
    (~10° of parallax; a surface facing both cameras is then foreshortened by ~1.5 %, 0.3 px
    across a 21 px window). A stereo endoscope's is ~0.06; wider rigs keep their keypoints."""
    return np.asarray(baseline_ratio) <= REFINE_MAX_BASELINE_RATIO


def first_views(obs: Observations, n_points: int) -> np.ndarray:
    """Index (N,) into `obs` of each point's view in its lowest-numbered camera (-1: none)."""
    order = np.lexsort((obs.camera, obs.point))
    first = np.full(n_points, -1)
    lead = np.ones(len(order), bool)
    lead[1:] = obs.point[order[1:]] != obs.point[order[:-1]]
    first[obs.point[order[lead]]] = order[lead]
    return first


def refine_observations(obs: Observations, views: list[TrackingView | None],
                        models: list[CameraModel], tracker: TargetConfig,
                        max_shift_px: float, pairs: np.ndarray) -> tuple[Observations, np.ndarray]:
    """Each view of a point in a camera b moved to where KLT (the tracker's window, no
    pyramid levels) aligns the patch around the point's first view (`first_views`, camera a)
    with it, for the camera pairs `pairs[a, b]` (C, C) bool (views alike enough for a
    translated patch: `refinable_pairs`), when the track passes the tracker's checks and
    moves at most `max_shift_px` px; other views, and the first views themselves, stay.
    `views[c]` is camera c's `tracking_view` (None: unusable). Returns the observations
    (pixels and their undistorted coordinates replaced) and which rows (M,) bool are kept:
    all but the views of `pairs` that were not refined. Such a view is dropped: the
    registration tracks the same patches with the same checks and would not follow it."""
    n_points = int(obs.point.max()) + 1 if len(obs.point) else 0
    first = first_views(obs, n_points)
    source = first[obs.point]
    pixels = obs.pixels.copy()
    refined = np.zeros(len(obs.point), bool)
    others = np.flatnonzero(source != np.arange(len(obs.point)))
    pair = obs.camera[source[others]] * len(views) + obs.camera[others]
    tried = np.zeros(len(obs.point), bool)
    for key in np.unique(pair):
        a, b = divmod(int(key), len(views))
        view_a, view_b = views[a], views[b]
        if view_a is None or view_b is None or not pairs[a, b]:
            continue
        rows = others[pair == key]
        tried[rows] = True
        moved, ok = klt_track(view_a, view_b, obs.pixels[source[rows]], obs.pixels[rows],
                              tracker, levels=0)
        ok &= np.linalg.norm(moved - obs.pixels[rows], axis=1) <= max_shift_px
        pixels[rows[ok]] = moved[ok]
        refined[rows[ok]] = True
    normalized = obs.normalized.copy()
    for c in np.unique(obs.camera[refined]):
        rows = refined & (obs.camera == c)
        normalized[rows] = undistort_pixels(pixels[rows], models[c])
    kept = refined | ~tried
    return Observations(obs.point, obs.camera, pixels, normalized, obs.rgb), kept
