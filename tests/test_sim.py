"""Simulator: ground-truth file layout, label rule, determinism."""

from __future__ import annotations

import numpy as np
import pytest

from surgrecon_cli.core.classify.labels import (
    DEFORMING,
    SHIFTING,
    STATIC,
    label_rule,
    radius_neighbourhoods,
    true_labels,
)
from surgrecon_cli.sim.motion import Motion
from surgrecon_cli.sim.scene import SimConfig, make_tissue
from surgrecon_cli.sim.simulate import simulate

SMALL = SimConfig(cameras=2, frames=3, width=96, height=72, seed=11)


@pytest.fixture(scope="module")
def small_log(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim") / "small.mcap"
    return simulate(out, SMALL)


def test_ground_truth_file_matches_the_spec(small_log):
    with np.load(small_log.gt_path, allow_pickle=False) as gt:
        assert set(gt.files) == {"faces", "vertices", "labels", "stamps_ns", "tool_poses",
                                 "indentation_m"}
        assert gt["tool_poses"].shape == (SMALL.frames, 4, 4)
        assert gt["indentation_m"].shape == (SMALL.frames,)
        assert (gt["indentation_m"] >= 0).all()
        faces, vertices, labels, stamps = gt["faces"], gt["vertices"], gt["labels"], gt["stamps_ns"]
    assert faces.dtype == np.int32 and faces.shape[1] == 3
    assert vertices.dtype == np.float64 and vertices.shape[0] == SMALL.frames
    assert labels.dtype == np.uint8 and labels.shape == vertices.shape[:2]
    assert stamps.dtype == np.int64 and np.all(np.diff(stamps) > 0)
    assert faces.max() < vertices.shape[1]
    assert (labels[0] == STATIC).all()  # frame 0 is the reference
    # Tissue dome is tens of millimetres across.
    extent = np.ptp(vertices[0][:, :2], axis=0)
    assert (extent > 0.08).all() and (extent < 0.12).all()


def test_simulation_is_deterministic(small_log, tmp_path):
    again = simulate(tmp_path / "again.mcap", SMALL)
    assert again.log_path.read_bytes() == small_log.log_path.read_bytes()
    assert again.gt_path.read_bytes() == small_log.gt_path.read_bytes()


def test_default_motion_has_all_three_classes():
    cfg = SimConfig()
    motion = Motion(cfg, make_tissue(cfg))
    frames = [0, 6, 10, 14]
    vertices = np.stack([motion.tissue_vertices(f / cfg.frame_rate) for f in frames])
    labels = true_labels(vertices, 1.0, 5.0, 0.25)
    later = labels[1:]
    for code in (STATIC, SHIFTING, DEFORMING):
        assert (later == code).mean() > 0.03


def test_label_rule_on_synthetic_motions():
    rng = np.random.default_rng(0)
    xy = rng.uniform(-0.02, 0.02, (1500, 2))
    ref = np.column_stack([xy, np.zeros(len(xy))])
    index, mask = radius_neighbourhoods(ref, 0.005)
    translated = ref + np.array([0.0, 0.0, 0.002])
    assert (label_rule(ref, translated, index, mask, 1.0, 0.25) == SHIFTING).all()
    assert (label_rule(ref, ref + 0.0002, index, mask, 1.0, 0.25) == STATIC).all()
    dent = ref.copy()
    dent[:, 2] -= 0.006 * np.exp(-(ref[:, :2] ** 2).sum(1) / (2 * 0.003**2))
    labels = label_rule(ref, dent, index, mask, 1.0, 0.25)
    centre = np.linalg.norm(ref[:, :2], axis=1) < 0.002
    assert (labels[centre] == DEFORMING).all()
    assert (labels[np.linalg.norm(ref[:, :2], axis=1) > 0.015] == STATIC).all()


def test_pose_convention_names_match_the_conventions():
    """The CLI's light list of convention names is the simulator's table, in order."""
    from surgrecon_cli.sim import POSE_CONVENTIONS
    from surgrecon_cli.sim.conventions import CONVENTIONS

    assert tuple(CONVENTIONS) == POSE_CONVENTIONS
