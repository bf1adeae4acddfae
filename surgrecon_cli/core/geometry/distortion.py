"""Lens distortion in normalised coordinates (x/z, y/z), OpenCV/ROS conventions.

Distortion models (ROS `sensor_msgs/CameraInfo.distortion_model` names, OpenCV order):

- `plumb_bob` (5 coefficients k1 k2 p1 p2 k3): OpenCV's standard model, `cv2.projectPoints`;
- `rational_polynomial` (8: k1 k2 p1 p2 k3 k4 k5 k6): radial term
  (1 + k1 r² + k2 r⁴ + k3 r⁶) / (1 + k4 r² + k5 r⁴ + k6 r⁶), same tangential terms;
- `equidistant` (4: k1 k2 k3 k4): OpenCV's fisheye model, `cv2.fisheye.projectPoints`:
  θ = atan r, θd = θ (1 + k1 θ² + k2 θ⁴ + k3 θ⁶ + k4 θ⁸), distorted point = (θd / r) (x, y).
  Points are handled in normalised coordinates (x/z, y/z), so rays at 90° or more from the
  optical axis (fields of view of 180° and wider) are not represented.
"""

from __future__ import annotations

import cv2
import numpy as np

from ...errors import GeometryError

DISTORTION_MODELS: dict[str, int] = {"plumb_bob": 5, "rational_polynomial": 8, "equidistant": 4}
"""Supported distortion models -> number of coefficients."""

_UNDISTORT_ITERATIONS = 20
_UNDISTORT_TOL = 1e-13  # normalised units (1e-10 px at f = 1000 px)


def distortion_model_name(name: str, coefficients: np.ndarray) -> str:
    """The supported model a CameraInfo's `distortion_model` names (case and surrounding
    blanks ignored). An empty name is plumb_bob; an unknown one is accepted as plumb_bob only
    when every coefficient is zero (no distortion). GeometryError otherwise."""
    key = str(name).strip().lower()
    if key in DISTORTION_MODELS:
        return key
    if not key or not np.any(np.asarray(coefficients, float) != 0):
        return "plumb_bob"
    raise GeometryError(f"distortion model {name!r} is not supported; supported: "
                        f"{', '.join(DISTORTION_MODELS)}")


def reduce_intrinsics(
    K: np.ndarray, width: int, height: int, binning_x: int = 0, binning_y: int = 0,
    roi: tuple[int, int, int, int, bool] = (0, 0, 0, 0, False),
) -> tuple[np.ndarray, int, int]:
    """Full-resolution K (3, 3) px and size -> (K, width, height) of the binned ROI image;
    rules in `CameraModel.from_camera_info`."""
    bx, by = int(binning_x) or 1, int(binning_y) or 1
    x0, y0, rw, rh = (int(v) for v in roi[:4])
    if min(bx, by, x0, y0, rw, rh) < 0:
        raise GeometryError(f"invalid binning {bx}x{by} or ROI {tuple(roi[:4])}")
    if (x0, y0, rw, rh) == (0, 0, 0, 0):
        rw, rh = width, height
    if rw <= 0 or rh <= 0 or x0 + rw > width or y0 + rh > height:
        raise GeometryError(f"ROI x_offset={x0} y_offset={y0} width={rw} height={rh} is not "
                            f"inside the {width}x{height} px image")
    Kr = np.array(K, float).reshape(3, 3)
    Kr[0, 2] -= x0
    Kr[1, 2] -= y0
    Kr[0, :] /= bx
    Kr[1, :] /= by
    return Kr, rw // bx, rh // by


def _coefficients(dist: np.ndarray, model: str) -> np.ndarray:
    """Coefficients padded to the model's count ((8,) for plumb_bob/rational, (4,) fisheye)."""
    n = 4 if model == "equidistant" else 8
    out = np.zeros(n)
    d = np.asarray(dist, float).ravel()[:n]
    out[: d.size] = d
    return out


def _rational_terms(xy: np.ndarray, c: np.ndarray):
    """Radial factor s (N,) and ds/dr² (N,) of plumb_bob / rational_polynomial."""
    k1, k2, _p1, _p2, k3, k4, k5, k6 = c
    r2 = xy[:, 0] ** 2 + xy[:, 1] ** 2
    a = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    b = 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
    da = k1 + r2 * (2 * k2 + 3 * k3 * r2)
    db = k4 + r2 * (2 * k5 + 3 * k6 * r2)
    return a / b, (da * b - a * db) / (b * b), r2


def _fisheye_terms(xy: np.ndarray, c: np.ndarray):
    """Scale g = θd / r (N,) and (dg/dr) / r (N,) of the equidistant model, r = |xy|."""
    k1, k2, k3, k4 = c
    r = np.hypot(xy[:, 0], xy[:, 1])
    theta = np.arctan(r)
    t2 = theta * theta
    theta_d = theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
    dtheta_d = 1 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))
    small = r < 1e-8
    rs = np.where(small, 1.0, r)
    g = np.where(small, 1.0, theta_d / rs)
    # dg/dr = (θd'(θ) r / (1 + r²) - θd) / r²; its limit over r at r -> 0 is 2 (k1 - 1/3).
    dg_r = np.where(small, 2 * (k1 - 1.0 / 3.0),
                    (dtheta_d * rs / (1 + rs * rs) - theta_d) / rs**3)
    return g, dg_r


def distort_normalized(xy: np.ndarray, dist: np.ndarray, model: str = "plumb_bob") -> np.ndarray:
    """Undistorted normalised coordinates (N, 2) -> distorted ones (N, 2) under `model`
    with coefficients `dist` (see the module docstring)."""
    xy = np.asarray(xy, float)
    c = _coefficients(dist, model)
    x, y = xy[:, 0], xy[:, 1]
    if model == "equidistant":
        g, _ = _fisheye_terms(xy, c)
        return xy * g[:, None]
    p1, p2 = c[2], c[3]
    s, _, r2 = _rational_terms(xy, c)
    xd = x * s + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * s + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([xd, yd], axis=1)


def distortion_jacobian(xy: np.ndarray, dist: np.ndarray, model: str = "plumb_bob") -> np.ndarray:
    """∂ distorted / ∂ undistorted normalised coordinates (N, 2, 2) at xy (N, 2), analytic."""
    xy = np.asarray(xy, float)
    c = _coefficients(dist, model)
    x, y = xy[:, 0], xy[:, 1]
    J = np.empty((len(xy), 2, 2))
    if model == "equidistant":
        g, dg_r = _fisheye_terms(xy, c)
        J[:, 0, 0] = g + dg_r * x * x
        J[:, 1, 1] = g + dg_r * y * y
        J[:, 0, 1] = J[:, 1, 0] = dg_r * x * y
        return J
    p1, p2 = c[2], c[3]
    s, ds, _ = _rational_terms(xy, c)
    J[:, 0, 0] = s + 2 * x * x * ds + 2 * p1 * y + 6 * p2 * x
    J[:, 1, 1] = s + 2 * y * y * ds + 6 * p1 * y + 2 * p2 * x
    J[:, 0, 1] = J[:, 1, 0] = 2 * x * y * ds + 2 * p1 * x + 2 * p2 * y
    return J


def undistort_normalized(xy_d: np.ndarray, dist: np.ndarray, model: str = "plumb_bob",
                         polish: bool = True) -> np.ndarray:
    """Distorted normalised coordinates (N, 2) -> undistorted ones (N, 2), the inverse of
    `distort_normalized` to ~1e-14 inside the calibrated field of view.

    plumb_bob / rational_polynomial: OpenCV's fixed-point `cv2.undistortPointsIter`, then
    (`polish`) Newton steps with `distortion_jacobian`, each kept only where it lowers the
    residual (beyond the fold-over radius of a strong distortion, the best estimate, as
    OpenCV); without the polish, OpenCV's iteration alone (~1e-9 px on the simulated
    lenses: enough wherever pixel accuracy is, e.g. the tool mask).
    equidistant: Newton on θ of θd(θ) = |xy_d|, as `cv2.fisheye.undistortPoints`; NaN where
    it does not converge or θ >= 90° (no ray in front of the camera)."""
    xy_d = np.asarray(xy_d, float).reshape(-1, 2)
    if len(xy_d) == 0:
        return np.zeros((0, 2))
    c = _coefficients(dist, model)
    if model == "equidistant":
        return _undistort_fisheye(xy_d, c)
    finite = np.isfinite(xy_d).all(1)
    xy = np.full_like(xy_d, np.nan)
    if finite.any():
        pts = np.ascontiguousarray(xy_d[finite]).reshape(-1, 1, 2)
        start = cv2.undistortPointsIter(  # type: ignore[call-overload]  # cv2 stub: R, P take None
            pts, np.eye(3), c, None, None,
            (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-12)).reshape(-1, 2)
        xy[finite] = start
    if not polish:
        return xy
    err = np.linalg.norm(distort_normalized(xy, c, model) - xy_d, axis=1)
    for _ in range(_UNDISTORT_ITERATIONS):
        active = err > _UNDISTORT_TOL
        if not active.any():
            break
        J = distortion_jacobian(xy[active], c, model)
        r = distort_normalized(xy[active], c, model) - xy_d[active]
        det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
        ok = np.abs(det) > 1e-12
        safe = np.where(ok, det, 1.0)
        step = np.stack([J[:, 1, 1] * r[:, 0] - J[:, 0, 1] * r[:, 1],
                         J[:, 0, 0] * r[:, 1] - J[:, 1, 0] * r[:, 0]], 1) / safe[:, None]
        cand = xy[active] - np.where(ok[:, None], step, 0.0)
        cand_err = np.linalg.norm(distort_normalized(cand, c, model) - xy_d[active], axis=1)
        better = cand_err < err[active]
        idx = np.flatnonzero(active)[better]
        xy[idx], err[idx] = cand[better], cand_err[better]
        if not better.any():
            break
    return xy


def _undistort_fisheye(xy_d: np.ndarray, c: np.ndarray) -> np.ndarray:
    k1, k2, k3, k4 = c
    theta_d = np.hypot(xy_d[:, 0], xy_d[:, 1])
    theta = theta_d.copy()
    for _ in range(_UNDISTORT_ITERATIONS):
        t2 = theta * theta
        f = theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))) - theta_d
        df = 1 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))
        step = f / np.where(np.abs(df) > 1e-12, df, np.nan)
        theta = theta - step
        if np.all(~(np.abs(step) > _UNDISTORT_TOL)):
            break
    t2 = theta * theta
    residual = theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))) - theta_d
    small = theta_d < 1e-12
    scale = np.where(small, 1.0, np.tan(theta) / np.where(small, 1.0, theta_d))
    bad = ~((np.abs(residual) <= 1e-10 * (1 + theta_d)) & (theta >= 0) & (theta < np.pi / 2))
    scale[bad] = np.nan
    return xy_d * scale[:, None]
