"""Pose conventions of real recordings (sim/conventions.py): one simulated log rewritten as
transforms, as a navigation system's TF tree (tracker, markers, hand-eye on /tf_static), with
the cameras in the tracker's frame, and with the tool in the robot's base frame. Ingest
must give the same poses, tool poses and images as the plain log, in every encoding, and the
whole pipeline the same scores; a frame it cannot connect to the world is refused in one
line."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from surgrecon_cli.cli.main import main
from surgrecon_cli.io.run.ingest_store import load_ingested
from surgrecon_cli.sim.conventions import CONVENTIONS
from surgrecon_cli.sim.scene import SimConfig
from surgrecon_cli.sim.simulate import simulate

SMALL = SimConfig(cameras=3, frames=3, width=160, height=120, seed=3)
PIPELINE = SimConfig(cameras=6, frames=6, width=320, height=240)  # = conftest's pipeline_log


def _settings(convention: str) -> list[str]:
    return [arg for s in CONVENTIONS[convention].settings for arg in ("--set", s)]


def _ingest(log: Path, run: Path, *extra: str) -> int:
    return main(["ingest", str(log), "-o", str(run), "-q", *extra])


@pytest.fixture(scope="module")
def plain(tmp_path_factory: pytest.TempPathFactory):
    root = tmp_path_factory.mktemp("plain")
    simulate(root / "plain.mcap", SMALL)
    assert _ingest(root / "plain.mcap", root / "run") == 0
    return load_ingested(root / "run" / "ingest")


@pytest.mark.parametrize("encoding", ["ros2", "ros1", "foxglove-protobuf"])
@pytest.mark.parametrize("convention", [c for c in CONVENTIONS if c != "topics"])
def test_every_convention_ingests_as_the_plain_log(plain, tmp_path: Path, convention: str,
                                                   encoding: str):
    log = tmp_path / "log.mcap"
    simulate(log, SMALL, encoding=encoding, convention=convention)
    assert _ingest(log, tmp_path / "run", *_settings(convention)) == 0
    got = load_ingested(tmp_path / "run" / "ingest")
    np.testing.assert_array_equal(got.usable, plain.usable)
    np.testing.assert_allclose(got.poses, plain.poses, atol=1e-9)
    np.testing.assert_allclose(got.tool_poses, plain.tool_poses, atol=1e-9)
    np.testing.assert_array_equal(got.image_stamps_ns, plain.image_stamps_ns)
    for c in range(len(plain.cameras)):
        np.testing.assert_array_equal(got.load_image(1, c), plain.load_image(1, c))


def _drop_static(convention: str, child: str):
    """The convention's rewrite without the static transform whose child is `child`."""
    rewrite = CONVENTIONS[convention].rewrite
    assert rewrite is not None

    def rewritten(messages):
        return (m for m in rewrite(messages)
                if not (m[0] == "/tf_static" and m[2].child_frame_id == child))

    return rewritten


@pytest.mark.parametrize(("convention", "child", "named"), [
    ("tracker-frame", "tracker", ("'tracker'", "topics.world_frame = 'world'")),
    ("tf-tree", "endoscope_0_optical", ("'endoscope_0_optical'", "topics.camera_frame")),
])
def test_a_frame_not_connected_to_the_world_is_refused(tmp_path: Path, capsys, monkeypatch,
                                                       convention: str, child: str,
                                                       named: tuple[str, ...]):
    log = tmp_path / "log.mcap"
    monkeypatch.setitem(CONVENTIONS, "broken", CONVENTIONS[convention].__class__(
        _drop_static(convention, child), CONVENTIONS[convention].settings))
    simulate(log, SMALL, convention="broken")
    assert _ingest(log, tmp_path / "run", *_settings(convention)) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and all(n in err for n in named), err
    assert not (tmp_path / "run" / "ingest").exists()


def _scores(run: Path) -> dict:
    evaluation = json.loads((run / "metrics" / "evaluation.json").read_text())
    evaluation.pop("ground_truth")
    return evaluation


@pytest.mark.slow
@pytest.mark.parametrize("convention", ["tf-tree", "robot-base"])
def test_the_pipeline_scores_the_same_in_another_convention(pipeline_run, tmp_path: Path,
                                                            convention: str):
    """A non-identity base frame (tool.base_to_world) and a TF tree through every stage:
    the tool is where the plain log has it (applied once), so the scores are the same."""
    log = tmp_path / "log.mcap"
    simulate(log, PIPELINE, convention=convention)
    run = tmp_path / "run"
    assert main(["run", str(log), "-o", str(run), "-q", *_settings(convention)]) == 0
    plain, got = _scores(pipeline_run[0]), _scores(run)
    assert got["template"]["points"] == plain["template"]["points"]
    assert got["template"]["on_tool"] == plain["template"]["on_tool"]
    for part in ("template", "registration", "labels"):
        assert _close(plain[part], got[part]), part


def _close(a, b, tol: float = 1e-6) -> bool:
    """Nested JSON values equal, numbers within `tol` (relative or absolute)."""
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_close(a[k], b[k], tol) for k in a)
    if isinstance(a, list):
        return len(a) == len(b) and all(_close(x, y, tol) for x, y in zip(a, b, strict=True))
    if isinstance(a, float) or isinstance(b, float):
        return abs(a - b) <= tol * max(1.0, abs(a))
    return a == b
