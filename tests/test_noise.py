"""The run's noise model recovers known pixel and tracker noise (core/noise/model.py)."""

from __future__ import annotations

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from surgrecon_cli.core.geometry.cameras import CameraModel, project, undistort_pixels
from surgrecon_cli.core.geometry.poses import make_pose
from surgrecon_cli.core.geometry.triangulate import (
    Observations,
    reprojection_residuals,
    triangulate,
)
from surgrecon_cli.core.noise.frame_noise import (
    tracked_observations,
    tracking_excess_px2,
    triangulate_found,
)
from surgrecon_cli.core.noise.model import (
    NoiseModel,
    covariance_sigma,
    image_noise_sigma,
    localisation_noise_px,
    localisation_variance_px2,
    pixel_noise_from_residuals,
    point_covariances,
    pose_jitter,
    projection_jacobians,
)


def _rig(n_cams: int = 4):
    """Cameras on a ring 55 mm above a patch of points, looking at its centre."""
    K = np.array([[450.0, 0, 320], [0, 450.0, 240], [0, 0, 1]])
    models = [CameraModel(K, np.zeros(5), 640, 480) for _ in range(n_cams)]
    poses = []
    for a in np.linspace(0, 2 * np.pi, n_cams, endpoint=False):
        c = np.array([0.03 * np.cos(a), 0.03 * np.sin(a), 0.055])
        z = -c / np.linalg.norm(c)
        x = np.cross(z, [0.0, 0.0, 1.0])
        x /= np.linalg.norm(x)
        R = np.column_stack([x, np.cross(z, x), z])
        poses.append(make_pose(c, Rotation.from_matrix(R).as_quat()))
    return models, np.stack(poses)


def _observe(points, models, poses, sigma_px, rng):
    rows, cams, px = [], [], []
    for c, (model, pose) in enumerate(zip(models, poses, strict=True)):
        uv, _ = project(points, pose, model)
        rows.append(np.arange(len(points)))
        cams.append(np.full(len(points), c))
        px.append(uv + rng.normal(0, sigma_px, uv.shape))
    rows, cams, px = np.concatenate(rows), np.concatenate(cams), np.concatenate(px)
    normalized = np.zeros_like(px)
    for c in range(len(models)):
        normalized[cams == c] = undistort_pixels(px[cams == c], models[c])
    return Observations(rows, cams, px, normalized, np.zeros((len(rows), 3), np.uint8))


def test_pixel_noise_recovered_within_20_percent():
    rng = np.random.default_rng(3)
    points = np.column_stack([rng.uniform(-0.01, 0.01, (800, 2)), rng.uniform(-0.002, 0.002, 800)])
    models, poses = _rig()
    for sigma in (0.3, 1.0):
        obs = _observe(points, models, poses, sigma, rng)
        tri = triangulate(obs, poses, models, len(points))
        residual, _ = reprojection_residuals(tri.points, obs, poses, models)
        estimate = pixel_noise_from_residuals(residual, obs.point)
        assert abs(estimate - sigma) <= 0.2 * sigma, (sigma, estimate)


def test_pixel_noise_of_two_views_counts_one_dof():
    """Two views leave one dof per point (the residual across the epipolar line, none along
    it): σ is still recovered, where pooling the four components would shrink it ~4x."""
    rng = np.random.default_rng(6)
    points = np.column_stack([rng.uniform(-0.01, 0.01, (1500, 2)), np.zeros(1500)])
    models, poses = _rig(2)
    obs = _observe(points, models, poses, 0.4, rng)
    tri = triangulate(obs, poses, models, len(points))
    residual, _ = reprojection_residuals(tri.points, obs, poses, models)
    assert abs(pixel_noise_from_residuals(residual, obs.point) - 0.4) <= 0.1 * 0.4


def test_calibration_offset_is_split_from_the_localisation_noise():
    """A stereo pair whose calibration is off: every view of camera 1 lies 0.3 px off where
    the cameras' geometry puts it, on top of 0.15 px of localisation noise. The raw residuals
    read the offset as noise; with each camera's median taken out, the localisation σ is
    recovered, and the two cameras' offsets differ by the offset's part across the epipolar
    line (the part along it moves the depth, not the residual)."""
    rng = np.random.default_rng(8)
    points = np.column_stack([rng.uniform(-0.01, 0.01, (1500, 2)), np.zeros(1500)])
    models, poses = _rig(2)
    obs = _observe(points, models, poses, 0.15, rng)
    offset = np.array([0.3, 0.0])
    obs.pixels[obs.camera == 1] += offset
    tri = triangulate(obs, poses, models, len(points))
    residual, _ = reprojection_residuals(tri.points, obs, poses, models)
    localisation, offsets = localisation_noise_px(residual, obs.point, obs.camera, 2)
    assert abs(localisation - 0.15) <= 0.15 * 0.15
    assert pixel_noise_from_residuals(residual, obs.point) >= 1.5 * 0.15
    # The epipolar line of the patch centre in camera 1: the images of two points on camera
    # 0's ray through it.
    ray = np.array([[0.0, 0.0, 0.0]]) - poses[0, :3, 3]
    ends = poses[0, :3, 3] + np.array([[0.8], [1.2]]) * ray
    uv, _ = project(ends, poses[1], models[1])
    along = (uv[1] - uv[0]) / np.linalg.norm(uv[1] - uv[0])
    across = abs(offset @ np.array([-along[1], along[0]]))
    assert abs(np.linalg.norm(offsets[0] - offsets[1]) - across) <= 0.05


def test_covariance_predicts_triangulation_error():
    """√trace Σ from the Jacobians matches the RMS 3D error of noisy triangulations."""
    rng = np.random.default_rng(4)
    points = np.column_stack([rng.uniform(-0.01, 0.01, (1500, 2)), np.zeros(1500)])
    models, poses = _rig(2)
    obs = _observe(points, models, poses, 0.5, rng)
    tri = triangulate(obs, poses, models, len(points))
    focal = np.array([m.K[0, 0] for m in models])
    J, _ = projection_jacobians(tri.points[obs.point], poses[obs.camera], focal[obs.camera])
    cov = point_covariances(obs.point, J, np.full(len(obs.point), 0.25), len(points))
    predicted = np.sqrt(np.mean(covariance_sigma(cov) ** 2))
    measured = np.sqrt(np.mean(np.sum((tri.points - points) ** 2, axis=1)))
    assert abs(predicted - measured) <= 0.15 * measured


def test_tracker_jitter_recovered_within_20_percent():
    """A smooth 40 Hz camera trajectory with known per-axis noise, uneven sampling."""
    rng = np.random.default_rng(5)
    t = np.cumsum(rng.uniform(0.02, 0.03, 600))
    truth = np.column_stack([0.003 * np.sin(2 * np.pi * 0.2 * t), 0.002 * np.cos(0.7 * t),
                             0.05 + 0.001 * t])
    rot_truth = Rotation.from_rotvec(np.column_stack([0.05 * np.sin(0.5 * t), 0.1 * t,
                                                      np.zeros_like(t)]))
    for sigma_pos, sigma_deg in ((0.1e-3 / np.sqrt(3), 0.05 / np.sqrt(3)), (0.25e-3, 0.1)):
        positions = truth + rng.normal(0, sigma_pos, truth.shape)
        noise = Rotation.from_rotvec(rng.normal(0, np.radians(sigma_deg), (len(t), 3)))
        quats = (noise * rot_truth).as_quat()
        pos, rot = pose_jitter((t * 1e9).astype(np.int64), positions, quats)
        assert abs(pos - sigma_pos) <= 0.2 * sigma_pos, (pos, sigma_pos)
        assert abs(np.degrees(rot) - sigma_deg) <= 0.2 * sigma_deg, (np.degrees(rot), sigma_deg)


def test_fixed_pose_stream_has_no_jitter():
    stamps = np.arange(10) * 25_000_000
    pos, rot = pose_jitter(stamps, np.tile([0.0, 0.0, 0.05], (10, 1)),
                           np.tile([0.0, 0.0, 0.0, 1.0], (10, 1)))
    assert pos == 0 and rot == 0


def test_cameras_on_one_tracked_body_are_found():
    """A stereo head's two cameras follow one marker: their relative pose does not jitter;
    a third, separately tracked camera's does."""
    from surgrecon_cli.core.noise.model import shared_bodies

    rng = np.random.default_rng(6)
    t = np.arange(400) * 0.025
    stamps = (t * 1e9).astype(np.int64)
    truth = np.column_stack([0.003 * np.sin(t), 0.002 * np.cos(0.7 * t), 0.05 + 0 * t])
    head = truth + rng.normal(0, 6e-5, truth.shape)  # one marker measurement for both
    own, rel = [], {}
    streams = [head, head + np.array([0.005, 0, 0]), truth + rng.normal(0, 6e-5, truth.shape)]
    noisy_quats = Rotation.from_rotvec(rng.normal(0, 5e-4, (len(t), 3))).as_quat()
    rotations = [noisy_quats, noisy_quats, Rotation.from_rotvec(
        rng.normal(0, 5e-4, (len(t), 3))).as_quat()]
    for positions, q in zip(streams, rotations, strict=True):
        own.append(pose_jitter(stamps, positions, q))
    for i in range(3):
        for j in range(i + 1, 3):
            ri, rj = Rotation.from_quat(rotations[i]), Rotation.from_quat(rotations[j])
            rel_pos = ri.inv().apply(streams[j] - streams[i])
            rel[(i, j)] = pose_jitter(stamps, rel_pos, (ri.inv() * rj).as_quat())
    assert shared_bodies(own, rel) == [[0, 1]]


def test_frame_tracking_excess_measures_the_error_beyond_the_model():
    """Tracked pixels with 0.4 px of error while the model says 0.1 px (pixel noise, a
    tracking bound of 0): the frame's re-triangulated residuals give the 0.4 px back and the
    excess variance is what the model lacks; a right model gets (nearly) none."""
    rng = np.random.default_rng(7)
    points = np.column_stack([rng.uniform(-0.01, 0.01, (1200, 2)), np.zeros(1200)])
    models, poses = _rig(2)
    obs = _observe(points, models, poses, 0.4, rng)
    pixels = np.full((len(points), 2, 2), np.nan)
    pixels[obs.point, obs.camera] = obs.pixels
    found = np.isfinite(pixels).all(2)
    zero = np.zeros(found.shape)
    multi = triangulate_found(found, pixels, models, poses)
    for model_px, expected in ((0.1, 0.4**2 - 0.1**2), (0.4, 0.0)):
        noise = NoiseModel(pixel_px=model_px, tracking_px=0.0, tracker_position_m=0.0,
                           tracker_rotation_rad=0.0)
        excess, measured = tracking_excess_px2(multi, zero, models, noise)
        assert abs(measured - 0.4) <= 0.05, measured
        assert abs(excess - expected) <= 0.03, (model_px, excess)


def test_one_triangulation_serves_any_subset_of_points():
    """The frame's points are triangulated once (`triangulate_found`, distorted lenses, 2-4
    views a point, some points seen once): the part of it for a subset of the points is what
    triangulating that subset's views alone gives, and near the true points."""
    rng = np.random.default_rng(11)
    points = np.column_stack([rng.uniform(-0.01, 0.01, (300, 2)), rng.uniform(-0.002, 0.002, 300)])
    models, poses = _rig(4)
    models = [CameraModel(m.K, np.array([-0.2, 0.05, 0.001, -0.001, 0.0]), m.width, m.height)
              for m in models]
    obs = _observe(points, models, poses, 0.3, rng)
    pixels = np.full((len(points), 4, 2), np.nan)
    pixels[obs.point, obs.camera] = obs.pixels
    found = rng.uniform(size=(len(points), 4)) < 0.6
    pixels[~found] = np.nan
    multi = triangulate_found(found, pixels, models, poses)
    assert np.array_equal(multi.idx, np.flatnonzero(found.sum(1) >= 2))
    rows = multi.idx[rng.uniform(size=len(multi.idx)) < 0.4]
    sub_obs, sub_tri = multi.of_rows(rows)
    alone = triangulate_found(found[rows], pixels[rows], models, poses)
    np.testing.assert_array_equal(sub_obs.point, alone.obs.point)
    np.testing.assert_array_equal(sub_obs.camera, alone.obs.camera)
    np.testing.assert_allclose(sub_tri.points, alone.tri.points, rtol=0, atol=1e-12)
    np.testing.assert_allclose(sub_tri.error_px, alone.tri.error_px, rtol=0, atol=1e-9)
    np.testing.assert_allclose(sub_tri.residual_px, alone.tri.residual_px, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(sub_tri.in_front, alone.tri.in_front)
    assert np.median(np.linalg.norm(sub_tri.points - points[rows], axis=1)) < 1e-4
    use = found[rows] & (rng.uniform(size=(len(rows), 4)) < 0.8)
    views = multi.views_of(rows, use)
    again = tracked_observations(use, pixels[rows], models)
    for field in ("point", "camera", "pixels", "normalized", "rgb"):
        np.testing.assert_array_equal(getattr(views, field), getattr(again, field))


def test_image_noise_sigma_recovers_known_noise_on_a_smooth_image():
    # a smooth shading plus Gaussian noise of sigma 3 grey levels, 8-bit and float: the
    # estimate is the noise, not the shading
    rng = np.random.default_rng(3)
    yy, xx = np.mgrid[0:512, 0:640]
    smooth = 90 + 0.05 * xx + 30 * np.sin(yy / 90.0)
    noisy = smooth + rng.normal(0, 3.0, smooth.shape)
    assert abs(image_noise_sigma(np.clip(np.round(noisy), 0, 255).astype(np.uint8)) - 3.0) < 0.25
    assert abs(image_noise_sigma(noisy.astype(np.float32)) - 3.0) < 0.15


def test_localisation_bound_at_the_image_border_reflects_the_image():
    # the Cramér-Rao bound of windows that reach over the border, against the same sums
    # on an explicitly reflected (numpy "reflect" = OpenCV's REFLECT_101) copy of the image
    rng = np.random.default_rng(4)
    g = cv2.GaussianBlur(rng.uniform(0, 255, (120, 160)).astype(np.float32), (0, 0), 1.5)
    window, sigma = 21, 2.0
    pixels = np.array([[0.0, 0.0], [159.0, 119.0], [3.2, 60.0], [80.0, 118.6], [80.0, 60.0],
                       [157.0, 2.0]])
    got = localisation_variance_px2(g, pixels, window, sigma)
    pad = window // 2 + 1
    padded = np.pad(g, pad, mode="reflect")
    gx = cv2.Sobel(padded, cv2.CV_64F, 1, 0, ksize=3, scale=1 / 8)
    gy = cv2.Sobel(padded, cv2.CV_64F, 0, 1, ksize=3, scale=1 / 8)
    half = window // 2
    for (u, v), value in zip(np.round(pixels).astype(int), got, strict=True):
        rows = slice(v + pad - half, v + pad + half + 1)
        cols = slice(u + pad - half, u + pad + half + 1)
        a = (gx[rows, cols] ** 2).sum()
        b = (gx[rows, cols] * gy[rows, cols]).sum()
        c = (gy[rows, cols] ** 2).sum()
        expected = sigma**2 * (a + c) / (a * c - b * b) / 2
        assert np.isclose(value, expected, rtol=1e-5)
