"""`surgrecon info`: channel table, TF tree, role candidates and `--write-config`, on the
shipped sample, on simulated logs, on a log with a TF tree, and on damaged logs."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import synth_log

from surgrecon_cli.cli.main import main
from surgrecon_cli.config import TopicsConfig, load_config
from surgrecon_cli.core.geometry.poses import invert_pose, make_pose, matrix_to_quat
from surgrecon_cli.info import camera_pattern, scan_log
from surgrecon_cli.io.logs.records import PoseRecord
from surgrecon_cli.io.run.ingest_store import load_ingested

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "sample_data" / "sample.mcap"
T0 = synth_log.T0
MS = synth_log.MS


def _info(capsys, *args: str) -> str:
    assert main(["info", *map(str, args)]) == 0
    return capsys.readouterr().out


# -- the shipped sample and simulated logs ---------------------------------------------------
def test_sample_log(tmp_path: Path, capsys):
    cfg = tmp_path / "topics.toml"
    out = _info(capsys, SAMPLE, "--write-config", cfg)
    lines = out.splitlines()
    assert "2000 messages on 20 channels, 4.000 s" in lines[0]
    assert "read from the summary and message indexes" in lines[1]
    row = next(line.split() for line in lines if line.startswith("  /navigation/endoscope_3/pose"))
    assert row[1:6] == ["geometry_msgs/msg/PoseStamped", "cdr", "160", "40.0", "3.98"]
    row = next(line.split() for line in lines if line.startswith("  /endoscope_0/color/compr"))
    assert row[1:6] == ["sensor_msgs/msg/CompressedImage", "cdr", "20", "5.0", "3.80"]
    assert "TF tree: none" in out
    assert "cameras 0 1 2 3 4 5; frame endoscope_{camera}_optical" in out
    assert "the config's [topics] find every role in this log" in out
    assert load_config(cfg).topics == TopicsConfig()


def test_info_reads_an_indexed_log_from_its_indexes():
    assert scan_log(SAMPLE).indexed


@pytest.fixture(scope="module")
def sim_logs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    from surgrecon_cli.sim.scene import SimConfig
    from surgrecon_cli.sim.simulate import simulate

    folder = tmp_path_factory.mktemp("sim")
    cfg = SimConfig(cameras=3, frames=2, width=64, height=48)
    out = {}
    for name, encoding, tf in (("ros2", "ros2", False), ("json", "foxglove-json", False),
                               ("tf", "ros2", True)):
        out[name] = folder / f"{name}.mcap"
        simulate(out[name], cfg, encoding=encoding, convention="tf" if tf else "topics")
    return out


@pytest.mark.parametrize("name", ["ros2", "json"])
def test_simulated_log_gives_the_default_topics(sim_logs, name: str, tmp_path: Path, capsys):
    cfg = tmp_path / "topics.toml"
    _info(capsys, sim_logs[name], "--write-config", cfg)
    assert load_config(cfg).topics == TopicsConfig()


def test_simulated_tf_log_gives_tf_topics_that_ingest_runs_with(sim_logs, tmp_path: Path,
                                                                capsys):
    cfg = tmp_path / "topics.toml"
    out = _info(capsys, sim_logs["tf"], "--write-config", cfg)
    assert "TF tree from /tf dynamic: 5 frames, root world" in out
    assert load_config(cfg).topics == TopicsConfig(camera_pose="/tf", tool_pose="/tf")
    assert "topics.camera_pose = '/navigation/endoscope_{camera}/pose' matches no topic" in out
    assert main(["ingest", str(sim_logs["tf"]), "-o", str(tmp_path / "run"), "--config",
                 str(cfg), "-q"]) == 0


# -- a log with a TF tree ------------------------------------------------------------------
WORLD_TRACKER = make_pose(np.array([0.5, -0.2, 1.0]), np.array([0, 0, np.sin(0.35),
                                                                  np.cos(0.35)]))
WORLD_BASE = make_pose(np.array([-0.3, 0.4, 0.2]), np.array([0.0, 0, 0, 1]))
HAND_EYE = make_pose(np.array([0.0, 0.02, 0.15]), np.array([np.sin(0.1), 0, 0, np.cos(0.1)]))


def _record(stamp: int, parent: str, child: str, T: np.ndarray) -> PoseRecord:
    return PoseRecord(stamp, parent, child, T[:3, 3], matrix_to_quat(T[:3, :3]))


def _to_tree(messages):
    """Camera poses world -> endoscope_c_optical become tracker -> endoscope_c_marker (/tf)
    with a static hand-eye marker -> optical; the tool world -> tip becomes psm1_base -> tip;
    static world -> tracker and world -> psm1_base on /tf_static."""
    out = []
    for topic, t, rec in messages:
        if topic == "/tf" and rec.child_frame_id.endswith("_optical"):
            P = make_pose(rec.position, rec.orientation)
            M = invert_pose(WORLD_TRACKER) @ P @ invert_pose(HAND_EYE)
            rec = _record(rec.stamp_ns, "tracker", rec.child_frame_id[:-8] + "_marker", M)
        elif topic == "/tf":
            P = make_pose(rec.position, rec.orientation)
            rec = _record(rec.stamp_ns, "psm1_base", rec.child_frame_id,
                          invert_pose(WORLD_BASE) @ P)
        out.append((topic, t, rec))
    statics = [_record(T0, "world", "tracker", WORLD_TRACKER),
               _record(T0, "world", "psm1_base", WORLD_BASE)]
    statics += [_record(T0, f"endoscope_{c}_marker", f"endoscope_{c}_optical", HAND_EYE)
                for c in (0, 1, 2)]
    return [("/tf_static", T0, r) for r in statics] + out


def write_tree_log(path: Path, encoding: str = "ros2") -> Path:
    spec = synth_log.SynthSpec(
        tf_topic="/tf", tool_frame="psm1_tool_tip", image_topic="/endoscope_{c}/image_raw",
        image_format="rgb8", info_topic="/endoscope_{c}/camera_info",
        joint_topic="/psm1/joint_states", mutate=_to_tree)
    return synth_log.write(path, spec, encoding)


@pytest.mark.parametrize("encoding", ["ros2", "ros1", "foxglove-protobuf"])
def test_tf_tree_log(tmp_path: Path, capsys, encoding: str):
    log = write_tree_log(tmp_path / "tree.mcap", encoding)
    cfg = tmp_path / "topics.toml"
    out = _info(capsys, log, "--write-config", cfg)
    assert "TF tree from /tf dynamic, /tf_static static: 10 frames, root world:" in out
    tree = out.split("TF tree from")[1].split("\n\n")[0].splitlines()[1:]
    rows = {line.split()[0]: line.split() for line in tree[1:]}
    assert tree[1].split() == ["world", "-", "root"]
    assert rows["tracker"][1:4] == ["world", "static", "1"]
    assert rows["endoscope_1_marker"][1:] == ["tracker", "dynamic", "25", "25.0", "0.96"]
    assert rows["endoscope_1_optical"][1:4] == ["endoscope_1_marker", "static", "1"]
    assert rows["psm1_tool_tip"][1:] == ["psm1_base", "dynamic", "20", "20.0", "0.95"]
    indent = {line.split()[0]: len(line) - len(line.lstrip()) for line in tree[1:]}
    assert indent["endoscope_0_optical"] == indent["endoscope_0_marker"] + 2 == (
        indent["tracker"] + 4)
    topics = load_config(cfg).topics
    assert topics == TopicsConfig(
        image="/endoscope_{camera}/image_raw", camera_info="/endoscope_{camera}/camera_info",
        camera_pose="/tf", camera_frame="endoscope_{camera}_optical", tool_pose="/tf",
        tool_frame="psm1_tool_tip", joint_states="/psm1/joint_states")
    info = scan_log(log)
    assert info.world_frame == "world" and info.role("camera_pose").cameras == ("0", "1", "2")
    # the tree reproduces the written camera poses at their stamps
    stamps = np.arange(T0, T0 + 1000 * MS, 40 * MS)
    got = info.tf_tree.lookup("world", "endoscope_2_optical", stamps, 100 * MS)
    np.testing.assert_allclose(got, synth_log.camera_pose(2, stamps), atol=1e-9)


def test_an_edge_left_out_of_the_tree_is_reported(tmp_path: Path, capsys):
    log = tmp_path / "bad.mcap"
    spec = synth_log.SynthSpec(tf_topic="/tf", extra=[
        ("/tf", T0 + 5 * MS, PoseRecord(T0, "map", "endoscope_1_optical", np.zeros(3),
                                        np.array([0.0, 0, 0, 1])))])
    synth_log.write(log, spec)
    out = _info(capsys, log)
    assert "left out: TF frame 'endoscope_1_optical' has 2 parents: 'map'" in out


# -- damaged and unindexed logs, config file handling --------------------------------------
def test_truncated_log_is_streamed_and_the_damage_reported(tmp_path: Path, capsys):
    log = write_tree_log(tmp_path / "tree.mcap")
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(log.read_bytes()[: log.stat().st_size // 2])
    out = _info(capsys, cut)
    assert "no usable index: streamed" in out and "damaged log: valid data ends at byte" in out
    assert "TF tree from /tf" in out
    full = {c.topic: c.count for c in scan_log(log).channels}
    part = {c.topic: c.count for c in scan_log(cut).channels}
    assert 0 < sum(part.values()) < sum(full.values())
    assert all(part[t] <= full[t] for t in part)


def test_corrupt_chunk_of_an_indexed_log_is_reported(tmp_path: Path, capsys):
    from surgrecon_cli.errors import InputError
    from surgrecon_cli.io.logs.transforms import read_transforms

    log = write_tree_log(tmp_path / "tree.mcap")
    data = bytearray(log.read_bytes())
    middle = len(data) // 2
    data[middle : middle + 64] = bytes(64)
    log.write_bytes(bytes(data))
    out = _info(capsys, log)
    assert "read from the summary" in out and "damaged log: the chunk at byte" in out
    with pytest.raises(InputError, match="damaged log: the chunk at byte"):
        read_transforms(log)


def test_write_config_keeps_an_existing_file(tmp_path: Path, capsys):
    cfg = tmp_path / "topics.toml"
    cfg.write_text("# mine\n")
    assert main(["info", str(SAMPLE), "--write-config", str(cfg)]) == 2
    assert "exists; pass --force" in capsys.readouterr().err
    assert cfg.read_text() == "# mine\n"
    assert main(["info", str(SAMPLE), "--write-config", str(cfg), "--force", "-q"]) == 0
    assert load_config(cfg).topics == TopicsConfig()


def test_not_an_mcap_file(tmp_path: Path, capsys):
    path = tmp_path / "x.mcap"
    path.write_text("a bag\n")
    assert main(["info", str(path)]) == 2
    assert "not an MCAP file" in capsys.readouterr().err


# -- camera-id patterns ----------------------------------------------------------------------
@pytest.mark.parametrize(("names", "ids", "pattern", "captured"), [
    (["/endoscope_0/color/compressed", "/endoscope_1/color/compressed"], (),
     "/endoscope_{camera}/color/compressed", ["0", "1"]),
    (["/endoscope_10/image", "/endoscope_11/image", "/endoscope_12/image"], (),
     "/endoscope_{camera}/image", ["10", "11", "12"]),
    (["/stereo/left/image_raw", "/stereo/right/image_raw"], (), "/stereo/{camera}/image_raw",
     ["left", "right"]),
    (["/cam0/image_raw", "/cam1/image_raw", "/cam0/image_rect_color", "/cam1/image_rect_color"],
     (), "/{camera}/image_rect_color", ["cam0", "cam1"]),
    (["/tracker/cam0_pose", "/tracker/cam1_pose", "/psm1/tool"], ("cam0", "cam1"),
     "/tracker/{camera}_pose", ["cam0", "cam1"]),
    (["/navigation/endoscope_0/pose", "/navigation/endoscope_1/pose", "/psm1/tip"], ("0", "1"),
     "/navigation/endoscope_{camera}/pose", ["0", "1"]),
    (["/robot/tool_tip"], ("0", "1"), "", []),
])
def test_camera_pattern(names, ids, pattern, captured):
    got, caps = camera_pattern(names, ids, prefer=("compressed", "color", "rect"))
    assert got == pattern and sorted(caps.values()) == captured


def test_a_ros_stereo_pair_without_poses_is_placed_by_its_camera_info(tmp_path: Path, capsys):
    # No pose topic, CameraInfo with a stereo R and P: info suggests camera_pose =
    # "camera_info", and the config it writes ingests the pair where its extrinsics put it.
    log = synth_log.write(tmp_path / "log.mcap", synth_log.SynthSpec(
        cameras=(0, 1), mutate=synth_log.ros_stereo))
    cfg = tmp_path / "stereo.toml"
    out = _info(capsys, log, "--write-config", cfg)
    assert "stereo baseline 5.5 mm" in out
    assert "its CameraInfo R and P, fixed in world" in out
    assert load_config(cfg).topics.camera_pose == "camera_info"
    assert main(["ingest", str(log), "-o", str(tmp_path / "run"), "--config", str(cfg),
                 "--quiet"]) == 0
    right = load_ingested(tmp_path / "run" / "ingest").poses[0, 1]
    np.testing.assert_allclose(right[:3, 3], -synth_log.STEREO_R.T @ synth_log.STEREO_T,
                               atol=1e-9)
