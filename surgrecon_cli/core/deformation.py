"""Tool–tissue contact and indentation measured from the reconstruction (issue 17): the
geometry behind vision-based force estimation (Su et al. 2019, introduction). Pure numpy, no
I/O; lengths in metres in and out (core/indentation.py assembles the per-frame figures, mm).

Inputs per frame k: the frame-0 template p_i (N, 3), its registered positions x_i (N, 3), their
uncertainty σ_i (N,) (3D RMS from the run's noise model, None for noiseless ground truth),
the tool-tip pose (4, 4) and the template's neighbourhoods (core/classify.py).

- compensated displacement u_i = x_i − (R_i p_i + t_i), (R_i, t_i) the best rigid motion of
  the point's *ring*: template points between ring_inner_mm and ring_outer_mm from p_i at
  frame 0 (fitted at ring centres, a voxel subsample of the template, and blended over the
  3 nearest: rings of neighbouring points are nearly the same). Breathing shifts the ring
  with the point and is removed; an indentation narrower than the ring stays. The fit is
  robust (iteratively reweighted from the least-squares fit, Cauchy weights, then Tukey's
  biweight, which gives members moving otherwise no weight at all; scale 4 x the members'
  median σ, 0.2 mm at least), so a ring crossing the edge of a breathing region or the dent's
  tail follows its majority (Cauchy weights alone let a ring half over a breathing ramp turn
  by 4° where the still part it centres on did not turn).
  σ_u² = σ_i² + σ̄²/n_eff (σ̄² the members' mean variance, n_eff their effective number).
- clearance: the tool is a capsule (core/tool.py, shaft_radius_m around the axis from the
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
from scipy.spatial import Delaunay, QhullError, cKDTree
from scipy.stats import chi2

from ..config import ToolConfig
from .classify import Neighbourhoods
from .geometry import nearest_rotation, point_to_segment_distance
from .tool import shaft_segment

SCALE_FLOOR_M = 2e-4  # robust scale of the ring fit at least 0.2 mm (noiseless truth)
SCALE_SIGMAS = 4.0  # ... else this many times the members' median σ
IRLS_ITERATIONS = 8
MIN_RING = 6  # ring members needed for a rigid fit worth the name
BLEND = 3  # ring centres whose motions carry a point
HOLE_SPACINGS = 8.0  # a gap this many typical edges wide is a hole, however long max_edge


@dataclass(frozen=True)
class Rings:
    """Rings of C centres (a voxel subsample of the template, spaced so that a ring holds
    about `members` of them): centres (C,) template indices, index (C, K) ring members
    (template indices, padded with the centre) and mask (C, K) bool; every template point
    takes the rigid motion of its BLEND nearest centres, nearest (N, BLEND) centre numbers
    with inverse-distance weights (N, BLEND) summing to 1."""

    centres: np.ndarray
    index: np.ndarray
    mask: np.ndarray
    nearest: np.ndarray
    weights: np.ndarray


@dataclass(frozen=True)
class CompensatedField:
    """One frame: displacement (N, 3) m after removing the rings' rigid motion (NaN:
    unknown), sigma (N,) m its 3D RMS uncertainty (NaN without a noise model), each point's
    rotation (N, 3, 3) (its nearest centre's), and the rings' motions: centre_rotation
    (C, 3, 3), centre_translation (C, 3) m, centre_used (C,) bool (enough members)."""

    displacement: np.ndarray
    sigma: np.ndarray
    rotation: np.ndarray
    centre_rotation: np.ndarray
    centre_translation: np.ndarray
    centre_used: np.ndarray


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


def voxel_subsample(points: np.ndarray, spacing_m: float) -> np.ndarray:
    """Indices (M,) of one point (the first) per cube of `spacing_m` of points (N, 3) m."""
    keys = np.floor(np.asarray(points, float) / spacing_m).astype(np.int64)
    _, first = np.unique(keys, axis=0, return_index=True)
    return np.sort(first)


def surrounding_rings(points: np.ndarray, inner_mm: float, outer_mm: float,
                      members: int) -> Rings:
    """Rings (see `Rings`) of template points (N, 3) m: for each centre, up to `members`
    centres between `inner_mm` and `outer_mm` from it at frame 0, spread over the ring."""
    points = np.asarray(points, float)
    inner, outer = inner_mm * 1e-3, outer_mm * 1e-3
    centres = voxel_subsample(points, float(np.sqrt(np.pi * (outer**2 - inner**2) / members)))
    c = len(centres)
    k = int(min(c, 4 * members))
    tree = cKDTree(points[centres])
    dist, idx = tree.query(points[centres], k=k, distance_upper_bound=outer)
    dist, idx = dist.reshape(c, k), idx.reshape(c, k)
    valid = np.isfinite(dist) & (dist >= inner)
    packed = np.take_along_axis(idx, np.argsort(~valid, axis=1, kind="stable"), 1)
    count = valid.sum(1)[:, None]
    j = np.arange(members)[None, :]
    pos = np.minimum(np.where(count > members, (j * count) // members, j), k - 1)
    mask = j < np.minimum(count, members)
    chosen = centres[np.minimum(np.take_along_axis(packed, pos, 1), c - 1)]
    blend = min(BLEND, c)
    dist, nearest = tree.query(points, k=blend)
    dist, nearest = dist.reshape(len(points), blend), nearest.reshape(len(points), blend)
    weights = 1.0 / np.maximum(dist, 1e-4)
    return Rings(centres, np.where(mask, chosen, centres[:, None]), mask, nearest,
                 weights / weights.sum(1, keepdims=True))


def surface_normals(points: np.ndarray, nb: Neighbourhoods, viewpoint: np.ndarray) -> np.ndarray:
    """Unit normals (N, 3) of template points (N, 3) m: the least-variance direction of each
    neighbourhood, turned towards `viewpoint` (3,) m (e.g. the cameras: out of the tissue)."""
    index = np.concatenate([np.arange(len(points))[:, None], nb.index], axis=1)
    w = np.concatenate([np.ones((len(points), 1)), nb.mask], axis=1).astype(float)
    q = points[index]
    mu = np.einsum("nk,nki->ni", w, q) / w.sum(1)[:, None]
    d = q - mu[:, None, :]
    _, vectors = np.linalg.eigh(np.einsum("nk,nki,nkj->nij", w, d, d))
    normals = vectors[:, :, 0]
    flip = ((np.asarray(viewpoint, float) - points) * normals).sum(1) < 0
    return np.where(flip[:, None], -normals, normals)


def compensated_field(reference: np.ndarray, moved: np.ndarray, rings: Rings,
                      sigma: np.ndarray | None = None) -> CompensatedField:
    """The rigid-motion-compensated displacement (module docstring) of every point from
    reference (N, 3) m (frame 0) to moved (N, 3) m (NaN: unknown), with σ (N,) m 3D RMS of
    the moved positions (including the template's) or None (noiseless). Each ring's motion
    is fitted at its centre; a point is carried by its nearest centres' motions, blended."""
    reference, moved = np.asarray(reference, float), np.asarray(moved, float)
    src, dst = reference[rings.index], moved[rings.index]
    keep = rings.mask & np.isfinite(dst).all(-1)
    member_sigma = np.zeros(rings.index.shape)
    if sigma is not None:
        member_sigma = np.asarray(sigma, float)[rings.index]
        keep &= np.isfinite(member_sigma)
        member_sigma = np.where(keep, member_sigma, 0.0)
    w = np.where(keep, 1.0 / (member_sigma**2 + SCALE_FLOOR_M**2), 0.0)
    used = keep.sum(1) >= MIN_RING
    scale = np.full(len(src), SCALE_FLOOR_M)
    if used.any() and sigma is not None:
        typical = np.nanmedian(np.where(keep, member_sigma, np.nan)[used], axis=1)
        scale[used] = np.maximum(SCALE_SIGMAS * typical, SCALE_FLOOR_M)
    dst = np.where(keep[..., None], dst, 0.0)
    R, t = _fit_rigid(src, dst, np.where(used[:, None], w, 1.0))  # least squares to start
    weight = w
    for it in range(IRLS_ITERATIONS):
        residual = np.where(keep[..., None], dst - np.matmul(src, R.transpose(0, 2, 1))
                            - t[:, None, :], 0.0)
        r2 = (residual**2).sum(-1) / scale[:, None] ** 2
        weight = w / (1.0 + r2)  # Cauchy first (from a start the outliers pulled) ...
        if it >= IRLS_ITERATIONS // 2:  # ... then Tukey's biweight, which rejects them
            hard = w * np.clip(1.0 - r2, 0.0, None) ** 2
            enough = (hard > 0).sum(1) >= MIN_RING
            weight = np.where(enough[:, None], hard, weight)
        R, t = _fit_rigid(src, dst, np.where(used[:, None], weight, 1.0))
    # a point carried by its nearest centres' motions (NaN where none could be fitted)
    near, blend = rings.nearest, rings.weights
    carried = np.einsum("nbij,nj->nbi", R[near], reference) + t[near]
    ok = used[near]
    blend = np.where(ok, blend, 0.0)
    total = blend.sum(1)
    with np.errstate(invalid="ignore", divide="ignore"):
        predicted = np.einsum("nb,nbi->ni", blend, carried) / total[:, None]
    u = moved - predicted
    u[total <= 0] = np.nan
    out_sigma = np.full(len(reference), np.nan)
    if sigma is not None:
        weight = np.where(keep, weight, 0.0)
        wsum = np.maximum(weight.sum(1), 1e-300)
        n_eff = np.maximum(wsum**2 / np.maximum((weight**2).sum(1), 1e-300), 1.0)
        fit_var = (weight * member_sigma**2).sum(1) / wsum / n_eff  # (C,)
        out_sigma = np.sqrt(np.asarray(sigma, float) ** 2 + fit_var[near[:, 0]])
        out_sigma[total <= 0] = np.nan
    return CompensatedField(u, out_sigma, R[near[:, 0]], R, t, used)


def _fit_rigid(src: np.ndarray, dst: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted least-squares rigid fits dst ≈ R src + t of (C, K, 3) members with weights
    (C, K): R (C, 3, 3), t (C, 3) (core/geometry.fit_rigid with batched matrix products)."""
    wn = w / np.maximum(w.sum(1, keepdims=True), 1e-300)
    mu_s = np.einsum("ck,cki->ci", wn, src)
    mu_d = np.einsum("ck,cki->ci", wn, dst)
    S = np.matmul((dst - mu_d[:, None, :]).transpose(0, 2, 1) * wn[:, None, :],
                  src - mu_s[:, None, :])
    R = nearest_rotation(S)
    return R, mu_d - np.einsum("cij,cj->ci", R, mu_s)


def tool_clearance(positions: np.ndarray, tool_pose: np.ndarray,
                   tool: ToolConfig) -> np.ndarray:
    """Clearance (N,) m of every point (N, 3) m to the tool capsule: distance to its axis
    minus the shaft radius (negative inside; NaN for unknown points or tool pose)."""
    out = np.full(len(positions), np.nan)
    pose = np.asarray(tool_pose, float)
    ok = np.isfinite(positions).all(1)
    if not np.isfinite(pose).all() or not ok.any():
        return out
    a, b = shaft_segment(pose, tool)
    out[ok] = point_to_segment_distance(positions[ok], a, b) - tool.shaft_radius_m
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
