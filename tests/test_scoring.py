"""Ground-truth scoring helpers."""

from __future__ import annotations

import numpy as np

from surgrecon_cli.core.classify.labels import DEFORMING, SHIFTING, STATIC, UNKNOWN
from surgrecon_cli.core.evaluate.scoring import (
    distance_stats_mm,
    label_scores,
    map_to_surface,
    on_mesh_rim,
)
from surgrecon_cli.sim.scene import SimConfig, make_tissue


def test_points_on_the_mesh_map_to_themselves_and_follow_the_motion():
    mesh = make_tissue(SimConfig())
    rng = np.random.default_rng(1)
    face = rng.integers(0, len(mesh.faces), 500)
    bary = rng.dirichlet([1, 1, 1], 500)
    points = np.einsum("nk,nkd->nd", bary, mesh.vertices[mesh.faces[face]])
    mapping = map_to_surface(points, mesh.vertices, mesh.faces)
    assert mapping.distance.max() < 1e-9
    moved = mesh.vertices + np.array([0.001, 0.0, 0.002])
    np.testing.assert_allclose(
        mapping.follow(moved, mesh.faces), points + np.array([0.001, 0.0, 0.002]), atol=1e-12
    )
    lifted = map_to_surface(points + np.array([0, 0, 0.0005]), mesh.vertices, mesh.faces)
    assert np.all(lifted.distance <= 0.0005 + 1e-9)
    assert np.median(lifted.distance) > 0.0004  # the dome is nearly flat at this scale


def test_distance_stats_and_label_scores():
    stats = distance_stats_mm(np.array([0.0001, 0.0002, 0.0003, np.nan]))
    assert stats["count"] == 3 and abs(stats["median_mm"] - 0.2) < 1e-12
    truth = np.array([STATIC] * 4 + [SHIFTING] * 4 + [DEFORMING] * 2)
    pred = np.array([STATIC] * 3 + [SHIFTING] + [SHIFTING] * 4 + [DEFORMING, UNKNOWN])
    scores = label_scores(pred, truth)
    assert scores["per_class"]["static"] == {
        "precision": 1.0,
        "recall": 0.75,
        "f1": 6 / 7,
        "support": 4,
    }
    assert scores["per_class"]["shifting"]["precision"] == 0.8
    assert scores["per_class"]["deforming"]["recall"] == 0.5
    assert scores["confusion"][2] == [0, 0, 1, 1]


def test_points_over_a_hole_or_beyond_the_border_map_to_the_rim():
    """A flat 10 x 10 mm grid (1 mm cells) without the cells within 2 mm of its centre: a
    point over the hole, or beyond the border, has its nearest point on the rim; a point
    over the surface, even beside the hole or over an interior edge or vertex, does not."""
    xs = np.arange(11) * 1e-3
    gx, gy = np.meshgrid(xs, xs)
    vertices = np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)])
    idx = np.arange(gx.size).reshape(gx.shape)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]
    faces = np.concatenate([np.column_stack([a.ravel(), b.ravel(), c.ravel()]),
                            np.column_stack([a.ravel(), c.ravel(), d.ravel()])])
    centre = np.array([5e-3, 5e-3, 0.0])
    faces = faces[np.linalg.norm(vertices[faces].mean(1) - centre, axis=1) > 2e-3]
    up = np.array([0.0, 0.0, 1e-3])
    points = np.array([centre + up,                         # over the hole
                       [12e-3, 5e-3, 1e-3],                 # beyond the border
                       [-1e-3, -1e-3, 0.0],                 # beyond a corner
                       [1.5e-3, 1.2e-3, 1e-3],              # over the surface
                       [8.5e-3, 5e-3, 1e-3],                # beside the hole, over cells
                       [3e-3, 3e-3, 1e-3],                  # over an interior vertex
                       [1.5e-3, 1.5e-3, 1e-3]])             # over an interior edge
    mapping = map_to_surface(points, vertices, faces)
    rim = on_mesh_rim(mapping, faces)
    assert rim.tolist() == [True, True, True, False, False, False, False]
