"""What a researcher trying surgrecon on their own stereo recordings runs into first (the SurgT
clip of tests/data/surgt, Apache-2.0, cut or altered the way real recordings are): a clip of
one stereo pair, a video downscaled after calibration, a calibration in the wrong unit."""

from __future__ import annotations

import json
from pathlib import Path

from surgrecon_cli.cli.main import main

SURGT = Path(__file__).parent / "data" / "surgt"


def _convert(out: Path, *args: str) -> int:
    return main(["convert", str(SURGT / "video.mp4"), "-o", str(out), "--calibration",
                 str(SURGT / "calibration.yaml"), "-q", *args])


def test_a_single_stereo_pair_runs_to_a_template_and_a_report(tmp_path: Path):
    # One frame: a template and its cloud, nothing to register; the run must finish (it
    # crashed in classify, whose folder only later frames create).
    log = tmp_path / "one.mcap"
    assert _convert(log, "--frames", "0:1") == 0
    run = tmp_path / "run"
    assert main(["run", str(log), "-o", str(run), "--config", str(log.with_suffix(".toml")),
                 "-q"]) == 0
    summary = json.loads((run / "metrics" / "summary.json").read_text(encoding="utf-8"))
    assert summary["frames"] == 1 and summary["template_points"] > 500
    assert (run / "clouds" / "000000.ply").is_file() and (run / "report.html").is_file()
