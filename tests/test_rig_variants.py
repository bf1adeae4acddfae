"""Rigs that look like real ones: a rigid scene (camera motion without a tracker) yields no
deforming."""

from __future__ import annotations

import numpy as np

from surgrecon_cli.config import Config
from surgrecon_cli.core.labels import DEFORMING, UNKNOWN
from surgrecon_cli.pipeline import run_pipeline
from surgrecon_cli.sim.simulate import simulate
from surgrecon_cli.sim.variants import variant_config
from surgrecon_cli.stages.classify import labels_path


def test_rigid_scene_yields_no_deforming(tmp_path):
    log = tmp_path / "rigid.mcap"
    simulate(log, variant_config("rigid", frames=5, width=320, height=240, seed=21))
    run_dir = tmp_path / "run"
    run_pipeline(log, run_dir, Config())
    with np.load(labels_path(run_dir)) as z:
        labels = z["labels"][1:]
    labelled = labels != UNKNOWN
    assert labelled.mean() > 0.8
    assert (labels[labelled] == DEFORMING).mean() <= 0.01
