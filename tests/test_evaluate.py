"""stages.evaluate / `surgrecon evaluate`: scores of a run folder with known errors."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from surgrecon_cli.cli.main import main
from surgrecon_cli.config import Config
from surgrecon_cli.core.classify.labels import DEFORMING, STATIC
from surgrecon_cli.core.evaluate.scoring import label_scores, map_to_surface
from surgrecon_cli.errors import InputError
from surgrecon_cli.io.logs.ground_truth import gt_path_beside, load_ground_truth
from surgrecon_cli.io.run.artefacts import (
    FrameLabels,
    FrameRegistration,
    read_registration,
    read_template,
    write_labels,
    write_registration,
)
from surgrecon_cli.io.run.atomic import write_npz
from surgrecon_cli.io.run.folder import RunFolder
from surgrecon_cli.io.run.ingest_store import load_ingested
from surgrecon_cli.io.run.layout import RunLayout
from surgrecon_cli.io.run.ply import write_cloud_ply
from surgrecon_cli.stages.evaluate import run_evaluate

OFFSET_MM = 0.5


def _strict_json(path: Path) -> dict:
    def no_nan(name: str) -> None:
        raise AssertionError(f"{path}: {name} in JSON")

    return json.loads(path.read_text(), parse_constant=no_nan)


@pytest.fixture
def known_run(copy_run: Path, pipeline_log: Path):
    """The session's run with its outputs replaced by ones of known error: 300 template
    points exactly on the true surface plus one on the tool shaft, every frame registered
    0.5 mm off along x, labels true except 10 static points called deforming at frame 2."""
    gt = load_ground_truth(gt_path_beside(pipeline_log))
    layout = RunLayout(copy_run)
    log = load_ingested(layout.ingest_dir)
    rng = np.random.default_rng(0)
    v0, faces = gt.vertices[0], gt.faces
    near = np.flatnonzero(np.linalg.norm(v0[faces].mean(1)[:, :2], axis=1) < 0.03)
    w = rng.dirichlet(np.ones(3), 300)
    points = np.einsum("nk,nkd->nd", w, v0[faces[rng.choice(near, 300)]])
    tool = log.tool_poses[0]
    points = np.vstack([points, tool[:3, 3] + 0.02 * tool[:3, 2]])  # 20 mm up the shaft
    n = len(points)
    write_cloud_ply(layout.template_ply, points, point_id=np.arange(n, dtype=np.int32))
    mapping = map_to_surface(points, v0, faces)
    truth = gt.labels[:, mapping.nearest_vertex(faces)]
    for k in range(1, gt.n_frames):
        registered = mapping.follow(gt.vertices[k], faces) + np.array([OFFSET_MM * 1e-3, 0, 0])
        T = np.tile(np.eye(3, 4), (n, 1, 1))
        T[:, :, 3] = registered - points
        write_registration(layout, k, FrameRegistration(
            transforms=T, registered=registered, target=registered,
            status=np.zeros(n, np.uint8), views=np.full(n, 2), residual=np.zeros(n),
            sigma=np.full(n, 1e-4), target_sigma=np.full(n, 1e-4),
            target_covariance=np.zeros((n, 3, 3)), target_pose_covariance=np.zeros((n, 3, 3)),
            support_mm=np.zeros(n), pixels=np.full((n, 1, 2), np.nan), tracking_px=0.05,
            base=0, converged=True, failed=False, error="", seconds_target=0.1,
            seconds_register=0.2, new_points=0, contact_points=0))
    run = RunFolder(copy_run)  # the contact measures were of the replaced template
    data = run.read()
    data["stages"].pop("measure")
    run.write(data)
    labels = truth.copy()
    static2 = np.flatnonzero(truth[2] == STATIC)[:10]
    labels[2, static2] = DEFORMING
    write_labels(layout, FrameLabels(labels, labels, np.zeros(labels.shape),
                                     np.zeros(labels.shape), np.zeros(labels.shape),
                                     np.zeros(labels.shape, np.uint8)))
    return copy_run, gt, truth, labels


def test_scores_of_known_errors(known_run):
    run_dir, gt, truth, labels = known_run
    result = run_evaluate(run_dir, Config(), gt.path)
    assert _strict_json(RunLayout(run_dir).evaluation_json) == json.loads(json.dumps(result))
    n, frames = labels.shape[1], labels.shape[0]
    tpl = result["template"]
    assert tpl["points"] == n and tpl["error"]["count"] == n
    assert tpl["error"]["median_mm"] < 1e-3               # on the surface
    assert tpl["error"]["max_mm"] > 5.0                    # the point on the tool
    assert tpl["on_tool"]["count"] == 1
    assert tpl["error_off_tool"]["max_mm"] < 1e-3
    reg = result["registration"]
    assert reg["overall"]["count"] == n * (frames - 1)
    for key in ("median_mm", "p95_mm", "max_mm"):
        assert reg["overall"][key] == pytest.approx(OFFSET_MM, abs=1e-6)
    assert reg["overall"]["within_1mm"] == 1.0
    assert [r["frame"] for r in reg["per_frame"]] == list(range(1, frames))
    lab = result["labels"]
    assert lab["overall"] == json.loads(json.dumps(label_scores(labels[1:], truth[1:])))
    assert lab["overall"]["confusion"][0][2] == 10         # static called deforming
    f1 = {r["frame"]: r["macro_f1"] for r in lab["per_frame"]}
    assert f1[2] < 1.0 and all(f1[k] == 1.0 for k in f1 if k != 2)
    assert RunFolder(run_dir).stage("evaluate")["parts"] == ["template", "registration", "labels"]


def test_calibration_counts_the_points_the_truth_covers(known_run, tmp_path):
    """A truth with a hole (a depth map's, where nothing was measured) maps the points over it
    to the hole's rim, millimetres from where they are: that error is the truth's, and the
    2σ calibration leaves those points out (the spec's registration errors keep them)."""
    run_dir, gt, _, _ = known_run
    layout = RunLayout(run_dir)
    points = read_template(layout).points[:-1]  # the 300 on the surface
    centre = points[0]
    centroids = gt.vertices[0][gt.faces].mean(1)
    holed = gt.faces[np.linalg.norm(centroids - centre, axis=1) > 3e-3]
    distance = np.linalg.norm(points - centre, axis=1)
    over, near = (distance < 2e-3).sum(), (distance < 4e-3).sum()  # inside; up to its rim
    assert over >= 1
    data = dict(np.load(gt.path))
    data["faces"] = holed
    gt_holed = tmp_path / "holed.gt.npz"
    np.savez(gt_holed, **data)
    n = len(points) + 1
    for k in range(1, gt.n_frames):  # σ 0.3 mm: 2σ holds the 0.5 mm offset, not the rim's
        reg = read_registration(layout, k, n)
        write_registration(layout, k, replace(reg, sigma=np.full(n, 3e-4)))
    whole = run_evaluate(run_dir, Config(), gt.path)["labels"]
    result = run_evaluate(run_dir, Config(), gt_holed)
    assert whole["truth_covered_fraction"] == 1.0
    assert whole["calibration_2sigma"] == pytest.approx(1.0)
    lab = result["labels"]
    assert 1.0 - near / n <= lab["truth_covered_fraction"] <= 1.0 - over / n
    assert lab["calibration_2sigma"] == pytest.approx(1.0)
    assert result["registration"]["overall"]["max_mm"] > 1.0  # the rim's error is scored


def test_template_only_run_gets_the_template_part(known_run):
    run_dir, gt, _, _ = known_run
    data = RunFolder(run_dir).read()
    for stage in ("register", "classify", "evaluate", "report"):
        data["stages"].pop(stage)
    RunFolder(run_dir).write(data)
    result = run_evaluate(run_dir, Config(), gt.path)
    assert result["registration"] is None and result["labels"] is None
    assert result["template"]["on_tool"]["count"] == 1


def test_frame_count_mismatch_is_a_clear_error(copy_run, pipeline_log, tmp_path):
    gt = load_ground_truth(gt_path_beside(pipeline_log))
    short = tmp_path / "short.gt.npz"
    write_npz(short, faces=gt.faces, vertices=gt.vertices[:-1], labels=gt.labels[:-1],
              stamps_ns=gt.stamps_ns[:-1])
    with pytest.raises(InputError, match=r"has 5 frames but .* ingested 6"):
        run_evaluate(copy_run, Config(), short)
    with pytest.raises(InputError, match="missing"):
        write_npz(tmp_path / "bad.npz", faces=gt.faces)
        run_evaluate(copy_run, Config(), tmp_path / "bad.npz")


def test_cli_prints_a_readable_summary(copy_run, capsys):
    assert main(["evaluate", str(copy_run), "-q"]) == 0  # ground truth found beside the log
    out = capsys.readouterr().out
    assert "template:" in out and "registration error" in out and "macro-F1" in out
    assert "confusion (rows: truth, columns: predicted)" in out
    assert out.strip().endswith(str(RunLayout(copy_run).evaluation_json))


def test_a_part_of_the_log_is_scored_against_its_frames_of_the_truth(pipeline_log, tmp_path):
    """A run of every 2nd frame (ingest.every) is scored against the truth's frames 0, 2, 4
    (matched by stamp), as well as the whole run is; a truth whose stamps match no frame
    of the run is a clear error."""
    from surgrecon_cli.config import load_config
    from surgrecon_cli.pipeline import run_pipeline

    run = tmp_path / "every2"
    config = load_config(None, ["ingest.every=2"])
    run_pipeline(pipeline_log, run, config)
    log = load_ingested(RunLayout(run).ingest_dir)
    gt = load_ground_truth(gt_path_beside(pipeline_log))
    assert np.abs(log.stamps_ns - gt.stamps_ns[::2]).max() < 1_000_000  # 1 ms
    result = _strict_json(run / "metrics/evaluation.json")
    assert result["frames"] == 3 and result["stamp_difference_max_ms"] < 1.0
    assert result["registration"]["overall"]["median_mm"] < 0.5
    moved = tmp_path / "moved.gt.npz"
    write_npz(moved, faces=gt.faces, vertices=gt.vertices, labels=gt.labels,
              stamps_ns=gt.stamps_ns + 40_000_000)
    with pytest.raises(InputError, match="no ground-truth frame within 15 ms of the run's frame 0"):
        run_evaluate(run, config, moved)
