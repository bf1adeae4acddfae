"""Several tools, each with a shaft and a jaw/wrist part: `[[tools]]` poses are ingested,
and every tool is masked in the images and removed from the template."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import synth_log
from scenes import render_frames
from synth_log import MS, T0, SynthSpec

from surgrecon_cli.cli.main import main
from surgrecon_cli.config import Config, ToolConfig, load_config
from surgrecon_cli.core.geometry.poses import make_pose, point_to_segment_distance
from surgrecon_cli.core.geometry.tool import (
    camera_tool_poses,
    points_near_tool,
    tool_capsules,
    tool_pixel_mask,
)
from surgrecon_cli.core.template.build import TemplateFrame, build_template
from surgrecon_cli.errors import ConfigError
from surgrecon_cli.io.logs.records import PoseRecord
from surgrecon_cli.io.run.ingest_store import load_ingested
from surgrecon_cli.sim.scene import SimConfig

TIP_DOWN = make_pose(np.zeros(3), np.array([1.0, 0, 0, 0]))  # z (shaft) points down: -z world
JAW = ToolConfig(jaw_offset_m=0.002, jaw_length_m=0.01, jaw_width_m=0.006)


def test_the_jaw_beyond_the_frame_is_part_of_the_tool():
    # The shaft runs along the frame's z (here world -z); the jaw the other way (world +z),
    # from 2 mm to 12 mm, 3 mm in radius.
    on_jaw = np.array([[0, 0, 0.005], [0, 0, 0.011], [0.002, 0, 0.008]])
    past_jaw = np.array([[0, 0, 0.018], [0.008, 0, 0.008]])
    assert not points_near_tool(on_jaw, TIP_DOWN, ToolConfig()).any()
    assert points_near_tool(on_jaw, TIP_DOWN, JAW).all()
    assert not points_near_tool(past_jaw, TIP_DOWN, JAW).any()
    # The frame's z pointing out of the jaws: shaft_axis = "-z" swaps the two sides.
    flipped = replace(JAW, shaft_axis="-z")
    assert points_near_tool(np.array([[0, 0, 0.05]]), TIP_DOWN, flipped).all()
    assert not points_near_tool(np.array([[0, 0, 0.05]]), TIP_DOWN, JAW).any()


def test_every_tool_is_masked_and_removed():
    second = make_pose(np.array([0.02, 0, 0]), np.array([1.0, 0, 0, 0]))
    both = np.stack([TIP_DOWN, second])
    near_second = np.array([[0.02, 0, -0.03]])
    assert not points_near_tool(near_second, TIP_DOWN, ToolConfig()).any()
    assert points_near_tool(near_second, both, (ToolConfig(), JAW)).all()
    unknown = np.stack([TIP_DOWN, np.full((4, 4), np.nan)])  # a tool not seen at this frame
    assert len(tool_capsules(unknown, (ToolConfig(), JAW))) == 1
    # A camera 10 cm above, looking down: the pixel of the second tool's axis is masked.
    camera_pose = make_pose(np.array([0.0, 0, 0.1]), np.array([1.0, 0, 0, 0]))
    from surgrecon_cli.core.geometry.cameras import CameraModel, project
    model = CameraModel(np.array([[400.0, 0, 160], [0, 400.0, 120], [0, 0, 1]]), np.zeros(5),
                        320, 240)
    px, _ = project(np.array([[0.02, 0, 0.0]]), camera_pose, model)
    assert not tool_pixel_mask(px, model, camera_pose, TIP_DOWN, ToolConfig()).any()
    assert tool_pixel_mask(px, model, camera_pose, both, (ToolConfig(), JAW)).all()


def test_tools_tables_are_read_checked_and_written(tmp_path: Path):
    path = tmp_path / "dvrk.toml"
    path.write_text('[topics]\ntool_pose = "/PSM1/measured_cp"\n[[tools]]\n'
                    'pose = "/PSM2/measured_cp"\nshaft_radius_m = 0.003\njaw_length_m = 0.01\n')
    config = load_config(path)
    assert [t.pose for t in config.tools] == ["/PSM2/measured_cp"]
    assert config.tool_configs()[1].shaft_radius_m == 0.003
    path.write_text('[[tools]]\nshaft_radius_m = 0.003\n')
    with pytest.raises(ConfigError, match=r"tools\.pose"):
        load_config(path)
    path.write_text('[[tools]]\npose = "/a"\nshaft_radius = 0.003\n')
    with pytest.raises(ConfigError, match=r"tools\[0\].shaft_radius"):
        load_config(path)


def _second_arm(spec: SynthSpec, topic: str = "/PSM2/measured_cp") -> list:
    return [(topic, t + MS, PoseRecord(t, "world", "", np.array([0.01 * k, 0.0, 0.02]),
                                       np.array([0.0, 0, 0, 1])))
            for k, t in enumerate(range(T0, spec.end(), 50 * MS))]


def test_a_second_arm_is_ingested(tmp_path: Path, capsys):
    spec = SynthSpec(frames=3)
    spec.extra = _second_arm(spec)
    log = synth_log.write(tmp_path / "log.mcap", spec)
    cfg = tmp_path / "two.toml"
    cfg.write_text('[[tools]]\npose = "/PSM2/measured_cp"\n')
    assert main(["ingest", str(log), "-o", str(tmp_path / "run"), "-q", "--config",
                 str(cfg)]) == 0
    ingested = load_ingested(tmp_path / "run" / "ingest")
    assert ingested.extra_tool_poses.shape == (3, 1, 4, 4)
    want_x = 0.01 * (ingested.stamps_ns - T0) / (50 * MS)  # linear between the samples
    np.testing.assert_allclose(ingested.extra_tool_poses[:, 0, 0, 3], want_x, atol=1e-9)
    assert ingested.all_tool_poses(1).shape == (2, 4, 4)
    cfg.write_text('[[tools]]\npose = "/PSM3/measured_cp"\n')
    assert main(["ingest", str(log), "-o", str(tmp_path / "run3"), "-q", "--config",
                 str(cfg)]) == 2
    assert "PSM3" in capsys.readouterr().err


def _scene_and_plain_template():
    """A small 4-camera scene, the default config, its template with the one simulated tool
    and the template point nearest the points' median (m)."""
    scene = render_frames(SimConfig(cameras=4, frames=2, width=300, height=250, seed=3), [0])
    cfg = Config()
    plain = build_template(TemplateFrame(scene.images[0], scene.poses[0], scene.tool_poses[0]),
                           scene.models, cfg.template, cfg.tool)
    median = np.median(plain.points, axis=0)
    return scene, cfg, plain, plain.points[np.argmin(np.linalg.norm(plain.points - median,
                                                                      axis=1))]


def test_the_template_has_no_point_on_a_second_tool():
    """A second tool laid across the tissue seen by the rig: without it the template has
    points along its axis, with it none within its radius."""
    scene, cfg, plain, centre = _scene_and_plain_template()
    across = make_pose(centre, np.array([0.0, np.sqrt(0.5), 0, np.sqrt(0.5)]))  # z along x
    second = ToolConfig(shaft_radius_m=0.002, shaft_length_m=0.01, jaw_length_m=0.01,
                        jaw_width_m=0.004)
    a, b = tool_capsules(across, second)[0][:2]
    assert (point_to_segment_distance(plain.points, a, b) < 0.002).sum() >= 2
    both = build_template(TemplateFrame(scene.images[0], scene.poses[0],
                                        np.stack([scene.tool_poses[0], across])),
                          scene.models, cfg.template, (cfg.tool, second))
    for a, b, radius in tool_capsules(across, second):
        assert (point_to_segment_distance(both.points, a, b) < radius).sum() == 0
    assert sum(both.stats["features"]) < sum(plain.stats["features"])  # masked before SIFT


def test_camera_offsets_move_a_tool_in_the_cameras_that_see_it_there():
    """The kinematics put a second tool 5 cm off where every camera sees it (a hand-eye
    error, `camera_offsets`): the template is masked and cleared at the seen place."""
    scene, cfg, plain, centre = _scene_and_plain_template()
    seen = make_pose(centre, np.array([0.0, np.sqrt(0.5), 0, np.sqrt(0.5)]))
    kinematic = seen.copy()
    kinematic[:3, 3] += [0.05, 0.0, 0.0]
    names = [f"cam{c}" for c in range(len(scene.models))]
    second = ToolConfig(shaft_radius_m=0.002, shaft_length_m=0.01, jaw_length_m=0.01,
                        jaw_width_m=0.004, camera_offsets=tuple(f"{n} -0.05 0 0" for n in names))
    tools = np.stack([scene.tool_poses[0], kinematic])
    assert camera_tool_poses(tools, (cfg.tool, replace(second, camera_offsets=())), names) is None
    with pytest.raises(ValueError, match="camera 'cam0'"):
        camera_tool_poses(tools, (cfg.tool, second), names[1:])
    per_camera = camera_tool_poses(tools, (cfg.tool, second), names)
    assert per_camera.shape == (len(names), 2, 4, 4)
    np.testing.assert_allclose(per_camera[:, 1], np.broadcast_to(seen, (len(names), 4, 4)),
                               atol=1e-12)
    np.testing.assert_allclose(per_camera[:, 0], np.broadcast_to(tools[0], (len(names), 4, 4)))
    moved = build_template(TemplateFrame(scene.images[0], scene.poses[0], per_camera),
                           scene.models, cfg.template, (cfg.tool, second))
    for a, b, radius in tool_capsules(seen, second):
        assert (point_to_segment_distance(plain.points, a, b) < radius).sum() >= 1
        assert (point_to_segment_distance(moved.points, a, b) < radius).sum() == 0


def test_info_proposes_every_dvrk_arm_and_its_config_runs(tmp_path: Path):
    spec = SynthSpec(frames=3, tool_topic="/PSM1/measured_cp")
    spec.extra = (_second_arm(spec, "/PSM2/measured_cp") + _second_arm(spec, "/ECM/measured_cp")
                  + _second_arm(spec, "/PSM2/local/measured_cp"))
    log = synth_log.write(tmp_path / "dvrk.mcap", spec)
    cfg = tmp_path / "dvrk.toml"
    assert main(["info", str(log), "--write-config", str(cfg)]) == 0
    config = load_config(cfg)
    assert config.topics.tool_pose == "/PSM1/measured_cp"
    assert [t.pose for t in config.tools] == ["/PSM2/measured_cp"]
    assert main(["ingest", str(log), "-o", str(tmp_path / "run"), "-q", "--config",
                 str(cfg)]) == 0
    assert load_ingested(tmp_path / "run" / "ingest").extra_tool_poses.shape == (3, 1, 4, 4)


def test_dvrk_arm_topics_are_recognised():
    from surgrecon_cli.info.dvrk import dvrk_arms
    got = dvrk_arms(["/PSM1/local/measured_cp", "/PSM1/measured_cp", "/ECM/measured_cp",
                     "/dvrk/PSM2/position_cartesian_current", "/jhu_daVinci/PSM3/measured_cp",
                     "/PSM2/setpoint_cp", "/camera/left/pose", "/MTML/measured_cp"])
    assert got == {"ECM": "/ECM/measured_cp", "PSM1": "/PSM1/measured_cp",
                   "PSM2": "/dvrk/PSM2/position_cartesian_current",
                   "PSM3": "/jhu_daVinci/PSM3/measured_cp"}


def test_cameras_on_the_ecm_by_their_hand_eye_poses(tmp_path: Path):
    """Camera poses from one ECM pose topic and topics.camera_from_ecm: camera 0 at the
    ECM's frame, camera 1 5 mm along its x and turned 10 degrees about its y."""
    from scipy.spatial.transform import Rotation

    from surgrecon_cli.core.geometry.poses import make_pose as pose_of

    spec = SynthSpec(cameras=(0, 1), frames=3)
    spec.mutate = lambda msgs: [
        ("/ECM/measured_cp", t, r) if topic == "/navigation/endoscope_0/pose" else (topic, t, r)
        for topic, t, r in msgs if topic != "/navigation/endoscope_1/pose"]
    log = synth_log.write(tmp_path / "ecm.mcap", spec)
    q = Rotation.from_euler("y", 10, degrees=True).as_quat()
    cfg = tmp_path / "ecm.toml"
    assert main(["info", str(log), "--write-config", str(cfg)]) == 0  # proposes the ECM
    written = cfg.read_text()
    assert 'camera_pose = "/ECM/measured_cp"' in written and "# camera_from_ecm" in written
    cfg.write_text(written.replace(
        "# camera_from_ecm = [x, y, z, qx, qy, qz, qw, ...]",
        f"camera_from_ecm = [0, 0, 0, 0, 0, 0, 1, 0.005, 0, 0, {q[0]}, {q[1]}, {q[2]}, {q[3]}]"))
    assert main(["ingest", str(log), "-o", str(tmp_path / "run"), "-q", "--config",
                 str(cfg)]) == 0
    got = load_ingested(tmp_path / "run" / "ingest")
    for k in range(3):
        ecm = synth_log.camera_pose(0, np.array([got.image_stamps_ns[k, 0]]))[0]
        np.testing.assert_allclose(got.poses[k, 0], ecm, atol=1e-9)
        ecm = synth_log.camera_pose(0, np.array([got.image_stamps_ns[k, 1]]))[0]
        want = ecm @ pose_of(np.array([0.005, 0, 0]), q)
        # camera 1's samples are interpolated after the lever arm moved them: their chord
        # misses the arc by |arm| x (turn between 40 ms samples)^2 / 8, well under 1 µm
        np.testing.assert_allclose(got.poses[k, 1], want, atol=1e-6)


def test_a_tools_clearance_counts_its_jaw():
    """Clearance to a plane z = 0 of a dVRK-style tool (frame z out of the jaws, shaft along
    -z) whose frame is 30 mm above the plane: its jaw, 5 to 25 mm beyond the frame and 8 mm
    wide, ends 5 mm above the plane, 1 mm nearer than its width's half: 1 mm clearance; the
    shaft alone would leave 30 mm; an unknown pose gives NaN."""
    from surgrecon_cli.core.measure.dent import tool_clearance

    xs = np.linspace(-0.01, 0.01, 21)
    plane = np.array([[x, y, 0.0] for x in xs for y in xs])
    down = np.array([1.0, 0, 0, 0])  # 180 degrees about x: z points down, out of the jaws
    pose = make_pose(np.array([0, 0, 0.03]), down)
    arm = ToolConfig(shaft_axis="-z", jaw_offset_m=0.005, jaw_length_m=0.02, jaw_width_m=0.008)
    assert np.nanmin(tool_clearance(plane, pose, arm)) == pytest.approx(0.001)
    shaft_only = ToolConfig(shaft_axis="-z")
    assert np.nanmin(tool_clearance(plane, pose, shaft_only)) == pytest.approx(0.03)
    assert np.isnan(tool_clearance(plane, np.full((4, 4), np.nan), arm)).all()


def test_mask_rays_without_the_polish_mask_the_same_pixels():
    """The mask casts its rays with OpenCV's undistortion alone (no Newton polish): on a
    strongly distorted lens they still reproject onto their pixels far below a pixel, and
    every pixel of a dense grid is masked as with the exactly inverted rays."""
    from surgrecon_cli.core.geometry.cameras import CameraModel, pixel_rays, project
    from surgrecon_cli.core.geometry.tool import ray_segment_distance

    model = CameraModel(np.array([[300.0, 0, 160], [0, 300.0, 120], [0, 0, 1]]),
                        np.array([-0.3, 0.1, 0.001, -0.001, 0.0]), 320, 240)
    camera_pose = make_pose(np.array([0.0, 0, 0.1]), np.array([1.0, 0, 0, 0]))
    tilted = make_pose(np.array([0.01, 0.005, 0.0]),
                       np.array([0.9, 0.3, 0.2, 0.1]) / np.linalg.norm([0.9, 0.3, 0.2, 0.1]))
    u, v = np.meshgrid(np.arange(0, 320, 0.7), np.arange(0, 240, 0.7))
    px = np.column_stack([u.ravel(), v.ravel()])
    origin, rays = pixel_rays(px, model, camera_pose, polish=False)
    back, _ = project(origin + 0.05 * rays, camera_pose, model)
    assert np.abs(back - px).max() < 1e-6
    cfg = ToolConfig()
    mask = tool_pixel_mask(px, model, camera_pose, tilted, cfg)
    origin, exact = pixel_rays(px, model, camera_pose, polish=True)
    expected = np.zeros(len(px), bool)
    for a, b, radius in tool_capsules(tilted, cfg):
        dist, s = ray_segment_distance(origin, exact, a, b)
        expected |= dist <= radius + cfg.mask_margin_px * s / model.K[0, 0]
    assert 0.02 < expected.mean() < 0.8  # the tool is in view, not all of it
    np.testing.assert_array_equal(mask, expected)
