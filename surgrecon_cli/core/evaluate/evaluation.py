"""Scoring a run against the simulator's ground truth (io/logs/ground_truth.py), per part:
template, registration, labels. Pure numpy on top of core/evaluate/scoring.py; the stage
(stages/evaluate.py) does the I/O.

Template points are mapped once onto the true frame-0 surface (`map_to_surface`); that
material point is followed through the frames (`SurfaceMapping.follow`) and its nearest true
vertex gives the true label. Distances in metres in, millimetres out.
"""

from __future__ import annotations

import numpy as np

from ...config import ToolConfig
from ..geometry.poses import point_to_segment_distance
from ..geometry.tool import shaft_segment
from .scoring import SurfaceMapping, distance_stats_mm

CLINICAL_MM = 1.0  # the spec's clinical accuracy requirement


def on_tool(points: np.ndarray, tool_pose: np.ndarray, cfg: ToolConfig) -> np.ndarray | None:
    """(N,) bool: points (N, 3) m closer to the shaft axis (tip + shaft_length_m along the tool
    frame's +z) than the shaft radius; None when the tool pose (4, 4) is unknown (NaN)."""
    pose = np.asarray(tool_pose, float)
    if not np.isfinite(pose).all():
        return None
    start, end = shaft_segment(pose, cfg)
    return point_to_segment_distance(points, start, end) < cfg.shaft_radius_m


def error_summary(errors_m: np.ndarray) -> dict[str, float]:
    """`distance_stats_mm` plus the fraction within the clinical 1 mm (of finite errors)."""
    stats: dict[str, float] = distance_stats_mm(errors_m)
    finite = np.asarray(errors_m, float)
    finite = finite[np.isfinite(finite)]
    within = float((finite <= CLINICAL_MM * 1e-3).mean()) if finite.size else float("nan")
    stats["within_1mm"] = within
    return stats


def registration_errors(mapping: SurfaceMapping, vertices: np.ndarray, faces: np.ndarray,
                        registered: np.ndarray) -> np.ndarray:
    """‖registered − followed material point‖ (N,) m at one frame (vertices (V, 3));
    NaN where the registered position (N, 3) is unknown."""
    followed = mapping.follow(vertices, faces)
    return np.linalg.norm(np.asarray(registered, float) - followed, axis=1)


def true_point_labels(mapping: SurfaceMapping, faces: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """True labels (..., N) of the template points: those of their nearest true vertices,
    for vertex labels (..., V)."""
    return np.asarray(labels)[..., mapping.nearest_vertex(faces)]

