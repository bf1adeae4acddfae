"""What a new user meets in the first hour, each said in one line: a log without camera images
(`info` says so and writes no config; ingest does not send the user back to `info`), channels
without a rate (one message, a burst within nanoseconds), a Git LFS pointer in place of a log
or ground truth, a `topics.world_frame` the TF tree lacks, and progress bars on a pipe."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest
import synth_log

from surgrecon_cli.cli.common import progress
from surgrecon_cli.cli.main import main
from surgrecon_cli.core.sync import streams as sync
from surgrecon_cli.errors import InputError
from surgrecon_cli.io.logs.ground_truth import load_ground_truth
from surgrecon_cli.io.logs.records import PoseRecord
from surgrecon_cli.sim.log_writer import write_log

T0, MS = synth_log.T0, synth_log.MS
LFS_POINTER = ("version https://git-lfs.github.com/spec/v1\n"
               "oid sha256:4d7a214614ab2935c943f9e0ff69d22eadbb8f32b1258daaa5e2ca24d17e2393\n"
               "size 7813509\n")


def _pose(stamp: int) -> PoseRecord:
    return PoseRecord(stamp, "world", "", np.zeros(3), np.array([0.0, 0, 0, 1]))


def _poses_only_log(path: Path) -> Path:
    """Two cameras' tracker poses at 40 Hz (0.2 s), one tool pose, and three pose messages
    3 ns apart: no image anywhere."""
    messages = [(f"/navigation/endoscope_{c}/pose", T0 + k * 25 * MS + c,
                 _pose(T0 + k * 25 * MS)) for k in range(9) for c in range(2)]
    messages.append(("/raven/tool_tip", T0 + 50 * MS, _pose(T0 + 50 * MS)))
    messages += [("/burst", T0 + 3 * k, _pose(T0)) for k in range(3)]
    write_log(path, sorted(messages, key=lambda m: m[1]), "ros2")
    return path


# -- a log without camera images ------------------------------------------------------------
def test_info_on_a_log_without_images_says_so_and_writes_no_config(tmp_path: Path, capsys):
    log = _poses_only_log(tmp_path / "poses.mcap")
    assert main(["info", str(log)]) == 0
    out = capsys.readouterr().out
    assert out.rstrip().splitlines()[-1].startswith(f"{log}: no camera images in this log")
    assert "--write-config" not in out  # nothing to write: no loop back to info
    cfg = tmp_path / "cfg.toml"
    assert main(["info", str(log), "--write-config", str(cfg)]) == 2
    err = capsys.readouterr().err
    assert "no camera images in this log" in err and f"{cfg} not written" in err
    assert not cfg.exists()


@pytest.mark.parametrize("command", ["ingest", "run"])
def test_ingesting_a_log_without_images_does_not_point_to_info(tmp_path: Path, capsys,
                                                               command: str):
    log = _poses_only_log(tmp_path / "poses.mcap")
    assert main([command, str(log), "-o", str(tmp_path / "run"), "-q"]) == 2
    err = capsys.readouterr().err
    assert "no camera images in this log" in err and "surgrecon info" not in err


# -- rates ----------------------------------------------------------------------------------
def test_one_message_or_a_burst_has_no_rate(tmp_path: Path, capsys):
    assert sync.mean_rate_hz(11, T0, T0 + 1_000_000_000) == pytest.approx(10.0)
    assert sync.mean_rate_hz(3, T0, T0 + 6) == 0.0  # 3 messages in 6 ns: no rate
    assert sync.mean_rate_hz(1, T0, T0) == 0.0
    assert sync.rate_hz(np.array([T0, T0 + 2, T0 + 5])) == 0.0
    log = _poses_only_log(tmp_path / "poses.mcap")
    assert main(["info", str(log)]) == 0
    rows = {line.split()[0]: line.split()[1:6] for line in capsys.readouterr().out.splitlines()
            if line.startswith("  /")}
    assert rows["/burst"] == ["geometry_msgs/msg/PoseStamped", "cdr", "3", "-", "0.00"]
    assert rows["/raven/tool_tip"] == ["geometry_msgs/msg/PoseStamped", "cdr", "1", "-", "0.00"]
    assert rows["/navigation/endoscope_0/pose"][3:] == ["40.0", "0.20"]


# -- Git LFS pointers -----------------------------------------------------------------------
@pytest.mark.parametrize("command", ["info", "ingest", "run"])
def test_an_lfs_pointer_log_is_named_as_such(tmp_path: Path, capsys, command: str):
    log = tmp_path / "sample.mcap"
    log.write_text(LFS_POINTER)
    run = tmp_path / "run"
    args = [command, str(log)] + (["-o", str(run)] if command != "info" else [])
    assert main(args) == 2
    err = capsys.readouterr().err
    assert f"{log}: a Git LFS pointer file, not the log itself" in err
    assert "git lfs pull" in err and "not an MCAP file" not in err
    assert not run.exists()


def test_an_lfs_pointer_among_split_files_or_as_ground_truth(tmp_path: Path, capsys):
    folder = tmp_path / "split"
    folder.mkdir()
    synth_log.write(folder / "rec_1.mcap", synth_log.SynthSpec(frames=2))
    (folder / "rec_2.mcap").write_text(LFS_POINTER)
    assert main(["info", str(folder)]) == 2
    assert f"{folder / 'rec_2.mcap'}: a Git LFS pointer file" in capsys.readouterr().err
    gt = tmp_path / "sample.gt.npz"
    gt.write_text(LFS_POINTER)
    with pytest.raises(InputError, match="a Git LFS pointer file, not the ground truth itself"):
        load_ground_truth(gt)


# -- a world frame the TF tree lacks --------------------------------------------------------
def test_a_world_frame_missing_from_the_tree_names_world_frame(tmp_path: Path, capsys):
    log = synth_log.write(tmp_path / "tf.mcap", synth_log.SynthSpec(frames=2, tf_topic="/tf"))
    sets = ["topics.camera_pose=/tf", "topics.tool_pose=/tf", "topics.world_frame=map"]
    args = [a for s in sets for a in ("--set", s)]
    assert main(["ingest", str(log), "-o", str(tmp_path / "run"), "-q", *args]) == 2
    err = capsys.readouterr().err
    assert "topics.world_frame = 'map' is not a frame of the log's TF tree (roots: world)" in err
    assert "camera_frame" not in err


# -- progress bars ----------------------------------------------------------------------------
class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_progress_bars_only_on_a_terminal(monkeypatch, tmp_path: Path, capsys):
    for stream, shown in ((io.StringIO(), False), (_Terminal(), True)):
        monkeypatch.setattr("sys.stderr", stream)
        with progress(False)(total=3, desc="work") as bar:
            bar.update(3)
        assert ("work" in stream.getvalue()) is shown
    monkeypatch.undo()
    # a command's stderr on a pipe (pytest captures it): no carriage-return bar updates
    assert main(["simulate", str(tmp_path / "s.mcap"), "--cameras", "2", "--frames", "2",
                 "--width", "64", "--height", "48"]) == 0
    captured = capsys.readouterr()
    assert "\r" not in captured.err and "wrote" in captured.out
