"""Camera models: plumb_bob, rational_polynomial and equidistant (fisheye) distortion agree
with OpenCV, undistortion inverts projection, analytic Jacobians agree with finite
differences (and make core/noise/model.py's covariances right for every model), and models
serialise (older dicts without a model load as plumb_bob)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from surgrecon_cli.core.geometry.cameras import (
    CameraModel,
    pixel_rays,
    project,
    projection_jacobian,
    undistort_pixels,
    view_distortion_jacobians,
)
from surgrecon_cli.core.geometry.distortion import (
    distort_normalized,
    distortion_jacobian,
    undistort_normalized,
)
from surgrecon_cli.core.geometry.poses import invert_pose, make_pose
from surgrecon_cli.core.geometry.triangulate import Observations, triangulate
from surgrecon_cli.core.noise.model import covariance_sigma, point_covariances, projection_jacobians
from surgrecon_cli.errors import GeometryError

K = np.array([[612.0, 0, 322.4], [0, 606.5, 238.9], [0, 0, 1]])
DIST = {
    "plumb_bob": np.array([-0.28, 0.09, 9e-4, -6e-4, -0.012]),
    "rational_polynomial": np.array([0.42, -0.18, 9e-4, -6e-4, 0.04, 0.71, -0.09, 0.07]),
    "equidistant": np.array([-0.025, 0.011, -0.0035, 4e-4]),
}
# Half-angle of the field of view sampled: the polynomial models are only valid (monotonic)
# inside their calibrated field, a fisheye much wider.
HALF_FOV_DEG = {"plumb_bob": 40.0, "rational_polynomial": 45.0, "equidistant": 75.0}
MODELS = tuple(DIST)


def camera(model: str) -> CameraModel:
    return CameraModel(K, DIST[model], 640, 480, model)


def pose() -> np.ndarray:
    q = np.array([0.05, -0.12, 0.03, 1.0])
    return make_pose(np.array([0.02, -0.01, 0.05]), q / np.linalg.norm(q))


def points_in_view(model: str, n: int = 3000, seed: int = 0) -> np.ndarray:
    """World points (n, 3) m spread over the model's field of view, 2 to 30 cm away."""
    rng = np.random.default_rng(seed)
    theta = np.radians(HALF_FOV_DEG[model]) * np.sqrt(rng.uniform(0, 1, n))
    phi = rng.uniform(0, 2 * np.pi, n)
    rays = np.column_stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi),
                            np.cos(theta)])
    pc = rays * rng.uniform(0.02, 0.3, (n, 1))
    T = pose()
    return pc @ T[:3, :3].T + T[:3, 3]


def opencv_projection(points: np.ndarray, model: str) -> np.ndarray:
    T = invert_pose(pose())
    rvec = cv2.Rodrigues(T[:3, :3])[0]
    tvec = T[:3, 3].copy()
    if model == "equidistant":
        uv, _ = cv2.fisheye.projectPoints(points.reshape(-1, 1, 3), rvec, tvec, K, DIST[model])
    else:
        uv, _ = cv2.projectPoints(points, rvec, tvec, K, DIST[model])
    return uv.reshape(-1, 2)


@pytest.mark.parametrize("model", MODELS)
def test_projection_matches_opencv(model: str):
    points = points_in_view(model)
    uv, z = project(points, pose(), camera(model))
    err = np.abs(uv - opencv_projection(points, model)).max()
    assert err < 1e-6  # px; measured ~4e-13
    assert (z > 0).all()


@pytest.mark.parametrize("model", MODELS)
def test_undistort_inverts_project(model: str):
    cam = camera(model)
    points = points_in_view(model, seed=1)
    uv, _ = project(points, pose(), cam)
    xy = undistort_pixels(uv, cam)
    pc = (points - pose()[:3, 3]) @ pose()[:3, :3]
    np.testing.assert_allclose(xy, pc[:, :2] / pc[:, 2:], rtol=0, atol=1e-10)
    # ... and back to the same pixels
    back = distort_normalized(xy, cam.dist, model) @ K[:2, :2].T + K[:2, 2]
    assert np.abs(back - uv).max() < 1e-6
    # rays through the pixels pass through the points
    origin, d = pixel_rays(uv, cam, pose())
    v = points - origin
    miss = np.linalg.norm(v - (v * d).sum(1, keepdims=True) * d, axis=1)
    assert miss.max() < 1e-10  # m


@pytest.mark.parametrize("model", MODELS)
def test_projection_jacobian_matches_finite_differences(model: str):
    cam = camera(model)
    points = points_in_view(model, n=500, seed=2)
    J, z = projection_jacobian(points, pose(), cam)
    np.testing.assert_array_equal(z, project(points, pose(), cam)[1])
    h = 1e-7  # m
    numeric = np.stack([(project(points + h * e, pose(), cam)[0]
                         - project(points - h * e, pose(), cam)[0]) / (2 * h)
                        for e in np.eye(3)], axis=-1)
    rel = np.abs(J - numeric).max() / np.abs(numeric).max()
    assert rel < 1e-6  # measured ~1e-10
    J0, _ = projection_jacobian(points, pose(), cam, distort=False)
    numeric0 = np.stack([(project(points + h * e, pose(), cam, distort=False)[0]
                          - project(points - h * e, pose(), cam, distort=False)[0]) / (2 * h)
                         for e in np.eye(3)], axis=-1)
    assert np.abs(J0 - numeric0).max() / np.abs(numeric0).max() < 1e-6


@pytest.mark.parametrize("model", MODELS)
def test_distortion_jacobian_matches_finite_differences(model: str):
    rng = np.random.default_rng(4)
    r = np.tan(np.radians(HALF_FOV_DEG[model])) * np.sqrt(rng.uniform(0, 1, 800))
    phi = rng.uniform(0, 2 * np.pi, 800)
    xy = np.column_stack([r * np.cos(phi), r * np.sin(phi)])
    xy[:3] = [[0.0, 0.0], [1e-9, 0.0], [0.0, -3e-7]]  # at and next to the axis
    J = distortion_jacobian(xy, DIST[model], model)
    h = 1e-6
    numeric = np.stack([(distort_normalized(xy + h * e, DIST[model], model)
                         - distort_normalized(xy - h * e, DIST[model], model)) / (2 * h)
                        for e in np.eye(2)], axis=-1)
    assert np.abs(J - numeric).max() < 1e-7


def test_fisheye_undistortion_beyond_90_degrees_is_nan():
    xy_d = np.array([[0.5, 0.0], [2.5, 0.0]])  # θd = 2.5 rad needs θ > 90°
    out = undistort_normalized(xy_d, np.zeros(4), "equidistant")
    np.testing.assert_allclose(out[0], [np.tan(0.5), 0.0])
    assert np.isnan(out[1]).all()


@pytest.mark.parametrize("model", MODELS)
def test_dict_round_trip(model: str):
    cam = camera(model)
    back = CameraModel.from_dict(cam.to_dict())
    assert back.model == model and back.same_as(cam)
    points = points_in_view(model, n=50)
    np.testing.assert_array_equal(project(points, pose(), back)[0],
                                  project(points, pose(), cam)[0])


def test_old_dicts_without_model_are_plumb_bob():
    old = {"K": K.tolist(), "dist": DIST["plumb_bob"].tolist(), "width": 640, "height": 480}
    cam = CameraModel.from_dict(old)
    assert cam.model == "plumb_bob" and cam.same_as(camera("plumb_bob"))
    assert cam.to_dict() == {**old, "model": "plumb_bob"}


def test_coefficient_counts():
    assert CameraModel(K, [0.1, 0.01], 640, 480, "rational_polynomial").dist.shape == (8,)
    assert CameraModel(K, np.zeros(8), 640, 480).dist.shape == (5,)  # trailing zeros dropped
    with pytest.raises(GeometryError, match="equidistant distortion has 4 coefficients"):
        CameraModel(K, DIST["plumb_bob"], 640, 480, "equidistant")
    with pytest.raises(GeometryError, match="plumb_bob distortion has 5 coefficients"):
        CameraModel(K, DIST["rational_polynomial"], 640, 480)
    with pytest.raises(GeometryError, match="'fov' is not supported"):
        CameraModel(K, np.zeros(5), 640, 480, "fov")
    assert not camera("plumb_bob").same_as(CameraModel(K, np.zeros(8), 640, 480,
                                                       "rational_polynomial"))


def _stereo_far_off_axis(model: str, dist: list[float], n: int = 3000, sigma_px: float = 0.5):
    """Two cameras 20 mm apart (f = 220 px) seeing points 50-60° off their axis, 50 mm away,
    through noisy pixels: (models, poses, points, observations, triangulation)."""
    rng = np.random.default_rng(4)
    Kw = np.array([[220.0, 0, 320], [0, 220.0, 240], [0, 0, 1]])
    models = [CameraModel(Kw, np.array(dist), 640, 480, model) for _ in range(2)]
    poses = np.stack([make_pose(np.array([x, 0.0, 0.0]), np.array([0.0, 0, 0, 1]))
                      for x in (-0.01, 0.01)])
    side = rng.choice([-1.0, 1.0], n)
    points = np.column_stack([rng.uniform(0.06, 0.085, n) * side, rng.uniform(-0.02, 0.02, n),
                              np.full(n, 0.05)])
    rows = np.tile(np.arange(n), 2)
    cams = np.repeat([0, 1], n)
    px = np.concatenate([project(points, poses[c], models[c])[0] for c in (0, 1)])
    px += rng.normal(0, sigma_px, px.shape)
    normalized = np.concatenate([undistort_pixels(px[cams == c], models[c]) for c in (0, 1)])
    obs = Observations(rows, cams, px, normalized, np.zeros((2 * n, 3), np.uint8))
    return models, poses, points, obs, triangulate(obs, poses, models, n)


@pytest.mark.parametrize(("model", "dist"), [("equidistant", [0.05, -0.01, 0.002, 0.0]),
                                             ("plumb_bob", [-0.12, 0.03, 0, 0, 0])])
def test_noise_jacobians_with_distortion_predict_triangulation_error(model, dist):
    """core/noise/model.py's Jacobians times the lens distortion's Jacobian are pixel Jacobians:
    the covariance they give matches the RMS error of noisy triangulations. Without it (the
    pinhole Jacobian) the prediction is 0.36x the error for this fisheye, 0.94x plumb_bob."""
    models, poses, points, obs, tri = _stereo_far_off_axis(model, dist)
    focal = np.full(len(obs.point), 220.0)
    at = tri.points[obs.point]
    D = view_distortion_jacobians(at, obs.camera, poses, models)
    J, _ = projection_jacobians(at, poses[obs.camera], focal, D)
    np.testing.assert_allclose(J, np.concatenate([projection_jacobian(
        at[obs.camera == c], poses[c], models[c])[0] for c in (0, 1)]), rtol=1e-12, atol=1e-9)
    cov = point_covariances(obs.point, J, np.full(len(obs.point), 0.25), len(points))
    predicted = np.sqrt(np.mean(covariance_sigma(cov) ** 2))
    measured = np.sqrt(np.mean(np.sum((tri.points - points) ** 2, axis=1)))
    assert abs(predicted / measured - 1) < 0.1
