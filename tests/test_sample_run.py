"""Smoke run of `surgrecon run` on the shipped sample log, scored against its ground truth.

The bounds are the issues' goals (template and registration accuracy, labels), with a
small margin on macro-F1 for floating-point differences between machines.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
from plyfile import PlyData

from surgrecon_cli.cli.main import main

pytestmark = pytest.mark.slow  # the whole sample run (module fixture)

SAMPLE = Path(__file__).resolve().parents[1] / "sample_data" / "sample.mcap"


@pytest.fixture(scope="module")
def sample_run(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("sample") / "run"
    assert main(["run", str(SAMPLE), "-o", str(run_dir), "-q"]) == 0
    return run_dir


def test_outputs_exist_and_parse(sample_run):
    run = json.loads((sample_run / "run.json").read_text())
    assert run["ingest"]["cameras"] == ["0", "1", "2", "3", "4", "5"]
    assert run["ingest"]["frames"] == 20
    clouds = sorted((sample_run / "clouds").glob("*.ply"))
    assert len(clouds) == 20
    ids = None
    for path in clouds[:: len(clouds) - 1]:  # first and last frame
        ply = PlyData.read(str(path))["vertex"]
        names = [p.name for p in ply.properties]
        assert names[:9] == ["x", "y", "z", "red", "green", "blue", "point_id", "label", "residual"]
        frame_ids = np.asarray(ply["point_id"])
        ids = frame_ids if ids is None else ids
        np.testing.assert_array_equal(frame_ids, ids)  # point ids stable across frames
        cloud = o3d.io.read_point_cloud(str(path))
        assert len(cloud.points) == len(frame_ids) and cloud.has_colors()
    report = (sample_run / "report.html").read_text()
    assert report.count("data:image/png;base64,") >= 5
    header = (sample_run / "metrics" / "frames.csv").read_text().splitlines()[0].split(",")
    assert {"frame", "static", "shifting", "deforming", "seconds_register"} <= set(header)


def test_scores_meet_the_goals(sample_run):
    ev = json.loads((sample_run / "metrics" / "evaluation.json").read_text())
    template = ev["template"]
    assert template["points"] >= 2000
    assert template["error"]["median_mm"] <= 0.3
    assert template["error"]["p95_mm"] <= 1.0
    assert template["on_tool"]["count"] == 0
    reg = ev["registration"]["overall"]
    assert reg["median_mm"] <= 0.3
    assert reg["p95_mm"] <= 1.0
    assert ev["registration"]["labelled"]["p95_mm"] <= 0.8
    labels = ev["labels"]["overall"]
    assert labels["macro_f1"] >= 0.88
    # A dent point is deforming only when its neighbourhood's departure from rigid motion is
    # significant against the measured noise, each point weighted by its full information
    # (precision 0.94, recall 0.82 measured; dents just above the 0.25 mm rule are called
    # shifting: with scalar weights 0.945 / 0.800, while a still real scene at 360x288 had
    # 116 deforming point-frames instead of 1).
    assert labels["per_class"]["deforming"]["precision"] >= 0.9
    assert labels["per_class"]["deforming"]["recall"] >= 0.78
    # The reported uncertainty is honest: the true error is within 2 sigma for 85-99 % of the
    # labelled points, and no point without data far off is labelled.
    assert 0.85 <= ev["labels"]["calibration_2sigma"] <= 0.99
    assert ev["registration"]["unsupported_moved"] == 0


def test_sample_export_is_small(sample_run, tmp_path):
    """The issue's goal for the size of the sample's Foxglove export: <= 1.5 x the log (its
    time is a benchmark's business, not a test's)."""
    out = tmp_path / "sample.mcap"
    assert main(["export", str(sample_run), "--mcap", str(out), "-q"]) == 0
    assert out.stat().st_size <= 1.5 * SAMPLE.stat().st_size
