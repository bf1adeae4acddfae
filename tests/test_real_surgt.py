"""Real footage: the pipeline on the SurgT clip (tests/data/surgt, Apache-2.0): a rigid scene
seen by a moving stereo endoscope, so (almost) nothing deforms, and the measured pixel noise
is what real images carry, not the sensor-noise floor (main measured 0.015 px here and
called 86 % of the points outliers)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from surgrecon_cli.cli.main import main
from surgrecon_cli.core.classify.labels import DEFORMING, SHIFTING, STATIC
from surgrecon_cli.io.run.layout import RunLayout
from surgrecon_cli.io.run.ply import read_ply

SURGT = Path(__file__).parent / "data" / "surgt"
FRAMES = 6


def test_surgt_rigid_scene_is_not_called_deforming(tmp_path: Path):
    log = tmp_path / "surgt.mcap"
    assert main(["convert", str(SURGT / "video.mp4"), "-o", str(log), "--calibration",
                 str(SURGT / "calibration.yaml"), "--frames", f"0:{FRAMES}", "-q"]) == 0
    run = tmp_path / "run"
    assert main(["run", str(log), "-o", str(run), "--config", str(log.with_suffix(".toml")),
                 "-q"]) == 0
    layout = RunLayout(run)
    summary = json.loads(layout.summary_json.read_text())
    # Real images locate features to a few tenths of a pixel (an independent NCC check on
    # this clip, benchmarks/real_reference.py: 0.44 px), far above the Cramér-Rao floor.
    assert summary["noise"]["pixel_px"] >= 0.1
    frames = summary["quality"]["per_frame"]
    assert np.mean([q["outlier_fraction"] for q in frames]) <= 0.2
    counts = np.zeros(256)
    for k in range(1, FRAMES):
        counts += np.bincount(read_ply(layout.cloud(k))["label"], minlength=256)
    labelled = counts[[STATIC, SHIFTING, DEFORMING]].sum()
    assert labelled >= 0.5 * counts.sum()
    assert counts[DEFORMING] <= 0.05 * labelled
