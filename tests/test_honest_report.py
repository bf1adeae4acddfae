"""The report never claims more than its own numbers: the quality verdict follows the measured
calibration (ground truth) or the residual statistics, and whatever damaged or altered the
run (--allow-truncated, --force, failed frames) is recorded and boxed at the top."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
import synth_log
from synth_log import SynthSpec

from surgrecon_cli.cli.main import main
from surgrecon_cli.config import Config
from surgrecon_cli.core.classify.quality import (
    FrameFit,
    frame_quality,
    pooled_within_2sigma,
    verdict,
)
from surgrecon_cli.io.run.folder import RunFolder
from surgrecon_cli.io.run.ingest_store import load_ingested
from surgrecon_cli.report.caveats import run_caveats
from surgrecon_cli.stages.report import run_report


def test_verdict_follows_measured_calibration():
    # the stereo run of issue 22: residuals look fine, the truth does not
    bad = verdict(0.94, 0.05, calibration_2sigma=0.69, sigma_scale_95=2.4)
    assert not bad.fits and bad.basis == "ground truth"
    assert "69%" in bad.text and "2.4× larger" in bad.text and "fits" not in bad.text
    good = verdict(0.94, 0.9, calibration_2sigma=0.96)
    assert good.fits and "96%" in good.text


def test_verdict_without_ground_truth_reads_the_residuals():
    wide = verdict(0.40, 4.0)
    assert not wide.fits and "4.0× larger than the noise model expects" in wide.text
    assert "40%" in wide.text
    fine = verdict(0.96, 0.9)
    assert fine.fits and "not whether the targets themselves are right" in fine.text
    tight = verdict(0.99, 0.05)
    assert tight.fits and "say little about accuracy" in tight.text


def test_residual_share_within_2sigma_is_measured():
    # residual / σ_target = 0, 1, 3, 5 on four points with a target: half within 2σ
    n = 5
    sigma = np.full(n, 1e-3)
    residual = np.array([0.0, 1e-3, 3e-3, 5e-3, np.nan])
    status = np.zeros(n, np.uint8)
    q = frame_quality(1, FrameFit(status, sigma, residual, sigma, False, True))
    assert q.within_2sigma == pytest.approx(0.5) and q.with_target == 4
    q2 = frame_quality(2, FrameFit(status, sigma, np.zeros(n), sigma, False, True))
    share, _ = pooled_within_2sigma([q, q2])
    assert share == pytest.approx((2 + 5) / (4 + 5))


def test_caveats_from_run_json():
    run = {"stages": {"ingest": {"truncated": "the file ends inside a record", "frames": 3,
                                 "replaced": "replaced the run of a.mcap (another log)"},
                      "register": {"frames_failed": {"4": "no target", "2": "diverged"}}}}
    text = run_caveats(run, {"frames_dropped_after_damage": 1})
    assert len(text) == 3
    assert "--allow-truncated" in text[0] and "3 frames kept" in text[0]
    assert "1 incomplete" in text[0]
    assert text[1].startswith("--force: replaced the run of a.mcap")
    assert "2 frames could not be registered (frame 2: diverged; frame 4: no target)" in text[2]
    assert run_caveats({"stages": {"ingest": {"truncated": None}}}, {}) == []


def test_truncated_and_forced_ingests_are_recorded(tmp_path: Path):
    full = synth_log.write(tmp_path / "full.mcap", SynthSpec(frames=12), chunk_size=4096)
    data = full.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * 0.6)])
    run = tmp_path / "run"
    assert main(["ingest", str(cut), "-o", str(run), "-q", "--allow-truncated"]) == 0
    info = RunFolder(run).read()
    caveats = run_caveats(info, load_ingested(run / "ingest").report)
    assert len(caveats) == 1 and "--allow-truncated" in caveats[0]
    assert isinstance(info["stages"]["ingest"]["seconds"], float)
    assert main(["ingest", str(full), "-o", str(run), "-q", "--force"]) == 0
    caveats = run_caveats(RunFolder(run).read(), load_ingested(run / "ingest").report)
    assert caveats == [f"--force: replaced the run of {cut.resolve()} (another log) in this "
                       "folder."]
    # damage after the data section: every message read, and said so
    salvaged = tmp_path / "salvaged.mcap"
    salvaged.write_bytes(full.read_bytes()[:-20])
    assert main(["ingest", str(salvaged), "-o", str(tmp_path / "s"), "-q"]) == 0
    (caveat,) = run_caveats(RunFolder(tmp_path / "s").read(), {})
    assert caveat.startswith("Damaged log salvaged: salvaged.mcap") and "every message" in caveat
    # the same log again, --force: nothing was lost, nothing to say
    assert main(["ingest", str(full), "-o", str(run), "-q", "--force"]) == 0
    assert run_caveats(RunFolder(run).read(), {}) == []


def _quality_text(html: str) -> str:
    return re.search(r'<section id="quality">(.*?)</section>', html, re.S).group(1)


def test_report_boxes_caveats_and_words_the_verdict(copy_run: Path):
    folder = RunFolder(copy_run)
    data = folder.read()
    data["stages"]["ingest"]["truncated"] = "the file ends inside a record"
    data["stages"]["register"]["frames_failed"] = {"3": "no target points"}
    folder.write(data)
    evaluation = copy_run / "metrics" / "evaluation.json"
    ev = json.loads(evaluation.read_text())
    ev["labels"]["calibration_2sigma"], ev["labels"]["sigma_scale_95"] = 0.69, 2.5
    evaluation.write_text(json.dumps(ev))
    files = run_report(copy_run, Config())
    html = files.html.read_text()
    box = html.index('<div class="caveats"')
    assert box < html.index("<section")
    assert "--allow-truncated" in html[box:] and "frame 3: no target points" in html[box:]
    quality = _quality_text(html)
    assert "fits within its noise" not in quality
    assert "only 69% of labelled points are within 2σ of the truth" in quality
    summary = json.loads(files.summary_json.read_text())
    assert len(summary["caveats"]) == 2
    assert RunFolder(copy_run).stage("report")["caveats"] == summary["caveats"]
    assert summary["quality"]["verdict"]["fits"] is False
    assert summary["quality"]["verdict"]["basis"] == "ground truth"


def test_a_truth_with_holes_is_said_to_cover_part_of_the_template(copy_run: Path):
    """The calibration of a run against a truth with holes counts the points it covers
    (evaluate); the verdict and the overview say how many those are."""
    evaluation = copy_run / "metrics" / "evaluation.json"
    ev = json.loads(evaluation.read_text())
    ev["labels"]["calibration_2sigma"], ev["labels"]["truth_covered_fraction"] = 0.97, 0.65
    evaluation.write_text(json.dumps(ev))
    files = run_report(copy_run, Config())
    verdict = json.loads(files.summary_json.read_text())["quality"]["verdict"]
    assert verdict["fits"] is True
    assert "The truth covers 65% of the template points" in verdict["text"]
    assert "within 2σ of the truth (95 % expected, of the 65% it covers)" in (
        files.html.read_text())


def test_report_stage_table_and_file_links(pipeline_run):
    run_dir, _ = pipeline_run
    html = (run_dir / "report.html").read_text()
    row = re.search(r"<tr><td>ingest</td><td>done</td><td>([^<]*)</td></tr>", html)
    assert row is not None and float(row.group(1)) > 0
    files = re.search(r'<section id="files">(.*?)</section>', html, re.S).group(1)
    links = re.findall(r'<a href="([^"]+)">', files)
    assert {"template.ply", "clouds", "metrics/summary.json", "run.json"} <= set(links)
    assert all(not link.startswith("/") and ":" not in link for link in links)
    assert all((run_dir / link).exists() for link in links)


def test_ingest_warnings_reach_the_report(tmp_path: Path):
    """What ingest warned about on the terminal is kept in its report and listed among the
    run's caveats (the report's box and summary.json), not lost with the terminal."""
    log = synth_log.write(tmp_path / "log.mcap", SynthSpec(frames=3))
    run = tmp_path / "run"
    assert main(["ingest", str(log), "-o", str(run), "-q", "--set", 'topics.tool_pose=""']) == 0
    report = load_ingested(run / "ingest").report
    assert any("no robot kinematics" in w for w in report["warnings"])
    caveats = run_caveats(RunFolder(run).read(), report)
    assert any(c.startswith("Ingest warned: ") and "tool removal is off" in c for c in caveats)
    many = {"warnings": [f"camera a: a message is lost before frame {k}" for k in range(25)]}
    listed = run_caveats({}, many)
    assert len(listed) == 11 and listed[-1].startswith("Ingest warned 15 more times")
