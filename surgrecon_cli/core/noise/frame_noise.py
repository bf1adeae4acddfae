"""The localisation error a frame's tracked pixels actually carry, measured from their
over-determined evidence (no constants fitted to a simulator).

The Cramér-Rao bound of locating a patch (core/noise/model.py) is a floor: on real images
(compression, demosaicing, specular highlights, interlacing, focus) the error is several
times larger. A point found by >= 2 cameras in a frame is re-triangulated from its tracked
pixels; its residuals leave 2n − 3 degrees of freedom (two views: the error across the
epipolar line), which measure the frame's true per-view pixel error σ_k
(`pixel_noise_from_residuals`). What σ_k² carries beyond the variance the noise model
predicts for those views (pixel noise + tracking bound + the pose error a view's residuals
can see) is added to every tracked pixel's localisation variance. Pure numpy; no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..geometry.cameras import CameraModel, undistort_pixels, view_distortion_jacobians
from ..geometry.triangulate import Observations, Triangulation, spd_solve, triangulate
from .model import (
    NoiseModel,
    body_pose_covariance,
    pixel_noise_from_residuals,
    point_covariances,
    projection_jacobians,
    robust_sigma,
)

MIN_POINTS = 20  # ours: fewer points seen twice measure no frame noise (excess 0)
REJECT = 4.0  # ours: a track beyond this many σ from its neighbours' motion is lost
NEIGHBOURS = 36  # ours: tracks in a track's quadratic motion fit (6 parameters per axis; 6x)
MIN_FIT_PER_TERM = 2  # ours: fewer weighted neighbours per monomial leave a fit undetermined
MAX_LEVERAGE = 4.0  # ours: ... as does a leverage above this (neighbours nearly on a curve)
RIDGE = 1e-9  # relative ridge keeping degenerate fits solvable (then caught by MAX_LEVERAGE)
CANDIDATES = 64  # nearest tracks by reference pixel held per track (`PixelNeighbours`)


def tracked_observations(found: np.ndarray, pixels: np.ndarray,
                         models: list[CameraModel]) -> Observations:
    """Observations of the pixels (M, C, 2) px found (M, C) bool; points numbered by row."""
    rows, cams = np.nonzero(found)
    px = pixels[rows, cams]
    normalized = np.zeros_like(px)
    for c in np.unique(cams):
        normalized[cams == c] = undistort_pixels(px[cams == c], models[c])
    return Observations(rows, cams, px, normalized, np.zeros((len(rows), 3), np.uint8))


@dataclass(frozen=True)
class MultiView:
    """A frame's points found by >= 2 cameras, re-triangulated from their tracked pixels
    without any gate: their rows idx (K,) among the frame's points, their observations
    (points numbered 0..K-1 in the order of idx) and their triangulation."""

    idx: np.ndarray
    obs: Observations
    tri: Triangulation

    def of_rows(self, rows: np.ndarray) -> tuple[Observations, Triangulation]:
        """Observations and triangulation of the points `rows` (ascending, a subset of idx),
        numbered 0..len(rows)-1: what triangulating them alone gives."""
        keep = np.isin(self.idx, rows)
        return self.obs.renumbered(keep), self.tri.of_points(keep, self.obs.point)

    def views_of(self, rows: np.ndarray, use: np.ndarray) -> Observations:
        """Observations of the points `rows` (ascending, a subset of idx) in the cameras
        use (R, C) bool (a subset of each one's found views), numbered 0..R-1: what
        `tracked_observations` of those views gives, without undistorting their pixels
        again (each pixel is undistorted alone)."""
        sub = self.obs.renumbered(np.isin(self.idx, rows))
        return sub.subset(use[sub.point, sub.camera])


def triangulate_found(found: np.ndarray, pixels: np.ndarray, models: list[CameraModel],
                      poses: np.ndarray) -> MultiView:
    """The points found (N, C) bool by >= 2 cameras, triangulated from their pixels
    (N, C, 2) px at camera poses (C, 4, 4): once per frame, for the frame's noise
    (`tracking_excess_px2`) and the target's reprojection check (core/target/cloud.py)."""
    idx = np.flatnonzero(found.sum(1) >= 2)
    obs = tracked_observations(found[idx], pixels[idx], models)
    return MultiView(idx, obs, triangulate(obs, poses, models, len(idx)))


def tracking_excess_px2(multi: MultiView, localisation: np.ndarray, models: list[CameraModel],
                        noise: NoiseModel) -> tuple[float, float]:
    """(excess variance px², measured σ_k px) of a frame's tracked pixels: multi the points
    found by >= 2 cameras (`triangulate_found`), localisation (N, C) px² the tracking bound
    of each found pixel (module docstring). (0, NaN) with fewer than MIN_POINTS such
    points."""
    idx, obs, tri = multi.idx, multi.obs, multi.tri
    if len(idx) < MIN_POINTS:
        return 0.0, float("nan")
    residual, depth = tri.residual_px, tri.depth
    measured = pixel_noise_from_residuals(residual, obs.point)
    focal = np.array([m.K[0, 0] for m in models])[obs.camera]
    predicted = noise.tracked_view_variance_px2(
        depth, focal, localisation[idx[obs.point], obs.camera],
        pose=~noise.on_shared_body(obs.camera))
    predicted = predicted[np.isfinite(predicted) & (depth > 0)]
    if not np.isfinite(measured) or predicted.size == 0:
        return 0.0, float("nan")
    return max(0.0, measured**2 - float(np.median(predicted))), measured


def retriangulate(found: np.ndarray, pixels: np.ndarray, models: list[CameraModel],
                  poses: np.ndarray, noise: NoiseModel) -> tuple[np.ndarray, np.ndarray,
                                                                  np.ndarray]:
    """Every point found (N, C) bool by >= 2 cameras, re-triangulated from its tracked pixels
    (N, C, 2) px at camera poses (C, 4, 4), without any gate: positions (N, 3) m and their
    covariances (N, 3, 3) m² from image noise (pixel noise + the frame's tracking noise,
    `noise.tracking_px`) and from the cameras' pose errors (per view, or the rigid error of a
    shared tracker body). NaN for the other points. The classifier's own look at the
    evidence a gate summarised (core/target/cloud.py calls a point static when its frame-0
    position still explains every view separately; its views together may not)."""
    n = len(found)
    found = found & np.isfinite(poses).all((1, 2))[None, :]  # a camera without a pose: unused
    positions = np.full((n, 3), np.nan)
    image_cov = np.full((n, 3, 3), np.nan)
    pose_cov = np.full((n, 3, 3), np.nan)
    multi = triangulate_found(found, pixels, models, poses)
    idx, obs, tri = multi.idx, multi.obs, multi.tri
    if len(idx) == 0:
        return positions, image_cov, pose_cov
    ok = tri.in_front & np.isfinite(tri.points).all(1)
    at = np.nan_to_num(tri.points[obs.point])
    focal_px = np.array([m.K[0, 0] for m in models])
    focal = focal_px[obs.camera]
    J, z = projection_jacobians(at, poses[obs.camera], focal,
                                view_distortion_jacobians(at, obs.camera, poses, models))
    image = noise.independent_view_variance_px2(noise.tracked_view_variance_px2(
        z, focal, np.full(len(z), noise.tracking_px**2), pose=False))
    independent = image + np.where(noise.on_shared_body(obs.camera), 0.0,
                                   noise.pose_variance_px2(z, focal))
    lateral = noise.lateral_covariance(np.nan_to_num(tri.points), obs.point, obs.camera,
                                       poses[:, :3, 3], focal_px)
    cov = point_covariances(obs.point, J, image, len(idx)) + lateral
    body = body_pose_covariance(np.nan_to_num(tri.points), obs.point, obs.camera,
                                poses[:, :3, 3], noise)
    pose = point_covariances(obs.point, J, independent, len(idx)) + lateral - cov + body
    positions[idx[ok]] = tri.points[ok]
    image_cov[idx[ok]] = cov[ok]
    pose_cov[idx[ok]] = pose[ok]
    return positions, image_cov, pose_cov


@dataclass(frozen=True)
class PixelNeighbours:
    """The CANDIDATES nearest tracks of each of N tracks by reference pixel, among every
    track with one: idx (N, CANDIDATES) their rows, nearest first (the track itself first;
    N where none), dist (N, CANDIDATES) px (inf there). Built once for a set of reference
    pixels (the template's in one camera), it gives the nearest neighbours within any
    subset of the tracks (`among`) without a k-d tree of that subset."""

    idx: np.ndarray
    dist: np.ndarray

    @classmethod
    def of(cls, reference: np.ndarray) -> PixelNeighbours:
        """The neighbours of tracks at reference (N, 2) px (NaN: none; not a neighbour)."""
        ref = np.asarray(reference, float).reshape(-1, 2)
        n = len(ref)
        have = np.flatnonzero(np.isfinite(ref).all(1))
        idx = np.full((n, CANDIDATES), n)
        dist = np.full((n, CANDIDATES), np.inf)
        if len(have):
            d, j = cKDTree(ref[have]).query(ref[have], k=CANDIDATES)
            d, j = d.reshape(len(have), -1), j.reshape(len(have), -1)
            idx[have] = np.append(have, n)[j]
            dist[have] = d
        return cls(idx, dist)

    def among(self, rows: np.ndarray, reference: np.ndarray, k: int) -> np.ndarray:
        """The k + 1 nearest (M, k + 1) of the tracks rows (M,) (ascending, with a
        reference pixel) among themselves, as positions in rows, nearest first: what
        `cKDTree(reference[rows]).query(reference[rows], k + 1)` gives (reference (N, 2) px
        the pixels this was built from). A track whose k + 2 nearest in rows are not all
        among its candidates at distinct distances (a tie leaves their order to the tree)
        is queried so."""
        n = len(self.idx)
        position = np.full(n + 1, -1)
        position[rows] = np.arange(len(rows))
        found = position[self.idx[rows]]  # (M, CANDIDATES), -1: not in rows
        valid = found >= 0
        count = valid.sum(1)
        enough = count >= k + 2
        # the first k + 2 members of each row with enough, in order
        take = valid & (np.cumsum(valid, 1, dtype=np.int32) <= k + 2)
        take[~enough] = False
        width = self.idx.shape[1]
        members = np.flatnonzero(take)  # flat indices into (M, width), row by row
        nearest = found.ravel()[members].reshape(-1, k + 2)
        ample = rows[enough]  # the rows with enough members: their distances alone
        dist = self.dist.ravel()[(ample * width)[:, None] + (members % width).reshape(-1, k + 2)]
        last = self.dist[ample, -1]
        exact = (np.diff(dist, axis=1) > 0).all(1) & (dist[:, -1] < last)
        out = np.empty((len(rows), k + 1), int)
        good = np.flatnonzero(enough)[exact]
        out[good] = nearest[exact, :k + 1]
        other = np.ones(len(rows), bool)
        other[good] = False
        if other.any():
            ref = np.asarray(reference, float).reshape(-1, 2)[rows]
            _, j = cKDTree(ref).query(ref[other], k=k + 1)
            out[other] = j.reshape(-1, k + 1)
        return out


@dataclass(frozen=True)
class LocalFits:
    """The leave-one-out quadratic fits of one camera's tracks (`local_motion_residuals`),
    set up once for any weighting of the neighbours: idx (M, K) the K nearest other tracks
    of each of the M tracks (by reference pixel), design (M, 6, K) their monomials
    1, u, v, u², uv, v² of the offsets (u, v) about the track divided by scale (M,) px (so
    at most 1; (M, 3, K) for affine fits), columns (M, K, 8) the same monomials beside the
    neighbours' motions (the right-hand factor of one batched product that gives each fit's
    normal equations and right-hand side; (M, K, 5) for affine fits), motion (M, 2) px each
    track's motion."""

    idx: np.ndarray
    design: np.ndarray
    columns: np.ndarray
    motion: np.ndarray
    scale: np.ndarray

    @classmethod
    def of(cls, reference: np.ndarray, current: np.ndarray, neighbours: int,
           quadratic: bool = True, nearest: np.ndarray | None = None) -> LocalFits:
        """The fits of tracks from reference (M, 2) px to current (M, 2) px, M > neighbours
        (quadratic=False: affine fits, the design's first 3 monomials); nearest
        (M, neighbours + 1): each track's nearest tracks by reference pixel, itself first
        (`PixelNeighbours.among`; None: queried here)."""
        ref = np.asarray(reference, float).reshape(-1, 2)
        motion = np.asarray(current, float).reshape(-1, 2) - ref
        idx = cKDTree(ref).query(ref, k=neighbours + 1)[1] if nearest is None else nearest
        idx = np.ascontiguousarray(idx[:, 1:])  # the nearest is the track itself: left out
        # Per coordinate, each (M, K) plane contiguous (gathers and writes of planes cost a
        # quarter of those of (M, K, 2) or (M, K, 8) arrays), transposed once at the end.
        (x, y), (mx, my) = np.ascontiguousarray(ref.T), np.ascontiguousarray(motion.T)
        u, v = x[idx] - x[:, None], y[idx] - y[:, None]  # (M, K) about the track
        scale = np.maximum(np.maximum(np.abs(u).max(1), np.abs(v).max(1)), 1e-9)
        u, v = u / scale[:, None], v / scale[:, None]
        monomials = [1.0, u, v] + ([u * u, u * v, v * v] if quadratic else [])
        planes = np.empty((len(monomials) + 2, *idx.shape))
        for term, values in enumerate([*monomials, mx[idx], my[idx]]):
            planes[term] = values
        columns = np.ascontiguousarray(planes.transpose(1, 2, 0))
        design = np.ascontiguousarray(planes[:len(monomials)].transpose(1, 0, 2))
        return cls(idx, design, columns, motion, scale)

    def _solve(self, weight: np.ndarray | None, rows: np.ndarray | None
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The weighted fits of the tracks `rows` (R,) (None: all), neighbours weighted
        weight (M,) 0/1 (None: all 1): coefficients (R, 6, 2), (XᵀWX)⁻¹'s first column
        (R, 6) and whether each fit is determined (R,) bool (at least MIN_FIT_PER_TERM
        weighted neighbours per monomial and a leverage under MAX_LEVERAGE); 3 in place of
        6 for affine fits."""
        idx, design, columns = (self.idx, self.design, self.columns) if rows is None else (
            self.idx[rows], self.design[rows], self.columns[rows])
        w = np.ones(idx.shape) if weight is None else np.asarray(weight, float)[idx]  # (R, K)
        weighted = design if weight is None else design * w[:, None, :]
        product = np.matmul(weighted, columns)  # (R, terms, terms + 2): XᵀWX beside XᵀWy
        terms = design.shape[1]
        normal = product[:, :, :terms]
        diagonal = np.einsum("rii->ri", normal)  # a view
        diagonal += (RIDGE * diagonal.sum(1) + RIDGE)[:, None]
        rhs = np.concatenate([np.eye(terms)[None, :, :1].repeat(len(normal), 0),
                              product[:, :, terms:]], 2)
        solved = spd_solve(normal, rhs)  # (R, terms, 3)
        first = solved[:, :, 0]
        ok = ((w.sum(1) >= MIN_FIT_PER_TERM * terms) & np.isfinite(first[:, 0])
              & (first[:, 0] < MAX_LEVERAGE))
        return solved[:, :, 1:], first, ok

    def residuals(self, weight: np.ndarray | None = None,
                  rows: np.ndarray | None = None) -> np.ndarray:
        """Standardised residuals (R, 2) px of the tracks `rows` (R,) (None: all) with
        neighbours weighted weight (M,) 0/1 (None: all 1); NaN rows where a fit is not
        determined (`_solve`). The prediction at the track is the fit's constant term, its
        leverage (XᵀWX)⁻¹₀₀."""
        coef, first, ok = self._solve(weight, rows)
        motion = self.motion if rows is None else self.motion[rows]
        out = (motion - coef[:, 0, :]) / np.sqrt(1.0 + np.abs(first[:, :1]))
        out[~ok] = np.nan
        return out

    def jacobians(self) -> np.ndarray:
        """The local image maps (M, 2, 2) of the fits, ∂ current / ∂ reference at each
        track (identity plus the fitted motion's slopes there; NaN where a fit is not
        determined): how the neighbourhood's patch is warped since the reference image."""
        coef, _, ok = self._solve(None, None)
        out = np.eye(2) + coef[:, 1:3, :].transpose(0, 2, 1) / self.scale[:, None, None]
        out[~ok] = np.nan
        return out


def local_motion_residuals(reference: np.ndarray, current: np.ndarray,
                           neighbours: int = NEIGHBOURS,
                           weight: np.ndarray | None = None) -> np.ndarray:
    """Standardised residuals (M, 2) px of one camera's tracks against their neighbours'
    motion: reference (M, 2) px where each track started (the template's pixel), current
    (M, 2) px where it is now; weight (M,) 0/1: tracks that may serve as neighbours (None:
    all). Each track's motion is predicted by a least-squares quadratic fit (6 parameters
    per axis) of the motions of its `neighbours` nearest tracks (by reference pixel),
    itself left out (an affine fit leaves the perspective's curvature: on the `default`
    simulator 0.15 px of the true motion at frame 11, as much as the tracks' error);
    the prediction error r has variance σ² (1 + h) for a track error σ (per axis) shared
    by all tracks, h = x₀ᵀ (XᵀWX)⁻¹ x₀ the leverage of the left-out track in its
    neighbours' fit (equivalently: the in-sample residual over √(1 − h_ii)), so r / √(1 + h)
    has variance σ². NaN rows where a fit is not determined (`LocalFits._solve`);
    (0, 2) with fewer than neighbours + 1 tracks."""
    if len(np.asarray(reference).reshape(-1, 2)) < neighbours + 1:
        return np.zeros((0, 2))
    return LocalFits.of(reference, current, neighbours).residuals(weight)


def local_motion_noise_px(reference: np.ndarray, current: np.ndarray, found: np.ndarray,
                          neighbours: int = NEIGHBOURS,
                          candidates: list[PixelNeighbours] | None = None
                          ) -> tuple[float, float]:
    """Tracking localisation noise (σ, σ_shared) px per axis, measured from the tracks
    themselves: reference (N, C, 2) px where the tracks started (NaN = none), current
    (F, N, C, 2) or (N, C, 2) px where they are in F frames, found (F, N, C) or (N, C) bool.

    σ: the robust (MAD) scale, over every track, camera and frame, of the standardised
    residuals of `local_motion_residuals`: a smooth non-rigid motion is absorbed by the
    local quadratic fits; lost tracks (beyond REJECT σ) are left out of their neighbours' fits
    and the residuals computed again (twice). σ_shared: the part of σ common to a point's
    views (the same pixel error in each; for a stereo pair, an error across the line of
    sight that no disparity shows), from pairs of views of one point: half their sum has
    variance σ_s² + σ_i²/2, half their difference σ_i²/2, over every pair of cameras
    (0 without pairs). (NaN, 0) with fewer than MIN_POINTS residuals. candidates: per
    camera, `PixelNeighbours.of` its reference pixels (None: each fit's neighbours are
    queried)."""
    ref = np.asarray(reference, float)
    cur = np.asarray(current, float)
    seen = np.asarray(found, bool)
    if cur.ndim == 3:
        cur, seen = cur[None], seen[None]
    n_frames, _, n_cams = seen.shape
    use = seen & np.isfinite(ref).all(2)[None] & np.isfinite(cur).all(3)
    sets = [(f, c) for f in range(n_frames) for c in range(n_cams)
            if use[f, :, c].sum() > neighbours]
    # The neighbours and fits are set up once; a later pass recomputes only the tracks
    # whose neighbours' weights changed (the others' fits are the same).
    rows = [np.flatnonzero(use[f, :, c]) for f, c in sets]
    fits = [LocalFits.of(ref[r, c], cur[f, r, c], neighbours, nearest=None if candidates is None
                         else candidates[c].among(r, ref[:, c], neighbours))
            for (f, c), r in zip(sets, rows, strict=True)]
    residuals = [fit.residuals() for fit in fits]
    used = [np.ones(len(fit.motion), bool) for fit in fits]  # the weights residuals came from
    weights = used
    out = np.full(cur.shape, np.nan)
    sigma = float("nan")
    for _ in range(3):
        for k, (fit, w, u) in enumerate(zip(fits, weights, used, strict=True)):
            changed = np.flatnonzero((w[fit.idx] != u[fit.idx]).any(1))
            if len(changed):
                residuals[k][changed] = fit.residuals(w, changed)
        used = weights
        for (f, c), r in zip(sets, residuals, strict=True):
            out[f, use[f, :, c], c] = r
        stacked = out.reshape(-1, 2)
        stacked = stacked[np.isfinite(stacked).all(1)]
        if len(stacked) < MIN_POINTS:
            return float("nan"), 0.0
        sigma = robust_sigma(stacked)
        weights = [np.nan_to_num(np.abs(r).max(1), nan=np.inf) <= REJECT * sigma
                   for r in residuals]
    first, second = np.triu_indices(n_cams, 1)  # every pair of cameras at once
    if not len(first):
        return sigma, 0.0
    view_a, view_b = out[..., first, :], out[..., second, :]  # (F, N, pairs, 2)
    total, difference = (h[np.isfinite(h).all(-1) & (np.abs(h).max(-1) <= REJECT * sigma)]
                         for h in ((view_a + view_b) / 2.0, (view_a - view_b) / 2.0))
    if min(len(total), len(difference)) < MIN_POINTS:
        return sigma, 0.0
    shared2 = robust_sigma(total) ** 2 - robust_sigma(difference) ** 2
    return sigma, float(np.sqrt(np.clip(shared2, 0.0, sigma**2)))

