"""Scoring the contact and indentation measures against the simulator's truth (issue 17).
Pure numpy; the stage (stages/evaluate.py) does the I/O.

The truth applies the same definitions (core/measure/indentation.py) to the true surface: its
vertices at every frame, noiseless (σ = None: the contact tolerance is contact_floor_mm and
the deformed region needs no significance), with the true tool-tip poses. The simulator's
own dent depth (`indentation_m` of the ground truth, when recorded) is reported beside it,
as the bias of the definition itself.

Goals: contact onset and release within GOAL_FRAMES of the truth; the indentation depth at
the tip in the frames truly in contact within GOAL_DEPTH_MM or GOAL_DEPTH_SHARE of the true
depth (median error); the deformed area within GOAL_AREA_SHARE (median relative error over
the frames truly in contact with a deformed area); out of contact (breathing alone) no contact
reported and the depth under the tip within GOAL_NOISE_SIGMAS of its σ.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ...config import Config
from ..classify.rules import template_neighbourhoods
from ..measure.deformation import ReferenceSurface, surface_normals, surrounding_rings
from ..measure.indentation import Deformation, DeformationSeries, contact_events, measure_sequence

GOAL_FRAMES = 1
GOAL_DEPTH_MM = 0.3
GOAL_DEPTH_SHARE = 0.10
GOAL_AREA_SHARE = 0.20
GOAL_NOISE_SIGMAS = 2.0


def true_deformation(vertices: np.ndarray, tool_poses: np.ndarray, viewpoint: np.ndarray,
                     config: Config) -> Deformation:
    """The measures of the true surface: vertices (T, V, 3) m, tool_poses (T, 4, 4), normals
    turned towards viewpoint (3,) m; neighbourhoods and rings as for the run."""
    v0 = np.asarray(vertices[0], float)
    c, d = config.classify, config.deformation
    nb = template_neighbourhoods(v0, c.neighbourhood_mm, c.min_neighbours, c.max_neighbours)
    rings = surrounding_rings(v0, d.ring_inner_mm, d.ring_outer_mm, d.ring_points)
    normals = surface_normals(v0, nb, viewpoint)
    return measure_sequence(ReferenceSurface(v0, normals, nb, rings),
                            np.asarray(vertices, float), None, tool_poses, d, config.tool)


def _event_error(measured: int | None, true: int | None) -> int | None:
    """|measured − true| frames; 0 when neither happened; None when only one did."""
    if measured is None and true is None:
        return 0
    if measured is None or true is None:
        return None
    return abs(measured - true)


def _median(values: np.ndarray) -> float | None:
    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    return float(np.median(v)) if v.size else None


def _max(values: np.ndarray) -> float | None:
    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    return float(v.max()) if v.size else None


def score_deformation(measured: DeformationSeries, truth: DeformationSeries,
                      commanded_m: np.ndarray | None = None) -> dict[str, Any]:
    """Scores of the measured series against the true one (both T frames): events, depth,
    area and volume errors in the frames truly in contact, the breathing check out of
    contact, the goals (True / False; None when there is nothing to judge) and per frame."""
    onset, release = contact_events(measured.contact)
    t_onset, t_release = contact_events(truth.contact)
    onset_err, release_err = _event_error(onset, t_onset), _event_error(release, t_release)
    touching = np.asarray(truth.contact, bool)
    depth_err = np.abs(measured.indentation_mm - truth.indentation_mm)[touching]
    true_depth = truth.indentation_mm[touching]
    with np.errstate(invalid="ignore", divide="ignore"):
        depth_share = depth_err / np.abs(true_depth)
        has_area = touching & (truth.area_mm2 > 0)
        area_share = np.abs(measured.area_mm2 / truth.area_mm2 - 1.0)[has_area]
        volume_share = np.abs(measured.volume_mm3 / truth.volume_mm3 - 1.0)[has_area]
        free = ~touching
        over_noise = np.abs(measured.depth_under_tip_mm) / measured.depth_sigma_mm
    false_contacts = int((np.asarray(measured.contact, bool) & free).sum())
    depth_median, share_median = _median(depth_err), _median(depth_share)
    noise_max = _max(over_noise[free])
    area_median = _median(area_share)
    goals = {
        "contact_events": bool(onset_err is not None and release_err is not None
                               and max(onset_err, release_err) <= GOAL_FRAMES),
        "indentation": (None if depth_median is None else bool(
            depth_median <= GOAL_DEPTH_MM
            or (share_median is not None and share_median <= GOAL_DEPTH_SHARE))),
        "area": None if area_median is None else bool(area_median <= GOAL_AREA_SHARE),
        "breathing": (None if not free.any() else bool(
            false_contacts == 0 and (noise_max is None or noise_max <= GOAL_NOISE_SIGMAS))),
    }
    per_frame = []
    for k in range(truth.n_frames):
        per_frame.append({
            "frame": k, "contact": bool(measured.contact[k]),
            "true_contact": bool(truth.contact[k]),
            "true_clearance_mm": float(truth.clearance_mm[k]),
            "indentation_mm": float(measured.indentation_mm[k]),
            "true_indentation_mm": float(truth.indentation_mm[k]),
            "area_mm2": float(measured.area_mm2[k]), "true_area_mm2": float(truth.area_mm2[k]),
            "volume_mm3": float(measured.volume_mm3[k]),
            "true_volume_mm3": float(truth.volume_mm3[k]),
            "commanded_depth_mm": None if commanded_m is None else float(commanded_m[k] * 1e3),
        })
    definition_bias = None
    if commanded_m is not None and touching.any():
        definition_bias = _max(np.abs(truth.indentation_mm - commanded_m * 1e3)[touching])
    return {
        "onset_frame": onset, "true_onset_frame": t_onset, "onset_error_frames": onset_err,
        "release_frame": release, "true_release_frame": t_release,
        "release_error_frames": release_err,
        "frames_in_contact": int(touching.sum()),
        "indentation_error_mm": {"median": depth_median, "max": _max(depth_err)},
        "indentation_error_share": {"median": share_median, "max": _max(depth_share)},
        "area_error_share": {"median": area_median, "max": _max(area_share)},
        "volume_error_share": {"median": _median(volume_share), "max": _max(volume_share)},
        "out_of_contact": {"frames": int(free.sum()), "false_contacts": false_contacts,
                           "depth_over_sigma_max": noise_max},
        "definition_vs_commanded_max_mm": definition_bias,
        "goals": goals,
        "per_frame": per_frame,
    }
