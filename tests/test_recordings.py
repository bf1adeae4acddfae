"""Real recordings: a log without robot kinematics, configured topics that are missing,
streams on different clocks, zero header stamps, and a run folder of another log."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import synth_log
from synth_log import SynthSpec

from surgrecon_cli.cli.main import main
from surgrecon_cli.io.logs.records import PoseRecord
from surgrecon_cli.io.run.ingest_store import load_ingested


def ingest(log: Path, run: Path, *extra: str) -> int:
    return main(["ingest", str(log), "-o", str(run), "--quiet", *extra])


def test_a_log_without_robot_runs_with_tool_removal_off(pipeline_log: Path, tmp_path: Path,
                                                         capsys):
    run = tmp_path / "run"
    code = main(["run", str(pipeline_log), "-o", str(run), "-q", "--set", 'topics.tool_pose=""',
                 "--set", 'topics.joint_states=""'])
    assert code == 0, capsys.readouterr().err
    log = load_ingested(run / "ingest")
    assert np.isnan(log.tool_poses).all() and log.report["robot"] is False
    assert "tool removal is off" in capsys.readouterr().err
    assert "No robot kinematics" in (run / "report.html").read_text(encoding="utf-8")


def test_a_configured_robot_topic_missing_from_the_log_is_an_error(tmp_path: Path, capsys):
    log = synth_log.write(tmp_path / "log.mcap", SynthSpec(tool_topic="/psm1/measured_cp"))
    assert ingest(log, tmp_path / "run") == 2
    err = capsys.readouterr().err
    assert "topics.tool_pose = '/raven/tool_tip'" in err and "/psm1/measured_cp" in err
    log = synth_log.write(tmp_path / "j.mcap", SynthSpec(joint_topic="/raven/joint_state"))
    assert ingest(log, tmp_path / "run_j") == 2
    assert "topics.joint_states = '/raven/joint_states'" in capsys.readouterr().err
    assert ingest(log, tmp_path / "run_k", "--set", 'topics.joint_states=""') == 0


def test_streams_on_different_clocks_fail_at_once_naming_them(tmp_path: Path, capsys):
    hour = 3600 * 10**9

    def poses_on_another_clock(messages):
        return [(topic, t, dataclasses.replace(r, stamp_ns=r.stamp_ns + hour))
                if isinstance(r, PoseRecord) and "navigation" in topic else (topic, t, r)
                for topic, t, r in messages]

    log = synth_log.write(tmp_path / "log.mcap", SynthSpec(mutate=poses_on_another_clock))
    assert ingest(log, tmp_path / "run") == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert "different clocks" in err and "/navigation/endoscope_0/pose" in err
    assert "header stamps" in err and "ingest.time_source=log_time" in err


def test_zero_header_stamps_are_named_once_per_channel(tmp_path: Path, capsys):
    def zero_image_stamps(messages):
        return [(topic, t, dataclasses.replace(r, stamp_ns=0)) if "color" in topic
                else (topic, t, r) for topic, t, r in messages]

    log = synth_log.write(tmp_path / "log.mcap", SynthSpec(mutate=zero_image_stamps))
    assert ingest(log, tmp_path / "run") == 0
    warned = [line for line in capsys.readouterr().err.splitlines()
              if "zero header stamp" in line]
    spec = SynthSpec()
    assert len(warned) == len(spec.cameras)
    assert all("log time" in w for w in warned)


def test_a_run_folder_of_another_log_is_refused_unless_forced(tmp_path: Path, capsys):
    first = synth_log.write(tmp_path / "a.mcap", SynthSpec())
    other = synth_log.write(tmp_path / "b.mcap", SynthSpec(frames=SynthSpec().frames - 1))
    run = tmp_path / "run"
    assert ingest(first, run) == 0
    stamp = (run / "ingest" / "frames.npz").stat().st_mtime_ns
    assert main(["run", str(other), "-o", str(run), "-q"]) == 2
    err = capsys.readouterr().err
    assert "--force" in err and "a.mcap" in err
    assert (run / "ingest" / "frames.npz").stat().st_mtime_ns == stamp  # nothing lost


def test_tagged_runs_of_one_log_sit_side_by_side(tmp_path: Path):
    from surgrecon_cli.errors import InputError
    from surgrecon_cli.pipeline import run_folders_for, tagged

    # beside the run, not inside it (issue 22)
    assert tagged(tmp_path, "") == tmp_path
    assert tagged(tmp_path / "run", "a0.2") == tmp_path / "run-a0.2"
    logs = [tmp_path / "x.mcap", tmp_path / "bag"]
    assert run_folders_for(logs, tmp_path / "runs", "strict") == [
        tmp_path / "runs" / "x-strict", tmp_path / "runs" / "bag-strict"]
    for bad in ("..", "a/b", "a\\b", "a\nb"):
        try:
            tagged(tmp_path, bad)
        except InputError as exc:
            assert "--tag" in str(exc)
        else:
            raise AssertionError(f"tag {bad!r} accepted")
