"""ROS 1 `.bag` and ROS 2 sqlite3 `.db3` bags are read directly (through rosbags): the
simulator's log written as MCAP, then converted to a `.db3` bag folder, a lone `.db3` file
and a ROS 1 `.bag` (CDR converted to ROS 1 wire format), ingests identically: same frames,
stamps to the nanosecond, poses to 1e-9, images byte-equal after decoding."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import synth_log
from rosbag_convert import mcap_to_bag, mcap_to_db3

from surgrecon_cli.cli.main import main
from surgrecon_cli.info import scan_log
from surgrecon_cli.io.run.ingest_store import load_ingested
from surgrecon_cli.sim.log_writer import write_log
from surgrecon_cli.sim.scene import SimConfig
from surgrecon_cli.sim.simulate import LogBuilder

CFG = SimConfig(cameras=3, frames=3, width=160, height=120, seed=7)
TF_CONFIG = ('[topics]\nimage = "/endoscope_{camera}/color/compressed"\n'
             'camera_info = "/endoscope_{camera}/calibration"\ncamera_pose = "/tf"\n'
             'camera_frame = "endoscope_{camera}_optical"\ntool_pose = "/tf"\n'
             'tool_frame = "raven_tool_tip"\njoint_states = "/raven/joint_states"\n')


@pytest.fixture(scope="module")
def logs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The simulator's log (poses on PoseStamped topics) and a synthetic one with raw images
    and poses on /tf, each as MCAP, .db3 bag folder and ROS 1 .bag."""
    root = tmp_path_factory.mktemp("rosbags")
    sim = root / "sim.mcap"
    write_log(sim, list(LogBuilder(CFG).messages()), "ros2")
    tf = synth_log.write(root / "tf.mcap", synth_log.SynthSpec(tf_topic="/tf", frames=3,
                                                               image_format="rgb8"))
    out = {"sim": sim, "tf": tf}
    for name, mcap in (("sim", sim), ("tf", tf)):
        out[f"{name}_db3"] = mcap_to_db3(mcap, root / f"{name}_db3")
        out[f"{name}_bag"] = mcap_to_bag(mcap, root / f"{name}.bag")
    (root / "tf.toml").write_text(TF_CONFIG)
    return out


def _ingest(log: Path, run: Path) -> Path:
    args = ["ingest", str(log), "-o", str(run), "-q"]
    if log.name.startswith("tf"):
        args += ["--config", str(log.parent / "tf.toml")]
    assert main(args) == 0
    return run


def _assert_same(run: Path, reference: Path) -> None:
    got, want = load_ingested(run / "ingest"), load_ingested(reference / "ingest")
    assert got.cameras == want.cameras and got.n_frames == want.n_frames > 0
    np.testing.assert_array_equal(got.stamps_ns, want.stamps_ns)
    np.testing.assert_array_equal(got.image_stamps_ns, want.image_stamps_ns)
    np.testing.assert_allclose(got.poses, want.poses, rtol=0, atol=1e-9)
    np.testing.assert_allclose(got.tool_poses, want.tool_poses, rtol=0, atol=1e-9)
    np.testing.assert_allclose(got.joint_positions, want.joint_positions, rtol=0, atol=1e-9)
    for a, b in zip(got.models, want.models, strict=True):
        np.testing.assert_array_equal(a.K, b.K)
    for k in range(want.n_frames):
        for c in range(len(want.cameras)):
            assert np.array_equal(got.load_image(k, c), want.load_image(k, c))


@pytest.mark.parametrize("name", ["sim", "tf"])
def test_bags_ingest_like_the_mcap(logs: dict[str, Path], tmp_path: Path, name: str):
    reference = _ingest(logs[name], tmp_path / "mcap")
    lone = tmp_path / f"{name}_lone.db3"  # a .db3 file named without its bag folder
    shutil.copy(next(logs[f"{name}_db3"].glob("*.db3")), lone)
    (tmp_path / "tf.toml").write_text(TF_CONFIG)
    for kind, log in (("bag", logs[f"{name}_bag"]), ("db3", logs[f"{name}_db3"]),
                      ("db3_file", lone)):
        _assert_same(_ingest(log, tmp_path / kind), reference)


def test_info_describes_a_bag_like_the_mcap(logs: dict[str, Path]):
    want = scan_log(logs["tf"])
    for kind in ("tf_bag", "tf_db3"):
        got = scan_log(logs[kind])
        assert got.topics == want.topics
        assert {c.topic: c.count for c in got.channels} == {c.topic: c.count
                                                            for c in want.channels}
        assert got.tf_tree is not None and set(got.tf_tree.frames) == set(want.tf_tree.frames)


def test_a_damaged_bag_is_refused_in_one_line(logs: dict[str, Path], tmp_path: Path, capsys):
    bad = tmp_path / "bad.bag"
    bad.write_bytes(logs["sim_bag"].read_bytes()[:3000])
    not_bag = tmp_path / "x.db3"
    not_bag.write_bytes(b"hello, not sqlite")
    for log in (bad, not_bag):
        assert main(["ingest", str(log), "-o", str(tmp_path / f"run_{log.stem}"), "-q"]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and str(log) in err, err


def test_a_db3_without_message_definitions_ingests_alike(logs: dict[str, Path], tmp_path: Path):
    """rosbag2 before Iron stored no message definitions: they come from rosbags' types."""
    import sqlite3

    old = tmp_path / "sim_old"
    shutil.copytree(logs["sim_db3"], old)
    with sqlite3.connect(next(old.glob("*.db3"))) as db:
        db.execute("DELETE FROM message_definitions")
    reference = _ingest(logs["sim"], tmp_path / "mcap")
    _assert_same(_ingest(old, tmp_path / "old"), reference)
