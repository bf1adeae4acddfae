"""The geometry of a tool pressing the tissue surface (issue 17; core/measure/indentation.py uses
it per frame, core/measure/deformation.py gives the compensated displacement u). Pure numpy, no
I/O; metres.

- clearance: the tool is a capsule (core/geometry/tool.py, shaft_radius_m around the axis from the
  rounded end's centre up the shaft); its clearance to the surface is min_i ‖x_i − axis‖ −
  radius (negative: tissue inside the tool model).
- under the tip: the points within tip_radius_mm of the tool axis (in the frame's positions)
  on the sheet of surface nearest the tip; a quantity there is fitted as c0 + c1 x + c2 y +
  c3 (x² + y²) over the lateral coordinates (Gaussian weights) and read at the axis, c0.
- deformed region: points whose |u| reaches threshold_mm, connected through the
  neighbourhoods to the most displaced point under the tip (and shown by the data: some of
  them beyond what σ_u explains, chi-square, 3 dof). Its area and volume are integrated over
  a Delaunay triangulation of the frame-0 points around it in their tangent plane (triangles
  with an edge longer than max_edge_mm and than HOLE_SPACINGS median edges span a hole in
  the template and are dropped; a sparse template keeps its wider triangles): per triangle
  touching the region, the share where the linearly interpolated |u| reaches the threshold, and the
  mean inward depth of its corners.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import Delaunay, QhullError
from scipy.stats import chi2

from ...config import ToolConfig
from ..classify.rules import Neighbourhoods
from ..geometry.poses import point_to_segment_distance
from ..geometry.tool import tool_capsules

HOLE_SPACINGS = 8.0  # a gap this many typical edges wide is a hole, however long max_edge


@dataclass(frozen=True)
class UnderTip:
    """The surface points under the tool tip: rows (M,) template indices, their lateral
    coordinates x, y (M,) m from the axis and heights h (M,) m along the axis above the
    tip, and Gaussian weights (M,)."""

    rows: np.ndarray
    x: np.ndarray
    y: np.ndarray
    h: np.ndarray
    weights: np.ndarray


def tool_clearance(positions: np.ndarray, tool_pose: np.ndarray,
                   tool: ToolConfig) -> np.ndarray:
    """Clearance (N,) m of every point (N, 3) m to the tool: the smallest over its capsules
    (shaft, jaw) of the distance to the capsule's axis minus its radius (negative inside;
    NaN for unknown points or tool pose)."""
    out = np.full(len(positions), np.nan)
    pose = np.asarray(tool_pose, float)
    ok = np.isfinite(positions).all(1)
    if not np.isfinite(pose).all() or not ok.any():
        return out
    out[ok] = np.min([point_to_segment_distance(positions[ok], a, b) - radius
                      for a, b, radius in tool_capsules(pose, tool)], axis=0)
    return out


def under_tip(positions: np.ndarray, tool_pose: np.ndarray, radius_m: float,
              ceiling_m: float) -> UnderTip:
    """The points (N, 3) m within `radius_m` of the tool axis, at most `ceiling_m` above the
    tip along it, on the sheet nearest the tip (within 2 x radius_m of the highest); weights
    exp(−ρ²/2s²) with s = radius_m / 2 (ρ the distance to the axis)."""
    pose = np.asarray(tool_pose, float)
    empty = np.zeros(0)
    if not np.isfinite(pose).all():
        return UnderTip(np.zeros(0, int), empty, empty, empty, empty)
    tip, axis = pose[:3, 3], pose[:3, 2] / np.linalg.norm(pose[:3, 2])
    e1 = np.cross(axis, [1.0, 0.0, 0.0] if abs(axis[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    d = np.asarray(positions, float) - tip
    with np.errstate(invalid="ignore"):
        h, x, y = d @ axis, d @ e1, d @ e2
        near = np.isfinite(h) & (x**2 + y**2 <= radius_m**2) & (h <= ceiling_m)
        if near.any():
            near &= h >= h[near].max() - 2.0 * radius_m
    rows = np.flatnonzero(near)
    s = radius_m / 2.0
    weights = np.exp(-(x[rows] ** 2 + y[rows] ** 2) / (2 * s**2))
    return UnderTip(rows, x[rows], y[rows], h[rows], weights)


def value_at_axis(tip: UnderTip, values: np.ndarray) -> float:
    """A quantity `values` (M,) of the points under the tip read at the axis: the weighted
    fit c0 + c1 x + c2 y + c3 (x² + y²), c0, with 6 points or more around the axis; with
    fewer, or all to one side, the radial fit c0 + c3 (x² + y²) when their distances to the
    axis differ enough to tell the curvature; else the weighted mean. NaN without points."""
    v = np.asarray(values, float)
    ok = np.isfinite(v)
    if not ok.any():
        return float("nan")
    w, x, y, v = tip.weights[ok], tip.x[ok], tip.y[ok], v[ok]
    r2 = x**2 + y**2
    sw = np.sqrt(w)
    mean = float((w * v).sum() / w.sum())
    spread = float(np.sqrt((w * r2).sum() / w.sum()))
    offset = float(np.hypot((w * x).sum(), (w * y).sum()) / w.sum())
    if len(v) >= 6 and offset <= 0.5 * spread:
        A = np.column_stack([np.ones_like(x), x, y, r2])
        if np.linalg.cond(A * sw[:, None]) < 1e8:
            return float(np.linalg.lstsq(A * sw[:, None], v * sw, rcond=None)[0][0])
    if len(v) >= 3 and np.sqrt(np.cov(r2, aweights=w)) >= 0.25 * spread**2:
        A = np.column_stack([np.ones_like(r2), r2])
        return float(np.linalg.lstsq(A * sw[:, None], v * sw, rcond=None)[0][0])
    return mean


def deformed_region(displacement: np.ndarray, sigma: np.ndarray | None, seed: int,
                    nb: Neighbourhoods, threshold_m: float, significance: float) -> np.ndarray:
    """(N,) bool: the points whose compensated displacement (N, 3) m reaches `threshold_m`,
    connected through the neighbourhoods to point `seed`; with σ (N,) m, only if some of
    them exceed what their noise explains (|u|² / (σ²/3) above the chi-square bound, 3 dof,
    at `significance`): a region the data show, grown over the points the registration
    carries with it (under the tool it is extrapolated, its σ large). Nothing when the seed
    does not reach the threshold, or seed < 0."""
    n = len(displacement)
    with np.errstate(invalid="ignore"):
        size = np.linalg.norm(displacement, axis=1)
        big = np.isfinite(size) & (size >= threshold_m)
    if seed < 0 or not big[seed]:
        return np.zeros(n, bool)
    edges = nb.mask & big[:, None] & big[nb.index]
    rows = np.repeat(np.arange(n), edges.sum(1))
    graph = coo_matrix((np.ones(len(rows)), (rows, nb.index[edges])), shape=(n, n))
    _, component = connected_components(graph, directed=False)
    region = big & (component == component[seed])
    if sigma is not None:
        var = np.asarray(sigma, float)[region] ** 2 / 3.0
        with np.errstate(invalid="ignore"):
            shown = size[region] ** 2 > chi2.isf(significance, 3) * np.where(
                np.isfinite(var), var, np.inf)
        if not shown.any():
            return np.zeros(n, bool)
    return region


def patch_triangles(points: np.ndarray, rows: np.ndarray,
                    max_edge_m: float) -> tuple[np.ndarray, np.ndarray]:
    """A Delaunay triangulation of the points `rows` (M,) of points (N, 3) m in their
    tangent plane: triangles (F, 3) of point indices (into `points`) and their areas (F,) m²
    in 3D; a triangle with an edge longer than `max_edge_m` and than HOLE_SPACINGS x the
    median edge spans a hole and is dropped.
    Empty when the patch cannot be triangulated."""
    rows = np.asarray(rows, int)
    q = np.asarray(points, float)[rows]
    none = (np.zeros((0, 3), int), np.zeros(0))
    if len(q) < 3:
        return none
    centred = q - q.mean(0)
    basis = np.linalg.svd(centred, full_matrices=False)[2][:2]
    try:
        tri = Delaunay(centred @ basis.T).simplices
    except QhullError:
        return none
    corners = q[tri]  # (F, 3, 3)
    edges = np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2)
    keep = edges.max(1) <= max(max_edge_m, HOLE_SPACINGS * float(np.median(edges)))
    tri, corners = tri[keep], corners[keep]
    area = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0],
                                         corners[:, 2] - corners[:, 0]), axis=1)
    return rows[tri], area


def share_above(values: np.ndarray, level: float) -> np.ndarray:
    """Share (F,) of each triangle where the linear interpolation of its corner values
    (F, 3) (magnitudes, >= 0; NaN counts as 0) reaches `level` > 0."""
    f = -np.sort(-np.nan_to_num(np.asarray(values, float), nan=0.0), axis=1)
    f1, f2, f3 = f[:, 0], f[:, 1], f[:, 2]
    with np.errstate(invalid="ignore", divide="ignore"):
        all_but_tip3 = 1.0 - (level - f3) ** 2 / ((f1 - f3) * (f2 - f3))
        tip1 = (f1 - level) ** 2 / ((f1 - f2) * (f1 - f3))
    out = np.where(f3 >= level, 1.0, 0.0)
    out = np.where((f2 >= level) & (f3 < level), all_but_tip3, out)
    out = np.where((f1 >= level) & (f2 < level), tip1, out)
    return np.clip(np.nan_to_num(out), 0.0, 1.0)
