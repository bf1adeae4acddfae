"""core.classify.rules: static / shifting / deforming on synthetic and true motion fields."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from gt_fixtures import true_field

from surgrecon_cli.config import ClassifyConfig, load_config
from surgrecon_cli.core.classify.labels import DEFORMING, SHIFTING, STATIC, UNKNOWN, true_labels
from surgrecon_cli.core.classify.rules import (
    RegisteredFrame,
    apply_hysteresis,
    classify_frame,
    classify_sequence,
    template_neighbourhoods,
    transform_difference_mm,
)
from surgrecon_cli.core.evaluate.scoring import label_scores
from surgrecon_cli.errors import ConfigError, GeometryError
from surgrecon_cli.sim.scene import SimConfig, make_tissue
from surgrecon_cli.sim.simulate import LogBuilder

S, H, D, U = STATIC, SHIFTING, DEFORMING, UNKNOWN
RULE = ClassifyConfig(static_mm=1.0, deform_mm=0.25)  # the truth rule's own thresholds


def _patch(n: int = 900, seed: int = 0) -> np.ndarray:
    """Points (N, 3) m on a gently curved 40 x 40 mm patch, ~1.3 mm apart."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-0.02, 0.02, (n, 2))
    z = 0.01 - 3.0 * (xy**2).sum(1)
    return np.column_stack([xy, z])


def _identity(n: int) -> np.ndarray:
    return np.tile(np.eye(3, 4), (n, 1, 1))


def _rotation(axis: np.ndarray, deg: float) -> np.ndarray:
    axis = axis / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    a = np.radians(deg)
    return np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K


def _rigid_transforms(n: int, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.zeros((n, 3, 4))
    T[:, :, :3] = R
    T[:, :, 3] = t
    return T


def _apply(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    return np.einsum("nij,nj->ni", T[:, :, :3], p) + T[:, :, 3]


@pytest.mark.parametrize("measure", ["rigid_rms", "transform_diff"])
def test_still_surface_is_static(measure):
    p = _patch()
    noisy = p + np.random.default_rng(1).normal(0, 0.05e-3, p.shape)
    nb = template_neighbourhoods(p, 5.0, 6, 128)
    out = classify_frame(p, RegisteredFrame(noisy, _identity(len(p))), nb,
                         dataclasses.replace(RULE, measure=measure))
    assert (out.labels == S).all()
    assert np.nanmax(out.displacement_mm) < 0.5
    assert np.isnan(out.deformation_mm).all()  # only moving points get a deformation measure


@pytest.mark.parametrize("measure", ["rigid_rms", "transform_diff"])
def test_pure_translation_and_rotation_are_shifting(measure):
    p = _patch()
    cfg = dataclasses.replace(RULE, measure=measure)
    nb = template_neighbourhoods(p, cfg.neighbourhood_mm, cfg.min_neighbours, cfg.max_neighbours)
    for R, t in [(np.eye(3), np.array([0.002, -0.001, 0.0025])),
                 (_rotation(np.array([0.3, 1.0, 0.2]), 8.0), np.array([0.0, 0.004, 0.001]))]:
        T = _rigid_transforms(len(p), R, t)
        out = classify_frame(p, RegisteredFrame(_apply(T, p), T), nb, cfg)
        assert (out.labels == H).all(), np.bincount(out.labels)
        assert np.nanmax(out.deformation_mm) < 1e-6


def _indentation(p: np.ndarray, depth: float = 0.006, sigma: float = 0.005):
    """A Gaussian dent along -z at the patch centre: positions and exact per-point affines
    (the Jacobian of the displacement field)."""
    g = np.exp(-(p[:, :2] ** 2).sum(1) / (2 * sigma**2))
    moved = p.copy()
    moved[:, 2] -= depth * g
    T = _identity(len(p))
    T[:, 2, 0] = depth * g * p[:, 0] / sigma**2  # d(-depth g)/dx
    T[:, 2, 1] = depth * g * p[:, 1] / sigma**2
    T[:, :, 3] = moved - np.einsum("nij,nj->ni", T[:, :, :3], p)
    return moved, T, g


@pytest.mark.parametrize("measure,threshold", [("rigid_rms", 0.25), ("transform_diff", 0.8)])
def test_local_indentation_is_deforming_and_its_surroundings_static(measure, threshold):
    p = _patch(1600)
    moved, T, _ = _indentation(p)
    cfg = dataclasses.replace(RULE, measure=measure, deform_mm=threshold)
    nb = template_neighbourhoods(p, cfg.neighbourhood_mm, cfg.min_neighbours, cfg.max_neighbours)
    out = classify_frame(p, RegisteredFrame(moved, T), nb, cfg)
    r = np.linalg.norm(p[:, :2], axis=1)
    assert (out.labels[r > 0.016] == S).all()          # dent < 0.04 mm out there
    core = r < 0.006
    assert (out.labels[core] == D).mean() > 0.9       # curvature is largest at the centre
    assert (out.labels == D).sum() > 50


def test_transform_difference_is_the_papers_measure():
    """(T_j - T_i) p_i for two neighbours whose transforms differ by a known translation."""
    p = np.array([[0.0, 0.0, 0.0], [0.001, 0.0, 0.0], [0.0, 0.001, 0.0], [0.001, 0.001, 0.0]])
    T = _identity(4)
    T[3, :, 3] = [0.0, 0.0, 0.002]  # point 3 carries its neighbours 2 mm up
    nb = template_neighbourhoods(p, 5.0, 2, 8)
    d = transform_difference_mm(p, T, nb, percentile=100)
    np.testing.assert_allclose(d, [2.0, 2.0, 2.0, 2.0], atol=1e-9)
    d_median = transform_difference_mm(p, T, nb, percentile=50, rows=np.array([0]))
    np.testing.assert_allclose(d_median, [0.0], atol=1e-9)


@pytest.fixture(scope="module")
def true_motion():
    """The simulator's true motion (10 frames: breathing + tool indentation) seen by 1500
    template-like points on the visible part of the dome (with 0.05 mm template noise)."""
    cfg = SimConfig(frames=10)
    vertices = LogBuilder(cfg).true_vertices()
    faces = make_tissue(cfg).faces
    labels = true_labels(vertices, 1.0, 5.0, 0.25)
    rng = np.random.default_rng(3)
    face = rng.choice(np.flatnonzero(np.linalg.norm(vertices[0][faces].mean(1)[:, :2], axis=1)
                                     < 0.035), 1500)
    w = rng.dirichlet(np.ones(3), 1500)
    points = np.einsum("nk,nkd->nd", w, vertices[0][faces[face]])
    points += rng.normal(0, 0.05e-3 / np.sqrt(3), points.shape)
    return true_field(points, vertices, faces, labels)


def test_true_motion_field_reproduces_the_ground_truth_labels(true_motion):
    f = true_motion
    assert {S, H, D} <= set(np.unique(f.labels[1:]))
    result = classify_sequence(f.template, f.registered, RULE, transforms=f.transforms)
    scores = label_scores(result.labels[1:], f.labels[1:])
    assert scores["macro_f1"] > 0.93, scores
    assert (result.labels[0] == S).all()
    # The paper's neighbour-transform measure gets there too, if less precisely.
    td = dataclasses.replace(RULE, measure="transform_diff", deform_mm=0.1, neighbour_percentile=50)
    scores_td = label_scores(classify_sequence(f.template, f.registered, td,
                                               transforms=f.transforms).labels[1:], f.labels[1:])
    assert scores_td["macro_f1"] > 0.85, scores_td


def test_hysteresis_drops_short_runs():
    raw = np.array([[S, S, S, S],
                    [H, H, D, U],
                    [S, H, D, H],
                    [H, H, H, H],
                    [H, D, H, H]], np.uint8)
    out = apply_hysteresis(raw, 2)
    np.testing.assert_array_equal(out[:, 0], [S, S, S, H, H])  # the 1-frame H run is undone
    np.testing.assert_array_equal(out[:, 1], [S, H, H, H, D])  # a run reaching the end stays
    np.testing.assert_array_equal(out[:, 2], [S, D, D, H, H])
    np.testing.assert_array_equal(out[:, 3], [S, U, H, H, H])  # unknown stays unknown
    single = np.array([[S], [D], [S], [S]], np.uint8)
    np.testing.assert_array_equal(apply_hysteresis(single, 2)[:, 0], [S, S, S, S])
    np.testing.assert_array_equal(apply_hysteresis(raw, 0), raw)


def test_unknown_positions_and_status_band():
    p = _patch(300)
    moved = p + np.array([0.0, 0.0, 0.00095])  # just below 1.0 mm
    moved[0] = np.nan
    nb = template_neighbourhoods(p, 5.0, 6, 128)
    status = np.zeros(len(p), np.uint8)
    status[1::2] = 1  # inter-camera inliers: dynamic evidence
    plain = classify_frame(p, RegisteredFrame(moved, status=status), nb, RULE)
    assert plain.labels[0] == U and (plain.labels[1:] == S).all()
    banded = classify_frame(p, RegisteredFrame(moved, status=status), nb,
                            dataclasses.replace(RULE, status_band_mm=0.1))
    assert (banded.labels[1::2] == H).all() and (banded.labels[2::2] == S).all()


def test_bad_inputs_raise_named_errors():
    p = _patch(50)
    nb = template_neighbourhoods(p, 5.0, 6, 128)
    with pytest.raises(GeometryError, match="registered positions"):
        classify_frame(p, RegisteredFrame(p[:10]), nb, RULE)
    with pytest.raises(GeometryError, match="transform_diff"):
        classify_frame(p, RegisteredFrame(p), nb,
                       dataclasses.replace(RULE, measure="transform_diff"))
    with pytest.raises(GeometryError, match="NaN"):
        template_neighbourhoods(np.full((5, 3), np.nan), 5.0, 2, 4)
    with pytest.raises(ConfigError, match=r"classify\.status_band_mm"):
        load_config(overrides=["classify.status_band_mm=2.0"])
    with pytest.raises(ConfigError, match=r"classify\.measure"):
        load_config(overrides=["classify.measure='max'"])

