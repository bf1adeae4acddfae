"""A log without a robot: `simulate --no-robot` (or `--set topics.tool_pose=""`) writes no
tool pose or joint states; contact then reads "not measured" (deformation.csv, summary,
report) and `evaluate` marks the contact goals "not measured", never "MISSED"."""

from __future__ import annotations

import csv
import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from surgrecon_cli.cli.cmd_evaluate import format_evaluation
from surgrecon_cli.cli.main import main
from surgrecon_cli.config import Config
from surgrecon_cli.io.run.ingest_store import load_ingested, save_ingested
from surgrecon_cli.stages.evaluate import run_evaluate
from surgrecon_cli.stages.measure import run_measure
from surgrecon_cli.stages.report import run_report

SMALL = ["--frames", "2", "--cameras", "2", "--width", "64", "--height", "48", "-q"]


def _topics(path: Path) -> set[str]:
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    return {c.topic for c in summary.channels.values()}


@pytest.mark.parametrize("how", [["--no-robot"], ["--set", 'topics.tool_pose=""']])
def test_simulate_without_robot(tmp_path: Path, capsys, how: list[str]):
    out = tmp_path / "nr.mcap"
    assert main(["simulate", str(out), *SMALL, *how]) == 0
    topics = _topics(out)
    assert "/endoscope_0/color/compressed" in topics
    assert not {"/raven/tool_tip", "/raven/joint_states"} & topics
    assert 'topics.tool_pose=""' in capsys.readouterr().out  # how to ingest it


def test_simulate_refuses_topics_it_cannot_honour(tmp_path: Path, capsys):
    out = tmp_path / "x.mcap"
    assert main(["simulate", str(out), *SMALL, "--set", "topics.joint_states=/j"]) == 2
    assert "topics.joint_states" in capsys.readouterr().err and not out.exists()
    assert main(["simulate", str(out), *SMALL, "--set", "topics.tool_pose=/other"]) == 2
    assert not out.exists()


def test_contact_not_measured_without_tool_pose(pipeline_log: Path, copy_run: Path):
    log = load_ingested(copy_run / "ingest")
    save_ingested(dataclasses.replace(log, tool_poses=np.full_like(log.tool_poses, np.nan)))
    config = Config()
    summary = run_measure(copy_run, config)
    assert summary["contact"] == "not measured" and summary["contact_measured_frames"] == 0
    with open(copy_run / "metrics" / "deformation.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert rows and all(r["contact"] == "not measured" and r["indentation_mm"] == ""
                        for r in rows)
    ev = run_evaluate(copy_run, config, pipeline_log.with_name("sim.gt.npz"))
    goals = ev["deformation"]["goals"]
    assert set(goals.values()) == {"not measured"}
    assert "MISSED" not in format_evaluation(ev) and "not measured" in format_evaluation(ev)
    files = run_report(copy_run, config)
    html = files.html.read_text()
    contact = html[html.index('<section id="contact">'):]
    contact = contact[: contact.index("</section>")]
    assert "not measured" in contact and "missed" not in contact
    assert '<div class="v">none</div>' not in contact
    assert "<td>not measured</td><td>within 1 frame</td>" in contact  # no made-up scores
    summary_json = json.loads(files.summary_json.read_text())
    assert summary_json["deformation"]["contact"] == "not measured"
    assert set(summary_json["evaluation"]["deformation"]["goals"].values()) == {"not measured"}
