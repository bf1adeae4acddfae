"""`surgrecon ingest`: logs in every encoding -> run folder with the known frames, intrinsics,
images and poses; every bad input -> one-line error, exit code 2, nothing half-written."""

from __future__ import annotations

import dataclasses
import json
import struct
from pathlib import Path

import numpy as np
import pytest
import synth_log
from synth_log import MS, T0, SynthSpec

from surgrecon_cli.cli.main import main
from surgrecon_cli.config import Config, to_toml
from surgrecon_cli.core.geometry.poses import make_pose
from surgrecon_cli.io.logs.records import ImageRecord, PoseRecord
from surgrecon_cli.io.run.folder import RunFolder, file_sha256
from surgrecon_cli.io.run.ingest_store import load_ingested
from surgrecon_cli.report.caveats import run_caveats
from surgrecon_cli.sim.log_writer import ENCODINGS


def run_ingest(log: Path, run: Path, *extra: str) -> int:
    return main(["ingest", str(log), "-o", str(run), "--quiet", *extra])


def check_log(run: Path, spec: SynthSpec, jpeg: bool = False) -> None:
    """The run folder holds exactly the synthetic log's frames, cameras, images and poses."""
    log = load_ingested(run / "ingest")
    ids = tuple(str(c) for c in spec.cameras)
    assert log.cameras == ids and log.n_frames == spec.frames
    frame_times = np.array([spec.frame_time(k) for k in range(spec.frames)])
    offsets = np.array(spec.cameras) * spec.camera_offset_ms * MS
    np.testing.assert_array_equal(log.stamps_ns, frame_times + int(np.median(offsets)))
    np.testing.assert_array_equal(log.image_stamps_ns, frame_times[:, None] + offsets[None])
    for c, cam in enumerate(spec.cameras):
        np.testing.assert_allclose(log.models[c].K, synth_log.intrinsics(cam))
        assert (log.models[c].width, log.models[c].height) == (synth_log.W, synth_log.H)
        for t in range(spec.frames):
            img = log.load_image(t, c)
            want = synth_log.image_rgb(cam, t)
            if jpeg:
                assert np.abs(img.astype(int) - want).mean() < 4
            else:
                np.testing.assert_array_equal(img, want)
        want = synth_log.camera_pose(cam, log.image_stamps_ns[:, c])
        usable = log.usable[:, c]
        np.testing.assert_allclose(log.poses[usable, c], want[usable], atol=1e-9)
    true_tool = make_pose(synth_log.tool_position(log.stamps_ns),
                          np.tile([0.0, 0, 0, 1], (log.n_frames, 1)))
    np.testing.assert_allclose(log.tool_poses, true_tool, atol=1e-12)
    if spec.joint_topic:
        assert log.joint_names == synth_log.JOINTS
        np.testing.assert_allclose(log.joint_positions, synth_log.joint_values(log.stamps_ns),
                                   atol=1e-12)


@pytest.mark.parametrize("encoding", ENCODINGS)
def test_ingest_every_encoding(tmp_path: Path, encoding: str, capsys):
    spec = SynthSpec()
    log = synth_log.write(tmp_path / "log.mcap", spec, encoding)
    run = tmp_path / "run"
    assert main(["ingest", str(log), "-o", str(run)]) == 0
    out = capsys.readouterr().out
    assert "6 frames from 3 cameras" in out and "tracker Hz" in out
    assert "25.0" in out and "10.0" in out  # tracker and image rates
    check_log(run, spec)
    assert load_ingested(run / "ingest").usable.all()
    meta = json.loads((run / "run.json").read_text())
    assert meta["stages"]["ingest"]["status"] == "done"
    assert meta["ingest"] == {"cameras": ["0", "1", "2"], "frames": 6}
    assert meta["input"]["sha256"] == file_sha256(log)
    assert meta["config"]["ingest"]["sync_tolerance_ms"] == 15.0
    assert set(meta["versions"]) >= {"surgrecon", "numpy", "scipy", "opencv", "open3d", "mcap"}
    assert (run / "config.toml").read_text() == to_toml(Config())
    assert not list(run.glob(".ingest-*"))


def test_ingest_jpeg_raw_and_late_intrinsics(tmp_path: Path):
    spec = SynthSpec(image_format="jpeg", info_first=False, cameras=(0, 1))
    assert run_ingest(synth_log.write(tmp_path / "a.mcap", spec), tmp_path / "a") == 0
    check_log(tmp_path / "a", spec, jpeg=True)
    assert (tmp_path / "a/ingest/images/00/000000.jpg").is_file()
    spec = SynthSpec(image_format="rgb8", cameras=(2, 4), joint_topic=None)
    assert run_ingest(synth_log.write(tmp_path / "b.mcap", spec, "foxglove-json"),
                      tmp_path / "b", "--set", 'topics.joint_states=""') == 0
    check_log(tmp_path / "b", spec)
    log = load_ingested(tmp_path / "b/ingest")
    assert log.cameras == ("2", "4") and log.joint_positions.shape == (spec.frames, 0)


def test_custom_topics_and_tf_poses_from_a_config_file(tmp_path: Path):
    spec = SynthSpec(
        image_topic="/stereo/cam{c}/image_raw", info_topic="/stereo/cam{c}/camera_info",
        tf_topic="/tf", camera_frame="cam{c}_optical_frame", tool_frame="psm1_tip",
        joint_topic="/psm1/joint_states", image_format="rgb8",
    )
    log = synth_log.write(tmp_path / "log.mcap", spec, "ros1")
    cfg = tmp_path / "dvrk.toml"
    cfg.write_text('[topics]\nimage = "/stereo/cam{camera}/image_raw"\n'
                   'camera_info = "/stereo/cam{camera}/camera_info"\ncamera_pose = "/tf"\n'
                   'camera_frame = "cam{camera}_optical_frame"\ntool_pose = "/tf"\n'
                   'tool_frame = "psm1_tip"\njoint_states = "/psm1/joint_states"\n')
    run = tmp_path / "run"
    assert run_ingest(log, run, "--config", str(cfg)) == 0
    check_log(run, spec)
    assert "psm1_tip" in (run / "config.toml").read_text()
    # The default topics do not fit this log: a one-line error listing what is there.
    assert run_ingest(log, tmp_path / "run2") == 2


def test_tool_base_to_world(tmp_path: Path):
    log = synth_log.write(tmp_path / "log.mcap")
    run = tmp_path / "run"
    assert run_ingest(log, run, "--set", "tool.base_to_world=[1, 2, 3, 0, 0, 1, 0]") == 0
    got = load_ingested(run / "ingest").tool_poses
    p = synth_log.tool_position(load_ingested(run / "ingest").stamps_ns)
    np.testing.assert_allclose(got[:, :3, 3], np.array([1, 2, 3]) + p * [-1, -1, 1], atol=1e-12)


def test_pose_gap_makes_camera_unusable_not_an_error(tmp_path: Path, capsys):
    spec = SynthSpec(tracker_gap=(1, 350, 560))  # frames 2, 3 of camera 1 fall in the gap
    log = synth_log.write(tmp_path / "log.mcap", spec)
    run = tmp_path / "run"
    assert main(["ingest", str(log), "-o", str(run)]) == 0
    captured = capsys.readouterr()
    assert "camera 1: no tracked pose within the gap limit at 2 of its images" in captured.err
    ingested = load_ingested(run / "ingest")
    assert [list(row) for row in ingested.usable[:, 1:2].T] == [[True, True, False, False,
                                                                 True, True]]
    assert np.isnan(ingested.poses[2:4, 1]).all() and ingested.usable[:, [0, 2]].all()
    assert ingested.report["cameras"]["1"]["pose_gaps"] == 2
    check_log(run, spec)  # the usable poses are right
    row = next(line for line in captured.out.splitlines() if line.startswith("1 "))
    assert row.split()[6] == "2"  # the pose-gaps column


def _fixed_rig(messages, resent_ms: int = 0):
    """Camera poses world -> endoscope_c_optical on /tf become world -> rig -> optical, all
    fixed (the poses at the log's start): rig -> optical latched on /tf_static, world -> rig
    too, or with `resent_ms` re-sent on /tf every ~`resent_ms` ms (+-10 %, as ROS 1's tf
    static_transform_publisher does). A rig fixed in the world, as a lab's bag records it."""
    rig = make_pose(np.array([0.01, 0.02, 0.3]), np.array([0.0, 0.0, 0.0, 1.0]))
    out = [m for m in messages if not (m[0] == "/tf" and m[2].child_frame_id.endswith("_optical"))]
    to_rig = [PoseRecord(T0, "world", "rig", rig[:3, 3], np.array([0.0, 0.0, 0.0, 1.0]))]
    statics = [] if resent_ms else to_rig
    for c in (0, 1, 2):
        in_rig = np.linalg.inv(rig) @ synth_log.camera_pose(c, np.array([T0]))[0]
        statics.append(PoseRecord(T0, "rig", f"endoscope_{c}_optical", in_rig[:3, 3],
                                  synth_log.camera_quat(c, np.array([T0]))[0]))
    if resent_ms:
        periods = resent_ms * (1.0 + 0.1 * np.random.default_rng(0).uniform(-1, 1, 40))
        for t in T0 + np.round(np.cumsum(periods) * MS).astype(np.int64) - resent_ms * MS:
            out.append(("/tf", int(t) + MS, PoseRecord(int(t), "world", "rig", *(
                to_rig[0].position, to_rig[0].orientation))))
    return [("/tf_static", T0 + MS, r) for r in statics] + out


@pytest.mark.parametrize("resent_ms", [0, 100])
def test_a_fixed_rig_is_placed_in_every_frame(tmp_path: Path, capsys, resent_ms: int):
    # A chain of latched transforms holds for the whole log: every frame, however far from
    # the one stamp /tf_static carries (the log spans 7 pose gaps of 100 ms); so does a
    # fixed transform re-sent on /tf with a jittery period (gaps above 100 ms).
    spec = SynthSpec(tf_topic="/tf", frames=8,
                     mutate=lambda messages: _fixed_rig(messages, resent_ms))
    log = synth_log.write(tmp_path / "log.mcap", spec)
    run = tmp_path / "run"
    assert main(["ingest", str(log), "-o", str(run), "--set", 'topics.camera_pose="/tf_static"',
                 "--set", 'topics.camera_frame="endoscope_{camera}_optical"',
                 "--set", 'topics.tool_pose="/tf"', "--set", 'topics.tool_frame="raven_tool_tip"']
                ) == 0
    assert "no tracked pose" not in capsys.readouterr().err
    ingested = load_ingested(run / "ingest")
    assert ingested.usable.all() and ingested.n_frames == 8
    for c in range(3):
        want = synth_log.camera_pose(c, np.array([T0]))[0]
        np.testing.assert_allclose(ingested.poses[:, c], np.broadcast_to(want, (8, 4, 4)),
                                   atol=1e-9)


@pytest.mark.parametrize("encoding", ENCODINGS)
def test_a_ros_stereo_pair_is_placed_by_its_camera_info(tmp_path: Path, encoding: str):
    # No pose topic: topics.camera_pose = "camera_info" places the pair by its CameraInfo R
    # and P, the left camera at the origin, the right where the stereo extrinsics put it.
    spec = SynthSpec(cameras=(0, 1), mutate=synth_log.ros_stereo)
    log = synth_log.write(tmp_path / "log.mcap", spec, encoding)
    run = tmp_path / "run"
    assert run_ingest(log, run, "--set", 'topics.camera_pose="camera_info"') == 0
    ingested = load_ingested(run / "ingest")
    assert ingested.usable.all()
    right_in_left = np.eye(4)
    right_in_left[:3, :3] = synth_log.STEREO_R.T
    right_in_left[:3, 3] = -synth_log.STEREO_R.T @ synth_log.STEREO_T
    np.testing.assert_allclose(ingested.poses[:, 0], np.broadcast_to(np.eye(4), (6, 4, 4)),
                               atol=1e-9)
    np.testing.assert_allclose(ingested.poses[:, 1], np.broadcast_to(right_in_left, (6, 4, 4)),
                               atol=1e-9)


def test_rectified_images_take_the_projection_and_the_rectified_orientation(tmp_path: Path):
    # image_rect* topics: modelled by P without distortion and turned by R, so that the two
    # rectified cameras look the same way (R2 STEREO_R = R1) and the right one sits on the
    # left one's x axis, -Tx / fx' away.
    spec = SynthSpec(cameras=(0, 1), mutate=synth_log.ros_stereo,
                     image_topic="/endoscope_{c}/image_rect_color")
    log = synth_log.write(tmp_path / "log.mcap", spec)
    run = tmp_path / "run"
    assert run_ingest(log, run, "--set", 'topics.camera_pose="camera_info"', "--set",
                      'topics.image="/endoscope_{camera}/image_rect_color"') == 0
    ingested = load_ingested(run / "ingest")
    P = synth_log.ros_stereo_projections()
    for c in (0, 1):
        np.testing.assert_allclose(ingested.models[c].K, P[c][:, :3])
        assert not np.any(ingested.models[c].dist)
    left, right = ingested.poses[0, 0], ingested.poses[0, 1]
    np.testing.assert_allclose(left[:3, :3], right[:3, :3], atol=1e-9)
    offset = left[:3, :3].T @ (right[:3, 3] - left[:3, 3])
    np.testing.assert_allclose(offset, [-P[1][0, 3] / P[1][0, 0], 0, 0], atol=1e-9)


def test_camera_info_poses_need_a_stereo_calibration(tmp_path: Path, capsys):
    # CameraInfo of monocular calibrations (R = I, P = [K | 0]): one line, nothing written.
    spec = SynthSpec(cameras=(0, 1), mutate=lambda ms: [m for m in ms
                                                        if not m[0].endswith("/pose")])
    log = synth_log.write(tmp_path / "log.mcap", spec)
    assert main(["ingest", str(log), "-o", str(tmp_path / "run"), "--set",
                 'topics.camera_pose="camera_info"']) == 2
    err = capsys.readouterr().err
    assert "cameras 0, 1 give the rig no baseline" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "run" / "ingest").exists()


def test_rerun_needs_force(tmp_path: Path, capsys):
    log = synth_log.write(tmp_path / "log.mcap")
    run = tmp_path / "run"
    assert run_ingest(log, run) == 0
    assert run_ingest(log, run) == 2
    assert "--force" in capsys.readouterr().err
    assert RunFolder(run).is_done("ingest")
    assert run_ingest(log, run, "--force") == 0
    assert RunFolder(run).is_done("ingest") and not list(run.glob(".ingest-*"))


def test_help_has_an_example(capsys):
    assert main(["ingest", "--help"]) == 0
    out = capsys.readouterr().out
    assert "Example" in out and "surgrecon ingest" in out and "--allow-truncated" in out


# -- bad input: one line, exit code 2, nothing claiming success ------------------------------

def assert_failed(run: Path, capsys, *fragments: str) -> str:
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert lines[0].startswith("error: ") and all(s.startswith("  ") for s in lines[1:]), err
    for fragment in fragments:
        assert fragment in err, err
    assert not (run / "ingest").exists()
    assert not list(run.glob(".ingest-*")) if run.exists() else True
    if (run / "run.json").exists():
        assert json.loads((run / "run.json").read_text())["stages"]["ingest"]["status"] == "failed"
    return lines[0]


def test_not_an_mcap_file(tmp_path: Path, capsys):
    log = tmp_path / "log.mcap"
    log.write_bytes(b"#ROSBAG V2.0\n" + bytes(100))
    assert run_ingest(log, tmp_path / "run") == 2
    assert_failed(tmp_path / "run", capsys, "not an MCAP file", str(log))
    assert not (tmp_path / "run").exists()


def _data_end(data: bytes) -> int:
    return struct.unpack("<Q", data[-28:-20])[0]  # footer.summary_start


@pytest.mark.parametrize(("fraction", "chunk_size"),
                         [(0.2, 4096), (0.5, 4096), (0.8, 4096), (0.97, 4096), (0.5, 1 << 20)])
def test_truncated_log(tmp_path: Path, capsys, fraction: float, chunk_size: int):
    full = synth_log.write(tmp_path / "full.mcap", chunk_size=chunk_size)
    data = full.read_bytes()
    log = tmp_path / "cut.mcap"
    log.write_bytes(data[: int(_data_end(data) * fraction)])
    run = tmp_path / "run"
    assert run_ingest(log, run) == 2
    assert_failed(run, capsys, str(log), "truncated", "valid data ends at byte",
                  "--allow-truncated")
    assert run_ingest(log, run, "--allow-truncated") in (0, 2)
    if RunFolder(run).is_done("ingest"):
        ingested = load_ingested(run / "ingest")
        assert 0 < ingested.n_frames <= 6 and ingested.usable.all(axis=1)[-1]
        assert ingested.report["truncated"]
    else:  # damage before the first complete frame
        assert_failed(run, capsys, "no complete frame before the damage")


def test_allow_truncated_keeps_complete_frames(tmp_path: Path):
    full = synth_log.write(tmp_path / "full.mcap", SynthSpec(frames=12), chunk_size=4096)
    data = full.read_bytes()
    log = tmp_path / "cut.mcap"
    log.write_bytes(data[: int(_data_end(data) * 0.7)])
    run = tmp_path / "run"
    assert run_ingest(log, run, "--allow-truncated") == 0
    ingested = load_ingested(run / "ingest")
    assert 2 <= ingested.n_frames < 12 and ingested.usable.all()
    meta = RunFolder(run).read()
    assert meta["stages"]["ingest"]["truncated"].startswith("the file ends inside a record")
    assert meta["input"]["sha256"] == file_sha256(log)


def test_truncated_inside_the_summary_loses_nothing(tmp_path: Path):
    full = synth_log.write(tmp_path / "full.mcap")
    log = tmp_path / "cut.mcap"
    log.write_bytes(full.read_bytes()[:-20])
    assert run_ingest(log, tmp_path / "run") == 0
    assert load_ingested(tmp_path / "run/ingest").n_frames == 6


def _chunks(data: bytes) -> list[tuple[int, int]]:
    """(offset, length) of each top-level Chunk record."""
    out, pos = [], 8
    while pos < len(data) - 8:
        opcode, length = data[pos], struct.unpack("<Q", data[pos + 1: pos + 9])[0]
        if opcode == 0x06:
            out.append((pos, length))
        if opcode == 0x0F:  # data end
            break
        pos += 9 + length
    return out


def test_flipped_bytes_inside_a_chunk(tmp_path: Path, capsys):
    full = synth_log.write(tmp_path / "full.mcap", chunk_size=4096)
    data = bytearray(full.read_bytes())
    chunks = _chunks(bytes(data))
    assert len(chunks) >= 3
    offset, length = chunks[1]
    for k in range(5):
        data[offset + length - 100 - 7 * k] ^= 0x5A
    log = tmp_path / "bad.mcap"
    log.write_bytes(bytes(data))
    run = tmp_path / "run"
    assert run_ingest(log, run) == 2
    line = assert_failed(run, capsys, str(log), "corrupt data", "--allow-truncated")
    assert f"valid data ends at byte {offset}" in line


def test_no_topic_for_a_role_lists_existing_topics(tmp_path: Path, capsys):
    log = synth_log.write(tmp_path / "log.mcap", SynthSpec(tool_topic="/psm2/tip"))
    run = tmp_path / "run"
    assert run_ingest(log, run) == 2
    assert_failed(run, capsys, "topics.tool_pose = '/raven/tool_tip'", "/psm2/tip",
                  "/endoscope_0/calibration")


def test_unsupported_schema_on_a_role_topic(tmp_path: Path, capsys):
    rec = PoseRecord(T0, "world", "", np.zeros(3), np.array([0.0, 0, 0, 1]))
    spec = SynthSpec(extra=[("/endoscope_7/color/compressed", T0, rec)])
    log = synth_log.write(tmp_path / "log.mcap", spec)
    assert run_ingest(log, tmp_path / "run") == 2
    assert_failed(tmp_path / "run", capsys, "/endoscope_7/color/compressed",
                  "geometry_msgs/msg/PoseStamped", "supported: sensor_msgs/msg/CompressedImage")


def test_camera_without_intrinsics(tmp_path: Path, capsys):
    log = synth_log.write(tmp_path / "log.mcap", SynthSpec(skip_info=(2,)))
    assert run_ingest(log, tmp_path / "run") == 2
    assert_failed(tmp_path / "run", capsys, "camera 2", "no intrinsics")


def _mutate_pose(camera: int, index: int, position=None, scale: float = 1.0):
    topic = f"/navigation/endoscope_{camera}/pose"

    def mutate(messages):
        hits = [i for i, m in enumerate(messages) if m[0] == topic]
        i = hits[index]
        name, log_time, rec = messages[i]
        messages[i] = (name, log_time, dataclasses.replace(
            rec, position=rec.position if position is None else np.asarray(position),
            orientation=rec.orientation * scale))
        return messages

    return mutate


def test_nan_pose(tmp_path: Path, capsys):
    spec = SynthSpec(mutate=_mutate_pose(1, 5, position=[0.0, np.nan, 0.0]))
    log = synth_log.write(tmp_path / "log.mcap", spec)
    assert run_ingest(log, tmp_path / "run") == 2
    stamp = T0 + 5 * spec.tracker_period_ms * MS
    assert_failed(tmp_path / "run", capsys, "/navigation/endoscope_1/pose",
                  f"{stamp // 10**9}.{stamp % 10**9:09d} s", "non-finite")


def test_non_normalised_quaternion(tmp_path: Path, capsys):
    log = synth_log.write(tmp_path / "log.mcap", SynthSpec(mutate=_mutate_pose(0, 3, scale=1.2)))
    assert run_ingest(log, tmp_path / "run") == 2
    assert_failed(tmp_path / "run", capsys, "/navigation/endoscope_0/pose", "non-unit quaternion")
    # A tiny deviation is normalised, not an error.
    log = synth_log.write(tmp_path / "ok.mcap", SynthSpec(mutate=_mutate_pose(0, 3, scale=1.0002)))
    assert run_ingest(log, tmp_path / "run_ok") == 0


def _replace_image(camera: int, frame: int, **changes):
    topic = f"/endoscope_{camera}/color/compressed"

    def mutate(messages):
        i = [i for i, m in enumerate(messages) if m[0] == topic][frame]
        name, log_time, rec = messages[i]
        messages[i] = (name, log_time, dataclasses.replace(rec, **changes))
        return messages

    return mutate


def test_image_that_does_not_decode(tmp_path: Path, capsys):
    spec = SynthSpec(mutate=_replace_image(1, 3, data=b"\xff\xd8\xff garbage, not a JPEG"))
    log = synth_log.write(tmp_path / "log.mcap", spec)
    run = tmp_path / "run"
    assert run_ingest(log, run) == 2
    stamp = spec.image_stamp(1, 3)
    assert_failed(run, capsys, "/endoscope_1/color/compressed",
                  f"{stamp // 10**9}.{stamp % 10**9:09d} s", "does not decode")


@pytest.mark.parametrize("info_first", [True, False])
def test_image_of_wrong_size(tmp_path: Path, capsys, info_first: bool):
    small = synth_log.encode(synth_log.image_rgb(0, 0)[:24, :32], "png")
    spec = SynthSpec(info_first=info_first, mutate=_replace_image(0, 2, data=small))
    log = synth_log.write(tmp_path / "log.mcap", spec)
    assert run_ingest(log, tmp_path / "run") == 2
    assert_failed(tmp_path / "run", capsys, "/endoscope_0/color/compressed", "32x24 px",
                  "/endoscope_0/calibration gives 64x48 px")


def test_unsupported_raw_encoding(tmp_path: Path, capsys):
    spec = SynthSpec(image_format="rgb8",
                     mutate=_replace_image(2, 0, format="nv21"))  # Bayer/YUV: test_encodings
    log = synth_log.write(tmp_path / "log.mcap", spec, "ros2")
    assert run_ingest(log, tmp_path / "run") == 2
    assert_failed(tmp_path / "run", capsys, "nv21", "not supported")


def test_failed_reingest_does_not_keep_done_status(tmp_path: Path, capsys):
    good = synth_log.write(tmp_path / "good.mcap")
    run = tmp_path / "run"
    assert run_ingest(good, run) == 0
    bad = synth_log.write(tmp_path / "bad.mcap", SynthSpec(skip_info=(0,)))
    assert run_ingest(bad, run, "--force") == 2
    err = capsys.readouterr().err
    assert "no intrinsics" in err
    assert RunFolder(run).stage_status("ingest") == "failed"
    assert not list(run.glob(".ingest-*"))


def test_camera_ids_are_sorted_strings(tmp_path: Path):
    spec = SynthSpec(cameras=(10, 2))
    log = synth_log.write(tmp_path / "log.mcap", spec)
    assert run_ingest(log, tmp_path / "run") == 0
    assert RunFolder(tmp_path / "run").read()["ingest"]["cameras"] == ["10", "2"]


def test_log_time_source(tmp_path: Path):
    # Stamps in the messages are zero: the log time (stamp + 1 ms) is used.
    def zero_image_stamps(messages):
        return [(t, lt, dataclasses.replace(r, stamp_ns=0) if isinstance(r, ImageRecord) else r)
                for t, lt, r in messages]

    log = synth_log.write(tmp_path / "log.mcap", SynthSpec(mutate=zero_image_stamps))
    assert run_ingest(log, tmp_path / "a") == 0
    a = load_ingested(tmp_path / "a/ingest")
    assert run_ingest(synth_log.write(tmp_path / "b.mcap"), tmp_path / "b", "--set",
                      "ingest.time_source='log_time'") == 0
    b = load_ingested(tmp_path / "b/ingest")
    np.testing.assert_array_equal(a.image_stamps_ns, b.image_stamps_ns)
    np.testing.assert_array_equal(b.image_stamps_ns[0], SynthSpec().frame_time(0) + MS +
                                  np.arange(3) * 3 * MS)


def test_a_part_of_a_long_log_is_ingested(tmp_path: Path, capsys):
    """ingest.start_s / duration_s / every keep a window of the recording at a lower rate;
    a window past the end is a clear error that names the keys and the log's span."""
    spec = SynthSpec(frames=12)
    log = synth_log.write(tmp_path / "log.mcap", spec)
    assert run_ingest(log, tmp_path / "whole") == 0
    whole = load_ingested(tmp_path / "whole/ingest")
    run = tmp_path / "part"
    start = (whole.stamps_ns[3] - whole.stamps_ns[0]) / 1e9
    assert run_ingest(log, run, "--set", f"ingest.start_s={start}", "--set",
                      "ingest.every=2") == 0
    part = load_ingested(run / "ingest")
    np.testing.assert_array_equal(part.stamps_ns, whole.stamps_ns[3::2])
    np.testing.assert_array_equal(part.image_stamps_ns, whole.image_stamps_ns[3::2])
    np.testing.assert_allclose(part.poses, whole.poses[3::2])
    for k, t in enumerate(range(3, 12, 2)):
        np.testing.assert_array_equal(part.load_image(k, 0), whole.load_image(t, 0))
    assert part.report["frames_in_log"] == 12 and part.report["part"]["every"] == 2
    assert part.report["start_s"] == pytest.approx(start)  # where its frame 0 lies
    (said,) = [c for c in run_caveats({}, part.report) if c.startswith("A part of the log")]
    assert said.startswith(f"A part of the log: 5 of its 12 frames (from {start:g} s after")
    assert len(part.image_paths) == len(part.stamps_ns)
    assert all((run / "ingest" / p).is_file() for row in part.image_paths for p in row if p)
    capsys.readouterr()
    assert main(["ingest", str(log), "-o", str(tmp_path / "none"), "-q", "--set",
                 "ingest.start_s=100"]) != 0
    err = capsys.readouterr().err
    assert "no frame from 100 s" in err and "ingest.start_s" in err and "12 frames span" in err
