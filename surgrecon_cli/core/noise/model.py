"""The run's noise model, measured from the run itself (no constants fitted to a simulator).

Three sources, each estimated from data the run already has:
- **pixel noise** σ_px (px, per image axis): from the template's reprojection residuals.
  A point triangulated from n views leaves 2n − 3 degrees of freedom in its 2n residual
  components, so each component has variance σ² (2n − 3) / (2n); a robust (MAD) scale of
  the components, divided by the root of that factor, estimates σ. It measures everything
  that scatters a point's image position at frame 0 (detector, JPEG, calibration, and the
  frame-0 tracker error seen through the other views). Its localisation part is measured
  apart: the residuals less each camera's median residual, the systematic offset a
  calibration error leaves (`localisation_noise_px`).
- **tracker jitter** (m and rad, per axis): from each pose stream on its own. At tracker
  rates (tens of Hz) the true motion is smooth over three samples, so the residual of a
  sample against the linear interpolation (slerp for rotation) of its two neighbours is
  noise: r = n_k − (1 − a) n_{k−1} − a n_{k+1}, variance σ² (1 + (1 − a)² + a²).
- **tracking noise** (px): the Cramér-Rao bound of locating a patch, σ_I² (Σ_w ∇I ∇Iᵀ)⁻¹
  over the KLT window, from the image's own noise σ_I (Immerkær 1996) and its texture at
  that point: a point on weak texture is known less well. (The forward-backward KLT
  disagreement does not measure it: tracking the same images back retraces the same path,
  0.003 px on our simulator against 0.1-0.3 px of real error.) The bound is a floor:
  core/noise/frame_noise.py adds what each frame's re-triangulated residuals show beyond it.

Cameras on one tracked body (a stereo endoscope carries one marker) share their pose error:
their relative pose does not jitter (`shared_bodies` finds them from the pose streams). For
views of such a body the pose error is not a per-view pixel error (it does not change the
disparity) but a rigid error of the whole reconstruction, added to the covariance as such
(`rigid_pose_covariance`); treating it per view would inflate a 5 mm baseline's depth
uncertainty several times.

From these and the camera geometry, every triangulated point gets a 3D covariance
Σ = (Σ_v J_vᵀ J_v / s_v²)⁻¹ (J_v the 2x3 pixel Jacobian of view v, s_v² its pixel
variance: pixel noise plus the tracker's pose error projected at the point's depth:
(f σ_pos / z)² + (f σ_rot)²). The scalar σ reported per point is √trace Σ, the RMS of the
3D position error: a Gaussian error lies within 2σ of it 95–99 % of the time, depending
on how elongated Σ is. Pure numpy; no I/O.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from ..geometry.triangulate import symmetric3_inverse, symmetric_sums

MAD_TO_SIGMA = 1.4826  # σ of a Gaussian from its median absolute deviation


@dataclass(frozen=True)
class NoiseModel:
    """Measured noise of a run (1σ, per axis): pixel_px image noise at frame 0 (px),
    tracking_px the median tracking (patch localisation) noise of a frame (px, reported;
    each view uses its own), tracker_position_m (m) and tracker_rotation_rad (rad) pose
    jitter of the navigation tracker; tracking_shared_px (px) the part of tracking_px
    common to a point's views (core/noise/frame_noise.local_motion_noise_px): it moves a
    re-triangulated point across the line of sight, not along it."""

    pixel_px: float
    tracking_px: float
    tracker_position_m: float
    tracker_rotation_rad: float
    shared_body: tuple[bool, ...] = ()  # per camera index: shares its tracker body
    tracking_shared_px: float = 0.0

    def pose_variance_px2(self, depth_m: np.ndarray, focal_px: np.ndarray) -> np.ndarray:
        """Pixel variance (px²) one view gets from the tracker's pose error, at depth (M,) m
        with focal length (M,) px: a position error moves the image by f σ / z, a rotation
        error by about f σ_rot."""
        depth = np.maximum(np.asarray(depth_m, float), 1e-6)
        focal = np.asarray(focal_px, float)
        return ((focal * self.tracker_position_m / depth) ** 2
                + (focal * self.tracker_rotation_rad) ** 2)

    def tracked_view_variance_px2(self, depth_m: np.ndarray, focal_px: np.ndarray,
                                  localisation_px2: np.ndarray,
                                  pose: np.ndarray | bool = True) -> np.ndarray:
        """Pixel variance (M,) px² of points found by tracking in a later frame: the base
        position's pixel noise, the tracking's localisation variance (M,) px² and, where
        `pose` (M,) bool, the current pose error."""
        pose_var = np.where(pose, self.pose_variance_px2(depth_m, focal_px), 0.0)
        return self.pixel_px**2 + np.asarray(localisation_px2, float) + pose_var

    def on_shared_body(self, cameras: np.ndarray) -> np.ndarray:
        """(M,) bool: each camera index (M,) shares its tracker body with another camera."""
        flags = np.array((*self.shared_body, False), bool)
        cams = np.asarray(cameras, int)
        return flags[np.where((cams >= 0) & (cams < len(self.shared_body)), cams, -1)]

    def rigid_pose_covariance(self, points: np.ndarray, centres: np.ndarray) -> np.ndarray:
        """(N, 3, 3) m²: a whole tracked body's pose error seen at points (N, 3) m from its
        camera centre (N, 3) m: σ_pos² I + σ_rot² (‖r‖² I − r rᵀ) (a small rotation about
        the camera moves a point at r by ω × r)."""
        r = np.asarray(points, float) - np.asarray(centres, float)
        eye = np.eye(3)[None]
        rot = (np.einsum("ni,ni->n", r, r)[:, None, None] * eye
               - np.einsum("ni,nj->nij", r, r))
        return self.tracker_position_m**2 * eye + self.tracker_rotation_rad**2 * rot


    def lateral_covariance(self, points: np.ndarray, point_index: np.ndarray,
                           cameras: np.ndarray, centres: np.ndarray,
                           focal_px: np.ndarray) -> np.ndarray:
        """(N, 3, 3) m²: the shared tracking error (`tracking_shared_px`) of points (N, 3) m
        with views point_index (M,) / cameras (M,) (camera centres (C, 3) m, focal lengths
        (C,) px): the same pixel error in every view moves a point across its line of sight
        d (from its first view's camera), by (r σ_shared / f)² (I − d dᵀ) at range r.
        Zero for points without a view."""
        out = np.zeros((len(points), 3, 3))
        if self.tracking_shared_px <= 0 or len(point_index) == 0:
            return out
        first_view = np.unique(point_index, return_index=True)[1]
        rows, cams = point_index[first_view], cameras[first_view]
        r = np.asarray(points, float)[rows] - np.asarray(centres, float)[cams]
        dist = np.maximum(np.linalg.norm(r, axis=1), 1e-9)
        d = r / dist[:, None]
        scale = (dist * self.tracking_shared_px / np.asarray(focal_px, float)[cams]) ** 2
        out[rows] = scale[:, None, None] * (np.eye(3)[None] - np.einsum("ni,nj->nij", d, d))
        return out

    def independent_view_variance_px2(self, variance_px2: np.ndarray) -> np.ndarray:
        """Pixel variance (M,) px² of views (M,) px² without the tracking error their point's
        views share (`lateral_covariance` carries it); at least the pixel noise."""
        return np.maximum(np.asarray(variance_px2, float) - self.tracking_shared_px**2,
                          self.pixel_px**2)


def robust_sigma(values: np.ndarray) -> float:
    """σ of zero-mean Gaussian samples from their median absolute value (NaN if empty)."""
    v = np.abs(np.asarray(values, float).ravel())
    v = v[np.isfinite(v)]
    return float(MAD_TO_SIGMA * np.median(v)) if v.size else float("nan")


def pixel_noise_from_residuals(residuals_px: np.ndarray, point_index: np.ndarray) -> float:
    """σ_px (px, per axis) from reprojection residual vectors (M, 2) of triangulated points,
    point_index (M,) the point of each residual.

    A point seen in n views leaves d = 2n − 3 degrees of freedom in its 2n residual
    components (two views: one, the error across the epipolar line; the components along it
    are zero). Its sum of squared residuals is σ² χ²(d), so σ² is estimated robustly as the
    median over the points of (sum / median of χ²(d)): every point counts once, with its
    own dof, and components that triangulation forced to zero never pull σ down."""
    r = np.asarray(residuals_px, float).reshape(-1, 2)
    point = np.asarray(point_index, np.int64).reshape(-1)
    ok = np.isfinite(r).all(1)
    if not ok.any():
        return float("nan")
    n_points = int(point[ok].max()) + 1
    squares = np.bincount(point[ok], (r[ok] ** 2).sum(1), minlength=n_points)
    views = np.bincount(point[ok], minlength=n_points)
    dof = 2 * views - 3
    has = dof >= 1
    if not has.any():
        return float("nan")
    return float(np.sqrt(np.median(squares[has] / chi2.median(dof[has]))))


def calibration_offsets_px(residuals_px: np.ndarray, camera: np.ndarray,
                           n_cameras: int) -> np.ndarray:
    """Each camera's systematic reprojection offset (C, 2) px: the median of its residual
    vectors (M, 2) (camera (M,) the camera of each). Localisation errors average out of the
    median; a calibration error does not: a stereo pair whose extrinsics are slightly off puts
    every match the same fraction of a pixel off its epipolar line (SurgT's rectified rows:
    0.37 px at 1280×1024), which the triangulation leaves in its views' residuals; so does the
    frame-0 pose error of a camera on its own tracker. NaN rows for cameras without
    residuals."""
    r = np.asarray(residuals_px, float).reshape(-1, 2)
    cam = np.asarray(camera, np.int64).reshape(-1)
    offsets = np.full((n_cameras, 2), np.nan)
    ok = np.isfinite(r).all(1)
    for c in np.unique(cam[ok]):
        offsets[c] = np.median(r[ok & (cam == c)], axis=0)
    return offsets


def localisation_noise_px(residuals_px: np.ndarray, point_index: np.ndarray,
                          camera: np.ndarray, n_cameras: int) -> tuple[float, np.ndarray]:
    """The localisation part of the pixel noise: σ (px, per axis) of the reprojection
    residuals (M, 2) once each camera's systematic offset (`calibration_offsets_px`) is taken
    out, and those offsets (C, 2) px. `pixel_noise_from_residuals` on the raw residuals
    measures both; without a calibration or pose error the two agree."""
    cam = np.asarray(camera, np.int64).reshape(-1)
    offsets = calibration_offsets_px(residuals_px, cam, n_cameras)
    centred = np.asarray(residuals_px, float).reshape(-1, 2) - np.nan_to_num(offsets)[cam]
    return pixel_noise_from_residuals(centred, point_index), offsets


def image_noise_sigma(grey: np.ndarray) -> float:
    """Intensity noise σ_I (grey levels) of an image (H, W), Immerkær's (1996) estimator:
    the mean absolute response to a mask that cancels locally planar intensity."""
    g = np.asarray(grey)
    if g.shape[0] < 3 or g.shape[1] < 3:
        return 0.0
    # the mask is the outer product of [1, -2, 1] with itself: separable, and on an 8-bit
    # image its integer response (at most 16 x 255) is exact in int16
    kernel = np.array([1, -2, 1], np.float32)
    depth = cv2.CV_16S if g.dtype == np.uint8 else cv2.CV_32F
    response = cv2.sepFilter2D(g, depth, kernel, kernel,
                               borderType=cv2.BORDER_REPLICATE)[1:-1, 1:-1]
    h, w = g.shape
    if depth == cv2.CV_16S:  # Σ |response|: integers, exact in any order (no copy)
        total = cv2.norm(response, cv2.NORM_L1)
    else:
        total = cv2.norm(np.ascontiguousarray(response), cv2.NORM_L1)
    return float(np.sqrt(np.pi / 2) * total / (6.0 * (w - 2) * (h - 2)))


def localisation_variance_px2(grey: np.ndarray, pixels: np.ndarray, window_px: int,
                              noise_sigma: float) -> np.ndarray:
    """Per-axis variance (M,) px² of locating the window around pixels (M, 2) in an image
    (H, W): the Cramér-Rao bound σ_I² trace((Σ_w ∇I ∇Iᵀ)⁻¹) / 2 (Sobel gradients, scale
    1/8, the window's sums centred on the rounded pixel). Pixels outside: inf."""
    g = np.asarray(grey, np.float32)
    out = np.full(len(pixels), np.inf)
    uv = np.round(np.asarray(pixels, float)).astype(np.int64) if len(pixels) else np.zeros(
        (0, 2), np.int64)
    inside = ((uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] < g.shape[1])
              & (uv[:, 1] < g.shape[0]))
    if inside.any():
        a, b, c = _gradient_sums(g, uv[inside, 0], uv[inside, 1], int(window_px))
        det = a * c - b * b
        trace_inverse = (a + c) / np.maximum(det, 1e-12)
        out[inside] = np.where(det > 1e-12, noise_sigma**2 * trace_inverse / 2.0, np.inf)
    return out


def _gradient_sums(g: np.ndarray, u: np.ndarray, v: np.ndarray,
                   window: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Σ gx², Σ gx gy, Σ gy² (each (M,)) over the window x window patches of image g (H, W)
    float32 centred on pixels (u, v) (M,) int: from patches cut around the points alone when
    they cover less than the image (cost ∝ points), else by box filters of the whole image
    (borders reflected either way)."""
    half = window // 2
    if len(u) * (window + 2) ** 2 >= g.size:
        gx = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3, scale=1 / 8)
        gy = cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3, scale=1 / 8)
        sums = cv2.boxFilter(cv2.merge([gx * gx, gx * gy, gy * gy]), -1, (window, window),
                             normalize=False)[v, u].astype(float)  # one pass, 3 channels
        return sums[:, 0], sums[:, 1], sums[:, 2]
    pad = half + 1
    steps = np.arange(-pad, pad + 1)
    h, w = g.shape
    if pad < min(h, w):  # the patches' pixels, borders reflected by index (no padded copy)
        patch = g[_reflect_101(v[:, None] + steps, h)[:, :, None],
                  _reflect_101(u[:, None] + steps, w)[:, None, :]]
    else:  # an image smaller than a patch: reflected repeatedly
        padded = cv2.copyMakeBorder(g, pad, pad, pad, pad, cv2.BORDER_REFLECT_101)
        patch = padded[(v + pad)[:, None, None] + steps[None, :, None],
                       (u + pad)[:, None, None] + steps[None, None, :]]
    # patch: (M, window + 2, window + 2)
    dx = patch[:, :, 2:] - patch[:, :, :-2]  # central differences, then [1 2 1] / 8 across
    dy = patch[:, 2:, :] - patch[:, :-2, :]
    gx = (dx[:, :-2] + 2.0 * dx[:, 1:-1] + dx[:, 2:]) / 8.0
    gy = (dy[:, :, :-2] + 2.0 * dy[:, :, 1:-1] + dy[:, :, 2:]) / 8.0
    return ((gx * gx).sum((1, 2), dtype=float), (gx * gy).sum((1, 2), dtype=float),
            (gy * gy).sum((1, 2), dtype=float))


def _reflect_101(index: np.ndarray, n: int) -> np.ndarray:
    """Indices (any shape) within one reflection of an axis of n pixels mapped onto it as
    OpenCV's BORDER_REFLECT_101 does (-1 -> 1, n -> n - 2)."""
    index = np.abs(index)
    return np.where(index > n - 1, 2 * (n - 1) - index, index)


def pose_jitter(stamps_ns: np.ndarray, positions: np.ndarray,
                quats: np.ndarray) -> tuple[float, float]:
    """Per-axis tracker noise (σ_position m, σ_rotation rad) of one pose stream: stamps (M,)
    increasing, positions (M, 3), quaternions (M, 4) x y z w. NaN with fewer than 3 samples.
    A stream that repeats one pose (a fixed or static pose) gives 0."""
    t = np.asarray(stamps_ns, np.float64)
    if len(t) < 3:
        return float("nan"), float("nan")
    a = (t[1:-1] - t[:-2]) / np.maximum(t[2:] - t[:-2], 1.0)
    gain = np.sqrt(np.mean(1.0 + (1.0 - a) ** 2 + a**2))
    p = np.asarray(positions, float)
    pos_res = p[1:-1] - ((1.0 - a)[:, None] * p[:-2] + a[:, None] * p[2:])
    rot = Rotation.from_quat(np.asarray(quats, float))
    before, after, middle = rot[:-2], rot[2:], rot[1:-1]
    step = (before.inv() * after).as_rotvec()
    predicted = before * Rotation.from_rotvec(step * a[:, None])
    rot_res = (predicted.inv() * middle).as_rotvec()
    return robust_sigma(pos_res) / gain, robust_sigma(rot_res) / gain


def projection_jacobians(points: np.ndarray, cam_to_world: np.ndarray,
                         focal_px: np.ndarray, distortion: np.ndarray | None = None
                         ) -> tuple[np.ndarray, np.ndarray]:
    """Pixel Jacobians J (M, 2, 3) px/m of points (M, 3) m in cameras with poses (M, 4, 4)
    and focal lengths (M,) px, and the points' depths (M,) m. distortion (M, 2, 2): the lens
    distortion's Jacobian at each view (`cameras.view_distortion_jacobians`), making J the
    Jacobian of the distorted pixel for any distortion model; None: pinhole (undistorted)
    pixels."""
    R = cam_to_world[:, :3, :3]
    Xc = np.einsum("mji,mj->mi", R, points - cam_to_world[:, :3, 3])  # R^T (X - c)
    z = Xc[:, 2]
    inv_z = 1.0 / np.where(np.abs(z) > 1e-9, z, 1e-9)
    dproj = np.zeros((len(points), 2, 3))
    dproj[:, 0, 0] = dproj[:, 1, 1] = inv_z
    dproj[:, 0, 2] = -Xc[:, 0] * inv_z**2
    dproj[:, 1, 2] = -Xc[:, 1] * inv_z**2
    # batched 2x2 and 2x3 products by matmul (einsum's loops cost ~3x as much)
    if distortion is not None:
        dproj = np.matmul(distortion, dproj)
    J = np.matmul(dproj, R.transpose(0, 2, 1)) * np.asarray(focal_px, float)[:, None, None]
    return J, z


def point_covariances(point_index: np.ndarray, jacobians: np.ndarray, variance_px2: np.ndarray,
                      n_points: int) -> np.ndarray:
    """3D covariances (N, 3, 3) m² of triangulated points from their views: point_index (M,)
    the point of each view, jacobians (M, 2, 3), variance_px2 (M,) pixel variance per view.
    Points with fewer than 2 views or a degenerate geometry get NaN."""
    weights = 1.0 / np.maximum(np.asarray(variance_px2, float), 1e-12)
    info = symmetric_sums(point_index, np.moveaxis(jacobians, 0, -1), n_points, weights)
    cov = np.full((n_points, 3, 3), np.nan)
    eig = np.linalg.eigvalsh(info)
    ok = eig[:, 0] > 1e-12 * np.maximum(eig[:, 2], 1e-300)
    cov[ok] = symmetric3_inverse(info[ok])
    return cov


def covariance_sigma(cov: np.ndarray) -> np.ndarray:
    """√trace Σ (N,) m: the RMS of a 3D position error with covariance (N, 3, 3)."""
    return np.sqrt(np.maximum(np.trace(cov, axis1=1, axis2=2), 0.0))


def shared_bodies(own: list[tuple[float, float]],
                  relative: dict[tuple[int, int], tuple[float, float]]) -> list[list[int]]:
    """Groups of camera indices on one tracked body: cameras i, j whose relative pose
    jitters less than half as much as either alone (independent markers would jitter √2
    times as much), by position and rotation. own: per camera (σ_pos, σ_rot); relative:
    (i, j) -> (σ_pos, σ_rot) of j's pose relative to i's. Cameras alone are left out."""
    parent = list(range(len(own)))

    def root(i: int) -> int:
        while parent[i] != i:
            i = parent[i]
        return i

    for (i, j), (pos, rot) in relative.items():
        pos_ref = min(own[i][0], own[j][0])
        rot_ref = min(own[i][1], own[j][1])
        if (np.isfinite(pos) and np.isfinite(rot) and pos_ref > 0 and rot_ref > 0
                and pos < 0.5 * pos_ref and rot < 0.5 * rot_ref):
            parent[root(j)] = root(i)
    groups: dict[int, list[int]] = {}
    for i in range(len(own)):
        groups.setdefault(root(i), []).append(i)
    return [g for g in groups.values() if len(g) > 1]


def noise_from_report(report: dict, cameras: tuple[str, ...], pixel_px: float) -> NoiseModel:
    """The run's noise model from ingest's report (per camera tracker_jitter_mm /
    tracker_jitter_deg, tracker_bodies) and the template's pixel noise (px): the tracker
    figures are the median over the cameras that have one (0 if none has); tracking_px is
    measured per frame later (0 here)."""
    per_camera = report.get("cameras", {})

    def median(key: str, to_si: Callable[[float], float]) -> float:
        values = [per_camera.get(cid, {}).get(key) for cid in cameras]
        finite = [to_si(v) for v in values if v is not None and np.isfinite(v)]
        return float(np.median(finite)) if finite else 0.0

    on_body = {cid for group in report.get("tracker_bodies", []) for cid in group}
    return NoiseModel(
        pixel_px=float(pixel_px) if np.isfinite(pixel_px) else 0.0,
        tracking_px=0.0,
        tracker_position_m=median("tracker_jitter_mm", lambda mm: mm * 1e-3),
        tracker_rotation_rad=median("tracker_jitter_deg", lambda deg: float(np.radians(deg))),
        shared_body=tuple(cid in on_body for cid in cameras),
    )


def body_pose_covariance(points: np.ndarray, point_index: np.ndarray, cameras: np.ndarray,
                         centres: np.ndarray, noise: NoiseModel) -> np.ndarray:
    """(N, 3, 3) m²: the rigid pose error of a shared tracker body for every point with a
    view (point_index (M,), cameras (M,)) from a camera on such a body (camera centres
    (C, 3) m); zero for the others."""
    out = np.zeros((len(points), 3, 3))
    shared = noise.on_shared_body(cameras)
    if shared.any():
        first = np.full(len(points), -1)
        first[point_index[shared][::-1]] = cameras[shared][::-1]
        has = first >= 0
        out[has] = noise.rigid_pose_covariance(points[has], centres[first[has]])
    return out
