"""Simulator variants (stereo head, rigid scene, sweeping cameras, tracker noise) and the
default scene kept (the shipped sample, within rounding)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from surgrecon_cli.cli.main import main
from surgrecon_cli.config import LabelsConfig, TopicsConfig
from surgrecon_cli.core.classify.labels import DEFORMING, SHIFTING, true_labels
from surgrecon_cli.core.geometry.poses import fit_rigid, invert_pose, make_pose, quat_to_matrix
from surgrecon_cli.io.logs.ground_truth import load_ground_truth
from surgrecon_cli.io.logs.reader import LogReader
from surgrecon_cli.io.logs.records import JointStateRecord, PoseRecord
from surgrecon_cli.sim.scene import SimConfig
from surgrecon_cli.sim.simulate import T0_NS, LogBuilder, simulate
from surgrecon_cli.sim.variants import STEREO_BASELINE, VARIANTS, variant_config
from surgrecon_cli.sim.visibility import visible_vertices

SMALL = {"frames": 4, "width": 320, "height": 240}


def _times(builder: LogBuilder) -> np.ndarray:
    """Tracker-like times over the whole log, and every image stamp."""
    cfg = builder.cfg
    stamps = [builder.image_stamp(f, c) for f in range(cfg.frames) for c in range(cfg.cameras)]
    return np.concatenate([np.linspace(-0.1, builder.frame_times[-1] + 0.1, 23), stamps])


def _seen(builder: LogBuilder, frame: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """(seen mask, depth) of the true frame-`frame` vertices in every camera."""
    vertices = builder.motion.tissue_vertices(builder.frame_times[frame])
    return [
        visible_vertices(
            vertices,
            builder.mesh.faces,
            builder.models[cam],
            builder.motion.camera_pose(cam, builder.image_stamp(frame, cam)),
        )
        for cam in range(builder.cfg.cameras)
    ]


# ---- default unchanged ------------------------------------------------------------------
SAMPLE = Path(__file__).resolve().parents[1] / "sample_data" / "sample.mcap"
# Rounding differs between numpy/scipy releases by ~1e-17 m; a real change to the scene is
# many orders of magnitude larger. Quaternion components and joint angles: the same bound.
POSITION_TOL = 1e-12  # m
UNITLESS_TOL = 1e-12


def _pose_streams(items) -> dict[str, list[tuple[int, int, np.ndarray]]]:
    """{topic: [(log time ns, stamp ns, values)]} of the pose and joint messages."""
    out: dict[str, list[tuple[int, int, np.ndarray]]] = {}
    for topic, log_ns, record in items:
        if isinstance(record, PoseRecord):
            values = np.concatenate([record.position, record.orientation])
        elif isinstance(record, JointStateRecord):
            values = np.asarray(record.positions, float)
        else:
            continue
        out.setdefault(topic, []).append((log_ns, record.stamp_ns, values))
    return out


def test_default_scene_is_the_shipped_sample():
    """The default scene (seed 7) still makes the shipped sample (`make sample`): its ground
    truth, in the current format, and every pose and joint message, within rounding; integer
    outputs (faces, labels, stamps) exactly. Images are not compared (JPEG encoders differ)."""
    cfg = SimConfig()
    assert variant_config("default") == cfg and cfg.seed == 7
    gt_path = SAMPLE.with_name("sample.gt.npz")
    with np.load(gt_path, allow_pickle=False) as z:
        assert set(z.files) == {"faces", "vertices", "labels", "stamps_ns", "tool_poses",
                                "indentation_m"}
    gt = load_ground_truth(gt_path)
    builder = LogBuilder(cfg)
    vertices = builder.true_vertices()
    np.testing.assert_array_equal(builder.mesh.faces, gt.faces)
    np.testing.assert_allclose(vertices, gt.vertices, rtol=0, atol=POSITION_TOL)
    rule = LabelsConfig()
    labels = true_labels(vertices, rule.static_mm, rule.neighbourhood_mm, rule.rigid_rms_mm)
    np.testing.assert_array_equal(labels, gt.labels)
    assert [T0_NS + round(t * 1e9) for t in builder.frame_times] == gt.stamps_ns.tolist()
    assert gt.tool_poses is not None and gt.indentation_m is not None
    tool = np.stack([make_pose(*builder.motion.tool_pose(t)) for t in builder.frame_times])
    np.testing.assert_allclose(tool, gt.tool_poses, rtol=0, atol=POSITION_TOL)
    dent = [builder.motion.indentation(t) for t in builder.frame_times]
    np.testing.assert_allclose(dent, gt.indentation_m, rtol=0, atol=POSITION_TOL)

    want = _pose_streams(builder._pose_messages())
    logged = LogReader(SAMPLE, TopicsConfig())
    got = _pose_streams((i.topic, i.log_time_ns, i.record) for i in logged
                        if i.role != "image" and i.role != "camera_info")
    assert sorted(got) == sorted(want)
    for topic, rows in want.items():
        assert [r[:2] for r in got[topic]] == [r[:2] for r in rows], topic
        np.testing.assert_allclose(np.stack([r[2] for r in got[topic]]),
                                   np.stack([r[2] for r in rows]), rtol=0,
                                   atol=POSITION_TOL, err_msg=topic)


# ---- stereo head ------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["stereo", "stereo-plus"])
def test_stereo_pair_is_rigid_and_30_to_80_mm_from_the_tissue(name):
    cfg = variant_config(name, seed=101, **SMALL)
    assert cfg.stereo_baseline == STEREO_BASELINE
    builder = LogBuilder(cfg)
    motion = builder.motion
    offset = np.eye(4)
    offset[0, 3] = cfg.stereo_baseline
    for t in _times(builder):
        T0, T1 = motion.camera_pose(0, t), motion.camera_pose(1, t)
        np.testing.assert_allclose(T1[:3, :3], T0[:3, :3], atol=1e-12)  # same orientation
        np.testing.assert_allclose(invert_pose(T0) @ T1, offset, atol=1e-12)
    # The head moves (it is tracked), and the two sensors share one clock.
    moved = motion.camera_pose(0, 0.7)[:3, 3] - motion.camera_pose(0, 0.0)[:3, 3]
    assert np.linalg.norm(moved) > 1e-4
    for f in range(cfg.frames):
        assert builder.image_stamp(f, 0) == builder.image_stamp(f, 1)
    for frame in (0, cfg.frames - 1):
        seen = _seen(builder, frame)
        for cam in (0, 1):
            mask, depth = seen[cam]
            assert mask.sum() > 2000
            assert depth[mask].min() >= 0.025 and depth[mask].max() <= 0.090
            assert depth[mask].min() < 0.040 and depth[mask].max() > 0.065  # oblique: a range
        both = seen[0][0] & seen[1][0]
        assert both.sum() > 0.8 * seen[0][0].sum()  # a narrow baseline: nearly the same view


def test_stereo_head_carries_one_tracker_marker():
    cfg = variant_config("stereo", seed=102, frames=3, width=96, height=72)
    builder = LogBuilder(cfg)
    by_cam: dict[str, list[PoseRecord]] = {"0": [], "1": []}
    for topic, _, record in builder._pose_messages():
        if topic.startswith("/navigation/endoscope_"):
            by_cam[topic.split("/")[2].removeprefix("endoscope_")].append(record)
    assert len(by_cam["0"]) == len(by_cam["1"]) > 10
    errors = []
    for r0, r1 in zip(by_cam["0"], by_cam["1"], strict=True):
        assert r0.stamp_ns == r1.stamp_ns
        M0 = make_pose(r0.position, r0.orientation)
        M1 = make_pose(r1.position, r1.orientation)
        np.testing.assert_allclose(invert_pose(M0) @ M1, builder.motion.stereo_offset, atol=1e-9)
        t = (r0.stamp_ns - T0_NS) * 1e-9
        errors.append(M0[:3, 3] - builder.motion.camera_pose(0, t)[:3, 3])
    assert 0.03e-3 < np.sqrt((np.square(errors).sum(1)).mean()) < 0.3e-3  # noisy, as tracked


def test_stereo_needs_two_cameras(capsys):
    with pytest.raises(ValueError, match="at least 2 cameras"):
        variant_config("stereo", cameras=1)
    assert main(["simulate", "x.mcap", "--variant", "stereo", "--cameras", "1", "-q"]) == 2
    assert "at least 2 cameras" in capsys.readouterr().err


# ---- rigid scene ------------------------------------------------------------------------
def test_rigid_scene_moves_rigidly_and_never_deforms():
    cfg = variant_config("rigid", seed=103, frames=6)
    builder = LogBuilder(cfg)
    vertices = builder.true_vertices()
    labels = true_labels(vertices, 1.0, 5.0, 0.25)
    assert not (labels == DEFORMING).any()
    assert (labels[-1] == SHIFTING).mean() > 0.5  # it does move (a few mm)
    moved = np.linalg.norm(vertices[-1] - vertices[0], axis=1)
    assert 0.002 < moved.max() < 0.010
    for frame in vertices[1:]:
        R, t = fit_rigid(vertices[0], frame)
        residual = np.linalg.norm(vertices[0] @ R.T + t - frame, axis=1)
        assert residual.max() < 1e-9
    angle = np.degrees(np.arccos((np.trace(fit_rigid(vertices[0], vertices[-1])[0]) - 1) / 2))
    assert 1.0 < angle < 8.0
    # The tool only hovers, >= 10 mm from the tissue (shaft as a capsule of its radius).
    motion = builder.motion
    for t in np.linspace(-0.1, builder.frame_times[-1] + 0.1, 15):
        tip, quat = motion.tool_pose(t)
        axis = quat_to_matrix(quat)[:, 2]
        d = motion.tissue_vertices(t) - tip
        along = np.clip(d @ axis, 0, cfg.tool_length)
        gap = np.linalg.norm(d - along[:, None] * axis, axis=1) - cfg.tool_radius
        assert gap.min() > 0.010


# ---- sweeping cameras ---------------------------------------------------------------------
def test_sweep_loses_a_large_share_of_the_frame0_tissue():
    cfg = variant_config("sweep", seed=104, **SMALL)
    builder = LogBuilder(cfg)
    first = np.any([m for m, _ in _seen(builder, 0)], axis=0)
    last = np.any([m for m, _ in _seen(builder, cfg.frames - 1)], axis=0)
    lost = (first & ~last).sum() / first.sum()
    assert 0.30 <= lost <= 0.50, lost
    # Pans only: the camera centres follow the un-swept drift; the angle grows smoothly.
    motion = builder.motion
    times = np.linspace(0, builder.frame_times[-1], 9)
    for cam in range(cfg.cameras):
        angles = []
        for t in times:
            T, base = motion.camera_pose(cam, t), motion._drifting_pose(cam, t)
            np.testing.assert_array_equal(T[:3, 3], base[:3, 3])
            cos = (np.trace(base[:3, :3].T @ T[:3, :3]) - 1) / 2
            angles.append(np.degrees(np.arccos(np.clip(cos, -1, 1))))
        assert angles[0] < 1e-3 and np.all(np.diff(angles) > 0)  # arccos: ~1e-5 deg at 0
        assert 0.7 * cfg.sweep_deg < angles[-1] <= cfg.sweep_deg + 1e-9


# ---- tracker noise, from the written log ----------------------------------------------------
def _tracker_noise(path, builder: LogBuilder) -> tuple[float, float]:
    """RMS position error (m) and RMS rotation error (deg) of the log's camera poses."""
    pos, rot = [], []
    for item in LogReader(path, TopicsConfig()):
        if item.role != "camera_pose":
            continue
        record = item.record
        T = builder.motion.camera_pose(int(item.camera), (record.stamp_ns - T0_NS) * 1e-9)
        pos.append(np.linalg.norm(record.position - T[:3, 3]))
        dR = quat_to_matrix(record.orientation) @ T[:3, :3].T
        rot.append(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))))
    assert len(pos) > 100
    return float(np.sqrt(np.mean(np.square(pos)))), float(np.sqrt(np.mean(np.square(rot))))


@pytest.mark.parametrize(
    ("args", "variant", "want_mm", "want_deg"),
    [
        ([], "default", 0.1, 0.05),
        (["--variant", "noisy"], "noisy", 0.25, 0.1),
        (["--tracker-noise-mm", "0.6", "--tracker-noise-deg", "0.3"], "noisy", 0.6, 0.3),
    ],
)
def test_tracker_noise_options_set_the_noise_of_the_pose_stream(
    tmp_path, args, variant, want_mm, want_deg
):
    out = tmp_path / "n.mcap"
    size = {"cameras": 5, "frames": 4, "width": 48, "height": 40, "seed": 9}
    cli_size = [x for k, v in size.items() for x in (f"--{k}", str(v))]
    if variant == "noisy" and "--variant" not in args:
        args = ["--variant", "noisy", *args]  # explicit options override the preset
    assert main(["simulate", str(out), *cli_size, *args, "-q"]) == 0
    noise = {"tracker_noise_pos": want_mm * 1e-3, "tracker_noise_deg": want_deg}
    builder = LogBuilder(variant_config(variant, **size, **noise))
    got_pos, got_deg = _tracker_noise(out, builder)
    assert got_pos == pytest.approx(want_mm * 1e-3, rel=0.2)
    assert got_deg == pytest.approx(want_deg, rel=0.2)
    assert load_ground_truth(out.with_name("n.gt.npz")).n_frames == 4  # the reader accepts it


# ---- presets and the command line -------------------------------------------------------------
def test_presets_and_explicit_options(tmp_path, capsys):
    assert set(VARIANTS) >= {"default", "stereo", "stereo-plus", "rigid", "sweep", "noisy"}
    assert variant_config("default") == SimConfig()
    assert variant_config("stereo-plus").cameras == 5
    assert variant_config("stereo", cameras=3).cameras == 3  # explicit beats the preset
    with pytest.raises(ValueError, match="unknown simulator variant"):
        variant_config("nope")
    assert main(["simulate", "--help"]) == 0
    help_text = capsys.readouterr().out
    for variant in VARIANTS.values():
        assert variant.name in help_text and variant.description in help_text
    out = tmp_path / "s.mcap"
    args = ["--variant", "stereo-plus", "--cameras", "3", "--frames", "2", "--width", "48"]
    assert main(["simulate", str(out), *args, "--height", "40", "--sweep-deg", "10", "-q"]) == 0
    assert "3 cameras, variant stereo-plus" in capsys.readouterr().out
    topics = {item.topic for item in LogReader(out, TopicsConfig()) if item.role == "image"}
    assert topics == {f"/endoscope_{c}/color/compressed" for c in range(3)}


def test_explicit_default_options_change_nothing(tmp_path):
    size = ["--cameras", "2", "--frames", "2", "--width", "48", "--height", "40", "--seed", "3"]
    defaults = ["--tracker-noise-mm", "0.1", "--tracker-noise-deg", "0.05",
                "--stereo-baseline-mm", "0", "--sweep-deg", "0", "--no-rigid-scene"]
    assert main(["simulate", str(tmp_path / "cli.mcap"), *size, *defaults, "-q"]) == 0
    ref = simulate(tmp_path / "ref.mcap", SimConfig(cameras=2, frames=2, width=48, height=40,
                                                    seed=3))
    assert (tmp_path / "cli.mcap").read_bytes() == ref.log_path.read_bytes()
    assert (tmp_path / "cli.gt.npz").read_bytes() == ref.gt_path.read_bytes()


def test_a_camera_that_sees_no_tissue_renders(tmp_path):
    cfg = SimConfig(cameras=3, frames=2, width=64, height=48, seed=3, separated=True)
    builder = LogBuilder(cfg)
    assert not _seen(builder, 0)[-1][0].any()
    assert simulate(tmp_path / "sep.mcap", cfg).n_frames == 2


def test_breathing_rises_rigidly_with_a_local_swelling():
    """The breathing variant: the whole tissue rises 2-5 mm within one breath (0.2-0.3 Hz),
    seen by a stereo head with real-image difficulty; only a local swelling deforms."""
    cfg = variant_config("breathing", seed=105, frames=12)
    assert cfg.cameras == 2 and cfg.stereo_baseline == STEREO_BASELINE and cfg.warp_px > 0
    assert 0.2 <= 1.0 / cfg.breath_period <= 0.3
    builder = LogBuilder(cfg)
    vertices = builder.true_vertices()
    peak = int(np.argmax(np.linalg.norm(vertices - vertices[0], axis=2).mean(1)))
    moved = np.linalg.norm(vertices[peak] - vertices[0], axis=1)
    far = np.linalg.norm(builder.mesh.vertices[:, :2] - cfg.swell_xy, axis=1) > 0.015
    assert 0.002 <= np.median(moved) <= 0.005
    R, t = fit_rigid(vertices[0][far], vertices[peak][far])
    assert np.abs(vertices[0][far] @ R.T + t - vertices[peak][far]).max() < 1e-9
    labels = true_labels(vertices, 1.0, 5.0, 0.25)[peak]
    assert not (labels[far] == DEFORMING).any()
    assert (labels == DEFORMING).sum() > 50  # the swelling
    # The tool is held well away from the tissue.
    tip, _ = builder.motion.tool_pose(builder.frame_times[peak])
    assert np.linalg.norm(vertices[peak] - tip, axis=1).min() > 0.010
