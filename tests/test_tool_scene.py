"""The Foxglove scene draws every tool as core/geometry/tool.py models it: the shaft and the
jaw/wrist capsule beyond the kinematic frame, each tool in its own frame (`tool`, `tool_1`, ...)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from surgrecon_cli.config import ToolConfig
from surgrecon_cli.core.geometry.cameras import CameraModel
from surgrecon_cli.io.export.foxglove_scene import frame_transforms, projected_labels, scene_update


def _matrix(p) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = Rotation.from_quat([p.orientation.x, p.orientation.y, p.orientation.z,
                                    p.orientation.w]).as_matrix()
    m[:3, 3] = [p.position.x, p.position.y, p.position.z]
    return m


def test_each_tool_is_drawn_with_its_jaw_where_its_pose_puts_it():
    # A dVRK-like second arm: frame z out of the jaws (shaft along -z), jaw 5-25 mm beyond.
    second = ToolConfig(shaft_radius_m=0.003, shaft_length_m=0.2, shaft_axis="-z",
                        jaw_offset_m=0.005, jaw_length_m=0.02, jaw_width_m=0.008)
    poses = np.stack([np.eye(4), np.eye(4)])
    poses[0, :3, 3] = [0.0, 0.0, 0.1]
    poses[1, :3, :3] = Rotation.from_euler("xyz", [30, -50, 10], degrees=True).as_matrix()
    poses[1, :3, 3] = [0.02, -0.01, 0.08]
    scene = scene_update(7, [], np.zeros(0, bool), [True, True], [ToolConfig(), second], 0.05)
    entities = {e.id: e for e in scene.entities}
    assert set(entities) == {"tool", "tool_1"}
    assert len(entities["tool"].cylinders) == 1  # no jaw configured: the shaft only
    arm = entities["tool_1"]
    assert arm.frame_id == "tool_1" and arm.frame_locked
    shaft, jaw = arm.cylinders
    # Ground truth from the config: the jaw's axis runs from 5 mm to 25 mm along -(shaft
    # axis) = +z of the frame, 8 mm wide; in the world the frame's pose carries it.
    tip, out = poses[1, :3, 3], poses[1, :3, 2]
    middle = poses[1] @ _matrix(jaw.pose)
    np.testing.assert_allclose(middle[:3, 3], tip + out * 0.015, atol=1e-12)
    assert abs(middle[:3, 2] @ out) == pytest.approx(1.0)  # the cylinder's z along the jaw
    assert (jaw.size.x, jaw.size.y, jaw.size.z) == pytest.approx((0.008, 0.008, 0.02))
    ends = [(poses[1] @ _matrix(s.pose))[:3, 3] for s in arm.spheres[2:]]
    np.testing.assert_allclose(ends, [tip + out * 0.005, tip + out * 0.025], atol=1e-12)
    assert arm.spheres[2].size.x == pytest.approx(0.008)
    np.testing.assert_allclose((poses[1] @ _matrix(shaft.pose))[:3, 3],
                               tip - out * (0.003 + 0.2) / 2, atol=1e-12)
    assert shaft.size.z == pytest.approx(0.2 - 0.003) and shaft.size.x == pytest.approx(0.006)
    frames = {t.child_frame_id: t for t in frame_transforms(7, np.zeros((0, 4, 4)),
                                                            poses).transforms}
    t = frames["tool_1"]
    np.testing.assert_allclose([t.translation.x, t.translation.y, t.translation.z], tip)
    unposed = scene_update(7, [], np.zeros(0, bool), [True, False], [ToolConfig(), second], 0.05)
    assert [e.id for e in unposed.entities] == ["tool"]


def test_points_behind_a_jaw_are_not_annotated():
    """A camera looking down -z at two points: the one behind the jaw of a tool (whose shaft
    is far aside) is hidden, the other not."""
    model = CameraModel(K=np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]]),
                        dist=np.zeros(5), width=640, height=480)
    cam = np.eye(4)
    cam[:3, :3] = np.diag([1.0, -1.0, -1.0])  # optical z along world -z
    cam[:3, 3] = [0.0, 0.0, 0.2]
    tool = ToolConfig(shaft_radius_m=0.002, shaft_axis="+x", jaw_length_m=0.03,
                      jaw_width_m=0.01)
    pose = np.eye(4)
    pose[:3, 3] = [0.03, 0.0, 0.1]  # shaft from x = 0.03 outwards, jaw back to x = 0
    points = np.array([[0.01, 0.0, 0.0], [-0.03, 0.0, 0.0]])
    _, labels = projected_labels(points, np.array([1, 2]), cam, model, pose, tool)
    assert labels.tolist() == [2]
    _, labels = projected_labels(points, np.array([1, 2]), cam, model)
    assert labels.tolist() == [1, 2]
