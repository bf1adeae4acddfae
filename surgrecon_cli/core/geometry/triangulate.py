"""N-view triangulation: linear (DLT) then Gauss-Newton on the reprojection error.

Observations are flat arrays (one row per observation) so that every step is vectorised
over points: `point` (M,) index of the 3D point, `camera` (M,) camera index, `normalized`
(M, 2) undistorted normalised coordinates.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .cameras import CameraModel, distortion_jacobians, project
from .poses import invert_pose

INVERSE_STEPS = 3  # inverse-iteration solves of a DLT's null vector (`smallest_eigenvector`)
SHIFT_REL = 1e-12  # their shift relative to the trace: keeps a noise-free system definite


@dataclass(frozen=True)
class Observations:
    """Flat observation table: point (M,), camera (M,), pixels (M, 2), normalized (M, 2),
    rgb (M, 3) uint8 colour seen."""

    point: np.ndarray
    camera: np.ndarray
    pixels: np.ndarray
    normalized: np.ndarray
    rgb: np.ndarray

    def subset(self, keep: np.ndarray) -> Observations:
        return Observations(
            self.point[keep],
            self.camera[keep],
            self.pixels[keep],
            self.normalized[keep],
            self.rgb[keep],
        )

    def renumbered(self, keep_point: np.ndarray) -> Observations:
        """Observations of the kept points (bool (N,)), points renumbered 0..K-1."""
        new_index = np.cumsum(keep_point) - 1
        sub = self.subset(keep_point[self.point])
        return Observations(new_index[sub.point], sub.camera, sub.pixels, sub.normalized, sub.rgb)

    def mean_rgb(self, n_points: int) -> np.ndarray:
        """Mean observed colour (N, 3) uint8 per point."""
        count = np.maximum(np.bincount(self.point, minlength=n_points), 1)[:, None]
        total = np.stack(
            [
                np.bincount(self.point, weights=self.rgb[:, k].astype(float), minlength=n_points)
                for k in range(3)
            ],
            1,
        )
        return np.round(total / count).astype(np.uint8)


@dataclass(frozen=True)
class Triangulation:
    """Points (N, 3) m; per point mean/max reprojection error (px), views, max ray angle (deg),
    in_front (all depths > 0); per observation error_px (M,), the residual (M, 2) px and the
    depth (M,) m of `reprojection_residuals`."""

    points: np.ndarray
    mean_error_px: np.ndarray
    max_error_px: np.ndarray
    n_views: np.ndarray
    angle_deg: np.ndarray
    in_front: np.ndarray
    error_px: np.ndarray
    residual_px: np.ndarray
    depth: np.ndarray

    def of_points(self, keep_point: np.ndarray, point: np.ndarray) -> Triangulation:
        """The triangulation of the kept points (bool (N,)) alone, numbered as
        `Observations.renumbered` numbers them; point (M,): each observation's point. Every
        point is triangulated from its own observations only, so this is what triangulating
        the kept points' observations gives."""
        rows = keep_point[point]
        return Triangulation(
            self.points[keep_point], self.mean_error_px[keep_point],
            self.max_error_px[keep_point], self.n_views[keep_point],
            self.angle_deg[keep_point], self.in_front[keep_point], self.error_px[rows],
            self.residual_px[rows], self.depth[rows])


def _world_to_camera(poses: np.ndarray) -> np.ndarray:
    return invert_pose(poses)[:, :3, :]


def _point_sums(point: np.ndarray, values: np.ndarray, n_points: int) -> np.ndarray:
    """Per-point sums (N, K) of per-observation values (K, M), point (M,) their point."""
    return np.stack([np.bincount(point, weights=v, minlength=n_points) for v in values], axis=1)


def symmetric_sums(point: np.ndarray, rows: np.ndarray, n_points: int,
                   weights: np.ndarray | None = None) -> np.ndarray:
    """Per-point Σ w rowsᵀ rows (N, K, K) of the observations' rows (R, K, M) (observations
    last: every product below runs over M contiguous values), weighted by weights (M,)
    (None: 1)."""
    k = rows.shape[1]
    i, j = np.triu_indices(k)
    products = (rows[:, i] * rows[:, j]).sum(axis=0)
    upper = _point_sums(point, products if weights is None else products * weights, n_points)
    out = np.empty((n_points, k, k))
    out[:, i, j] = upper
    out[:, j, i] = upper
    return out


def spd_solve(normal: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """Solutions (R, n, m) of R symmetric positive definite systems normal (R, n, n) with
    right-hand sides rhs (R, n, m), by Cholesky factors computed for all R at once (a loop
    over the n columns, not over the systems: np.linalg.solve's LU of each small system
    costs twice as much for n = 6, R ~ 700). NaN where a system is not positive definite."""
    n = normal.shape[1]
    a = np.ascontiguousarray(np.moveaxis(normal, 0, -1))  # (n, n, R): systems last
    low = np.zeros(a.shape)  # the Cholesky factor, lower triangle
    x = np.ascontiguousarray(np.moveaxis(rhs, 0, -1), dtype=float)  # (n, m, R)
    with np.errstate(invalid="ignore", divide="ignore"):
        for j in range(n):
            row = low[j, :j]  # (j, R)
            low[j, j] = np.sqrt(a[j, j] - (row * row).sum(0))
            low[j + 1:, j] = (a[j + 1:, j] - (low[j + 1:, :j] * row).sum(1)) / low[j, j]
        for i in range(n):  # forward: low y = rhs
            x[i] = (x[i] - (low[i, :i, None] * x[:i]).sum(0)) / low[i, i]
        for i in range(n - 1, -1, -1):  # backward: lowᵀ x = y
            x[i] = (x[i] - (low[i + 1:, i, None] * x[i + 1:]).sum(0)) / low[i, i]
    return np.moveaxis(x, -1, 0)


def symmetric3_inverse(a: np.ndarray) -> np.ndarray:
    """Inverses (N, 3, 3) of symmetric matrices a (N, 3, 3), by their cofactors over the
    determinant (closed form, vectorised over N: LAPACK's batched inverse or solve of 3x3
    systems costs several times as much); inf or NaN where a is singular."""
    a00, a01, a02 = a[:, 0, 0], a[:, 0, 1], a[:, 0, 2]
    a11, a12, a22 = a[:, 1, 1], a[:, 1, 2], a[:, 2, 2]
    c00, c11, c22 = a11 * a22 - a12 * a12, a00 * a22 - a02 * a02, a00 * a11 - a01 * a01
    c01, c02, c12 = a02 * a12 - a01 * a22, a01 * a12 - a02 * a11, a01 * a02 - a00 * a12
    cofactors = np.stack([c00, c01, c02, c01, c11, c12, c02, c12, c22], axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        return (cofactors / (a00 * c00 + a01 * c01 + a02 * c02)[:, None]).reshape(-1, 3, 3)


def smallest_eigenvector(a: np.ndarray, steps: int = INVERSE_STEPS) -> np.ndarray:
    """Eigenvectors (N, K) of the smallest eigenvalue of positive semi-definite matrices a
    (N, K, K) (a DLT's null vectors), up to sign and scale, by inverse iteration from the
    last axis (`steps` solves, `spd_solve`, with a shift of SHIFT_REL of the trace that
    leaves the eigenvectors as they are): each step shrinks the others by the ratio of
    the smallest eigenvalue to theirs (~1e-6 for triangulated points), where LAPACK's
    batched eigh of 4x4 matrices costs ~5x as much. NaN where a is zero."""
    k = a.shape[1]
    shifted = a + (SHIFT_REL * np.trace(a, axis1=1, axis2=2))[:, None, None] * np.eye(k)
    v = np.zeros((len(a), k, 1))
    v[:, -1] = 1.0
    for _ in range(steps):
        v = spd_solve(shifted, v)
        with np.errstate(invalid="ignore"):
            v /= np.abs(v).max(1, keepdims=True)
    return v[:, :, 0]


def triangulate_linear(obs: Observations, poses: np.ndarray, n_points: int) -> np.ndarray:
    """DLT: the null vector of the stacked constraints x P3 - P1, y P3 - P2, per point."""
    P = np.moveaxis(_world_to_camera(poses)[obs.camera], 0, -1)  # (3, 4, M)
    x, y = obs.normalized[:, 0], obs.normalized[:, 1]
    rows = np.stack([x * P[2] - P[0], y * P[2] - P[1]])  # (2, 4, M)
    h = smallest_eigenvector(symmetric_sums(obs.point, rows, n_points))
    with np.errstate(divide="ignore", invalid="ignore"):
        return h[:, :3] / h[:, 3:4]


def refine_points(
    points: np.ndarray, obs: Observations, poses: np.ndarray, focal: np.ndarray,
    iterations: int = 6, distortion: np.ndarray | None = None,
) -> np.ndarray:
    """Gauss-Newton on Σ ‖f_c D_v (π(R_c X + t_c) − x_v)‖² per point, damped: the pixel
    error to first order, D_v (M, 2, 2) the lens distortion's Jacobian at each observation
    (`cameras.distortion_jacobians`; None: identity, the undistorted-pixel error)."""
    # Observations last (K, ..., M): every step is a product of M contiguous values.
    P = _world_to_camera(poses)[obs.camera]
    R = np.ascontiguousarray(np.moveaxis(P[:, :, :3], 0, -1))  # (3, 3, M)
    t = np.ascontiguousarray(P[:, :, 3].T)  # (3, M)
    w = focal[obs.camera]
    D = (np.eye(2)[:, :, None] if distortion is None
         else np.ascontiguousarray(np.moveaxis(distortion, 0, -1)))  # (2, 2, M)
    seen = np.ascontiguousarray(obs.normalized.T)  # (2, M)
    n = len(points)
    X = np.array(points, dtype=float)
    for _ in range(iterations):
        Xc = (R * X[obs.point].T[None]).sum(axis=1) + t  # (3, M)
        z = Xc[2]
        proj = Xc[:2] / z
        r = (D * (proj - seen)[None]).sum(axis=1) * w  # (2, M) ≈ px
        # ∂π/∂X R = [R_0 - x R_2; R_1 - y R_2] / z (rows of R), then D and the focal length
        dR = (R[:2] - proj[:, None] * R[2:3]) * (w / z)  # (2, 3, M)
        J = (D[:, :, None] * dR[None]).sum(axis=1)  # (2, 3, M)
        JtJ = symmetric_sums(obs.point, J, n)
        Jtr = _point_sums(obs.point, (J * r[:, None]).sum(axis=0), n)
        JtJ += np.eye(3) * 1e-9 * np.trace(JtJ, axis1=1, axis2=2)[:, None, None] + np.eye(3) * 1e-12
        X = X - np.einsum("nij,nj->ni", symmetric3_inverse(JtJ), Jtr)
    return X


def triangulate(
    obs: Observations, poses: np.ndarray, models: list[CameraModel], n_points: int
) -> Triangulation:
    """Triangulate every point seen in >= 2 observations and measure its quality."""
    focal = np.array([m.K[0, 0] for m in models])
    X = triangulate_linear(obs, poses, n_points)
    finite = np.isfinite(X).all(1)
    X[~finite] = 0.0
    X = refine_points(X, obs, poses, focal,
                      distortion=distortion_jacobians(obs.normalized, obs.camera, models))
    X[~finite] = np.nan
    residual, depth = reprojection_residuals(X, obs, poses, models)
    error = np.linalg.norm(residual, axis=1)
    error[~np.isfinite(error)] = np.inf
    n_views = np.bincount(obs.point, minlength=n_points)
    mean_err: np.ndarray = np.bincount(obs.point, weights=np.minimum(error, 1e6),
                                       minlength=n_points)
    mean_err = mean_err / np.maximum(n_views, 1)
    max_err = np.zeros(n_points)
    np.maximum.at(max_err, obs.point, error)
    in_front = np.ones(n_points, bool)
    np.logical_and.at(in_front, obs.point, depth > 0)
    return Triangulation(
        X, mean_err, max_err, n_views, max_ray_angle(X, obs, poses), in_front, error, residual,
        depth)


def reprojection_residuals(points: np.ndarray, obs: Observations, poses: np.ndarray,
                           models: list[CameraModel]) -> tuple[np.ndarray, np.ndarray]:
    """Projected minus observed pixel (M, 2) px of every observation of points (N, 3) m, and
    the point's depth (M,) m in that camera (NaN rows for non-finite points)."""
    residual = np.full((len(obs.point), 2), np.nan)
    depth = np.full(len(obs.point), -1.0)
    for c in np.unique(obs.camera):
        sel = obs.camera == c
        uv, z = project(points[obs.point[sel]], poses[c], models[c])
        residual[sel] = uv - obs.pixels[sel]
        depth[sel] = z
    return residual, depth


def max_ray_angle(points: np.ndarray, obs: Observations, poses: np.ndarray) -> np.ndarray:
    """Largest angle (deg) between any two viewing rays of each point (N,)."""
    n = len(points)
    rays = points[obs.point] - poses[obs.camera, :3, 3]
    rays /= np.maximum(np.linalg.norm(rays, axis=1, keepdims=True), 1e-12)
    # The largest angle is bounded through the mean ray: max angle to it, doubled; exact for
    # two views and a tight bound for more, without forming all pairs.
    mean = np.zeros((n, 3))
    np.add.at(mean, obs.point, rays)
    mean /= np.maximum(np.linalg.norm(mean, axis=1, keepdims=True), 1e-12)
    cos = (rays * mean[obs.point]).sum(1).clip(-1, 1)
    min_cos = np.ones(n)
    np.minimum.at(min_cos, obs.point, cos)
    return 2 * np.degrees(np.arccos(min_cos))
