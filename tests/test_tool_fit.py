"""tool_fit: the tools' translation recovered from dark shafts rendered where they really are
(a known hand-eye error), in a stereo pair."""

from __future__ import annotations

import numpy as np
from scenes import tool_pose_along

from surgrecon_cli.config import ToolConfig
from surgrecon_cli.core.geometry.cameras import CameraModel
from surgrecon_cli.core.geometry.tool import tool_pixel_mask
from surgrecon_cli.core.geometry.tool_fit import ShaftFit, fit_tool_offset

CAMERA = CameraModel(K=np.array([[300.0, 0, 160], [0, 300, 120], [0, 0, 1]]), dist=np.zeros(5),
                     width=320, height=240)
SHAFT = ToolConfig(shaft_radius_m=0.004, shaft_length_m=0.15, mask_margin_px=0.0)


def _shaft_pose(tip: np.ndarray, up: np.ndarray) -> np.ndarray:
    return tool_pose_along(tip, up, np.array([0.0, 0.0, 1.0]))


def _render(cam_to_world: np.ndarray, tools: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Bright textured tissue (grey 150-210) with the dark instruments (grey 40) on it."""
    v, u = np.mgrid[0:CAMERA.height, 0:CAMERA.width]
    image = 180 + 25 * np.sin(u / 7.0) * np.cos(v / 11.0) + rng.normal(0, 4, u.shape)
    pixels = np.stack([u.ravel(), v.ravel()], 1).astype(float)
    on_tool = tool_pixel_mask(pixels, CAMERA, cam_to_world, tools, [SHAFT] * len(tools))
    image.ravel()[on_tool] = 40 + rng.normal(0, 4, on_tool.sum())
    return image.astype(np.float32)


def test_the_fit_finds_where_both_shafts_really_are():
    rng = np.random.default_rng(7)
    cams = np.stack([np.eye(4), np.eye(4)])
    cams[1, 0, 3] = 0.05  # 5 cm stereo baseline
    kinematic = np.stack([_shaft_pose(np.array([-0.01, 0.01, 0.15]), np.array([-1.0, -1, -0.3])),
                          _shaft_pose(np.array([0.015, 0.0, 0.14]), np.array([1.0, -0.6, -0.4]))])
    error = np.array([0.006, -0.008, 0.005])  # m: the instruments are here, relative to it
    real = kinematic.copy()
    real[:, :3, 3] += error
    images = [_render(c, real, rng) for c in cams]
    fit = fit_tool_offset(images, [CAMERA, CAMERA], cams, kinematic, [SHAFT, SHAFT],
                          ShaftFit(radius_m=0.004, max_turn_deg=0.0))
    assert np.linalg.norm(fit.move[:3, 3] - error) < 0.002  # m
    np.testing.assert_allclose(fit.move[:3, :3], np.eye(3))
    assert fit.contrast > fit.contrast_at_zero + 100  # grey levels, summed over 2 x 2 shafts
