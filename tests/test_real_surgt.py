"""Real footage: the pipeline on a cropped piece of the SurgT clip (tests/data/surgt_crop,
Apache-2.0): a rigid scene seen by a moving stereo endoscope, so (almost) nothing deforms,
and the measured pixel noise is what real images carry, not the sensor-noise floor."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from surgrecon_cli.cli.main import main
from surgrecon_cli.core.labels import DEFORMING, SHIFTING, STATIC
from surgrecon_cli.io.ply import read_ply
from surgrecon_cli.io.run_layout import RunLayout

DATA = Path(__file__).parent / "data" / "surgt_crop"


def test_surgt_rigid_scene_is_not_called_deforming(tmp_path: Path):
    log = tmp_path / "surgt.mcap"
    assert main(["convert", str(DATA), "-o", str(log), "--calibration",
                 str(DATA / "calibration.yaml"), "-q"]) == 0
    run = tmp_path / "run"
    assert main(["run", str(log), "-o", str(run), "--config", str(log.with_suffix(".toml")),
                 "-q"]) == 0
    layout = RunLayout(run)
    noise = json.loads(layout.summary_json.read_text())["noise"]
    # Real images locate features to a few tenths of a pixel (an independent NCC check on
    # these images, benchmarks/real_reference.py: 0.34 px), far above the Cramér-Rao floor.
    assert noise["pixel_px"] >= 0.1
    counts = np.zeros(256)
    frames = json.loads(layout.run_json.read_text())["ingest"]["frames"]
    for k in range(1, frames):
        counts += np.bincount(read_ply(layout.cloud(k))["label"], minlength=256)
    labelled = counts[[STATIC, SHIFTING, DEFORMING]].sum()
    assert labelled >= 0.5 * counts.sum()
    assert counts[DEFORMING] <= 0.05 * labelled
