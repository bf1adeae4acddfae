"""Rigid-body helpers: quaternions (x, y, z, w), homogeneous poses, slerp, rigid fits.

Quaternion conversions and slerp use `scipy.spatial.transform.Rotation` (scalar-last order,
as here); everything is vectorised over leading axes.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from ...errors import GeometryError


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Quaternions (..., 4) (x, y, z, w) -> rotation matrices (..., 3, 3).

    Normalised first; a zero or non-finite quaternion gives a NaN matrix.
    """
    q = np.asarray(q, dtype=float)
    flat = q.reshape(-1, 4)
    ok = np.isfinite(flat).all(axis=1) & (np.linalg.norm(flat, axis=1) > 0)
    out = np.full((len(flat), 3, 3), np.nan)
    if ok.any():
        out[ok] = Rotation.from_quat(flat[ok]).as_matrix()
    return out.reshape((*q.shape[:-1], 3, 3))


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) -> unit quaternions (..., 4) (x, y, z, w), w >= 0."""
    R = np.asarray(R, dtype=float)
    q = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_quat(canonical=True)
    return q.reshape((*R.shape[:-2], 4))


def make_pose(position: np.ndarray, quat: np.ndarray) -> np.ndarray:
    """Positions (..., 3) and quaternions (..., 4) -> homogeneous poses (..., 4, 4)."""
    position = np.asarray(position, dtype=float)
    T = np.zeros((*position.shape[:-1], 4, 4))
    T[..., :3, :3] = quat_to_matrix(quat)
    T[..., :3, 3] = position
    T[..., 3, 3] = 1.0
    return T


def invert_pose(T: np.ndarray) -> np.ndarray:
    """Inverse of rigid poses (..., 4, 4)."""
    Ti = np.zeros_like(T)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    Ti[..., :3, :3] = Rt
    Ti[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3])
    Ti[..., 3, 3] = 1.0
    return Ti


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply one pose (4, 4) to points (N, 3)."""
    return points @ T[:3, :3].T + T[:3, 3]


def compose_affines(outer: np.ndarray, inner: np.ndarray) -> np.ndarray:
    """Per-point affine composition (N, 3, 4) of affines outer and inner (N, 3, 4):
    x -> outer(inner(x))."""
    A = outer[:, :, :3] @ inner[:, :, :3]
    b = np.einsum("nij,nj->ni", outer[:, :, :3], inner[:, :, 3]) + outer[:, :, 3]
    return np.concatenate([A, b[:, :, None]], axis=2)


def slerp(q0: np.ndarray, q1: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Spherical interpolation between unit quaternions (N, 4) (x, y, z, w) at fractions
    s (N,) in [0, 1], along the shorter arc; s = 0 gives q0 itself (same sign)."""
    r0 = Rotation.from_quat(q0)
    step = (r0.inv() * Rotation.from_quat(q1)).as_rotvec()  # angle <= pi: the shorter arc
    return (r0 * Rotation.from_rotvec(np.asarray(s, float)[:, None] * step)).as_quat()


def interpolate_poses(
    stamps_ns: np.ndarray,
    positions: np.ndarray,
    quats: np.ndarray,
    query_ns: np.ndarray,
    max_gap_ns: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pose stream (M,) sorted stamps, (M, 3) positions, (M, 4) quats -> values at query (Q,).

    Linear in position, slerp in rotation. A query outside the stream or inside a gap
    longer than `max_gap_ns` is invalid (never extrapolated).
    Returns positions (Q, 3), quats (Q, 4) and valid (Q,) bool.
    """
    query_ns = np.asarray(query_ns, dtype=np.int64)
    n_query = query_ns.shape[0]
    out_p = np.full((n_query, 3), np.nan)
    out_q = np.full((n_query, 4), np.nan)
    if len(stamps_ns) == 0:
        return out_p, out_q, np.zeros(n_query, bool)
    hi = np.searchsorted(stamps_ns, query_ns, side="left")
    exact = (hi < len(stamps_ns)) & (stamps_ns[np.minimum(hi, len(stamps_ns) - 1)] == query_ns)
    lo = hi - 1
    inside = (lo >= 0) & (hi < len(stamps_ns))
    lo_c = np.clip(lo, 0, len(stamps_ns) - 1)
    hi_c = np.clip(hi, 0, len(stamps_ns) - 1)
    gap = stamps_ns[hi_c] - stamps_ns[lo_c]
    valid = exact | (inside & (gap <= max_gap_ns))
    span = np.where(gap > 0, gap, 1).astype(float)
    s = np.where(exact, 1.0, (query_ns - stamps_ns[lo_c]) / span).clip(0, 1)
    lo_c = np.where(exact, hi_c, lo_c)
    out_p[valid] = (positions[lo_c] * (1 - s[:, None]) + positions[hi_c] * s[:, None])[valid]
    out_q[valid] = slerp(quats[lo_c[valid]], quats[hi_c[valid]], s[valid])
    return out_p, out_q, valid


def fit_rigid(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None):
    """Least-squares rigid transform (Kabsch/Umeyama without scale), batched.

    src, dst: (..., N, 3); weights (..., N) or None. Returns R (..., 3, 3), t (..., 3)
    with dst ~ src @ R.T + t.
    """
    src = np.asarray(src, float)
    dst = np.asarray(dst, float)
    if src.shape != dst.shape or src.shape[-2] < 3:
        raise GeometryError(
            f"fit_rigid needs matching (..., N>=3, 3) arrays, got {src.shape}, {dst.shape}"
        )
    if weights is None:
        weights = np.ones(src.shape[:-1])
    w = weights / np.maximum(weights.sum(-1, keepdims=True), 1e-300)
    # weighted sums as batched products (numpy's three-operand einsum is ~2x slower)
    mu_s = np.matmul(w[..., None, :], src)[..., 0, :]
    mu_d = np.matmul(w[..., None, :], dst)[..., 0, :]
    S = np.matmul(np.swapaxes((dst - mu_d[..., None, :]) * w[..., None], -1, -2),
                  src - mu_s[..., None, :])
    R = nearest_rotation(S)
    t = mu_d - np.einsum("...ij,...j->...i", R, mu_s)
    return R, t


def nearest_rotation(A: np.ndarray) -> np.ndarray:
    """Closest rotation (Frobenius) to each 3x3 matrix in (..., 3, 3); det fixed to +1."""
    U, _, Vt = np.linalg.svd(A)
    d = np.sign(np.linalg.det(U @ Vt))
    D = np.ones(U.shape[:-1])
    D[..., -1] = d
    return U @ (D[..., :, None] * Vt)


def rectified_rig_pose(rectification: np.ndarray, projection: np.ndarray) -> np.ndarray:
    """Pose (4, 4) of a camera in the rectified frame of its stereo rig's first camera, from
    its ROS CameraInfo: x_rect = R x_raw (`rectification` (3, 3)), and its rectified frame
    sits at (−Tx/fx′, −Ty/fy′, 0) there (`projection` P (3, 4): Tx = P[0, 3], fx′ = P[0, 0];
    the lengths are P's, metres in a ROS message)."""
    R = np.asarray(rectification, float).reshape(3, 3)
    P = np.asarray(projection, float).reshape(3, 4)
    if not (np.isfinite(R).all() and np.isfinite(P).all()) or P[0, 0] == 0 or P[1, 1] == 0:
        raise GeometryError("a rectified camera needs a finite R and a P with fx', fy' != 0")
    pose = np.eye(4)
    pose[:3, :3] = nearest_rotation(R)
    pose[:3, 3] = [-P[0, 3] / P[0, 0], -P[1, 3] / P[1, 1], 0.0]
    return pose


def point_to_segment_distance(points: np.ndarray, start: np.ndarray, end: np.ndarray) -> np.ndarray:
    """Distance (N,) m from points (N, 3) to the segment start-end (3,)."""
    axis = end - start
    s = ((points - start) @ axis / max(float(axis @ axis), 1e-30)).clip(0, 1)
    return np.linalg.norm(points - (start + s[:, None] * axis), axis=1)
