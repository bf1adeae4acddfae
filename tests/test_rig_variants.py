"""Rigs that look like real ones: a rigid scene (camera motion without a tracker) yields no
deforming; a narrow-baseline stereo endoscope keeps its far points."""

from __future__ import annotations

import numpy as np
import pytest

from surgrecon_cli.config import Config
from surgrecon_cli.core.classify.labels import DEFORMING, UNKNOWN
from surgrecon_cli.core.geometry.cameras import world_to_camera
from surgrecon_cli.io.run.ingest_store import load_ingested
from surgrecon_cli.io.run.layout import RunLayout
from surgrecon_cli.pipeline import run_pipeline
from surgrecon_cli.sim.simulate import simulate
from surgrecon_cli.sim.variants import variant_config
from surgrecon_cli.stages.ingest import ingest
from surgrecon_cli.stages.template import run_build_template

pytestmark = pytest.mark.slow  # whole-pipeline runs of simulator variants


def test_rigid_scene_yields_no_deforming(tmp_path):
    log = tmp_path / "rigid.mcap"
    simulate(log, variant_config("rigid", frames=5, width=320, height=240, seed=21))
    run_dir = tmp_path / "run"
    run_pipeline(log, run_dir, Config())
    with np.load(RunLayout(run_dir).labels) as z:
        labels = z["labels"][1:]
    labelled = labels != UNKNOWN
    assert labelled.mean() > 0.8
    assert (labels[labelled] == DEFORMING).mean() <= 0.01


def test_narrow_baseline_keeps_far_points(tmp_path):
    """A 3 mm stereo baseline: tissue beyond ~57 mm is seen under less than 3 degrees, where
    a fixed `min_angle_deg = 3` dropped every point; kept by their depth accuracy now, with
    an uncertainty that grows with depth as triangulation predicts (~ z²)."""
    log = tmp_path / "stereo.mcap"
    simulate(log, variant_config("stereo", frames=2, width=640, height=480, seed=22,
                                 stereo_baseline=0.003))
    run_dir = tmp_path / "run"
    config = Config()
    ingest(log, run_dir, config)
    result = run_build_template(run_dir, config)
    pose = load_ingested(run_dir / "ingest").poses[0, 0]
    depth = world_to_camera(result.points, pose)[:, 2]
    angle = np.degrees(2 * np.arctan(0.003 / 2 / depth))
    far = angle < 3.0
    assert far.sum() >= 0.03 * len(depth), (far.sum(), np.percentile(depth, [5, 50, 95]))
    near = depth < np.percentile(depth, 20)
    ratio = np.median(result.sigma[far]) / np.median(result.sigma[near])
    expected = (np.median(depth[far]) / np.median(depth[near])) ** 2
    assert 0.5 * expected <= ratio <= 2.0 * expected, (ratio, expected)
