"""Camera grouping and pair sequencing (core/template/pairing.py) on synthetic rigs whose geometry
fixes the answer: working depths where optical axes meet, view angles and baselines from
the construction, cameras facing the same point, facing each other and facing away, and
groups / maximum-spanning-tree sequences from hand-made link weights.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from scipy.sparse.csgraph import minimum_spanning_tree

from surgrecon_cli.core.geometry.cameras import CameraModel
from surgrecon_cli.core.template.pairing import (
    FULL_ANGLE_DEG,
    MAX_ANGLE_DEG,
    MIN_BASELINE_RATIO,
    candidate_pairs,
    plan_pairs,
    predict_pairs,
    working_depths,
)

W, H, F = 320, 240, 300.0
MODEL = CameraModel(np.array([[F, 0, (W - 1) / 2], [0, F, (H - 1) / 2], [0, 0, 1]]), np.zeros(5),
                    W, H)


def look_at(centre, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world pose (optical frame: z forward, y down) at `centre` facing `target`."""
    centre, target = np.asarray(centre, float), np.asarray(target, float)
    z = target - centre
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(z, (0.0, 1.0, 0.0))
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, np.cross(z, x), z])
    T[:3, 3] = centre
    return T


def arc(angles_deg, distance=0.06, target=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Cameras on a vertical circle of radius `distance` around `target`, all facing it; the
    angle between the optical axes of two of them is the difference of their angles."""
    a = np.radians(np.asarray(angles_deg, float))
    centres = np.column_stack([distance * np.sin(a), np.zeros_like(a), distance * np.cos(a)])
    return np.array([look_at(c, target, up=(0.0, 1.0, 0.0)) for c in centres + target])


def predict(poses, usable=None, fallback=0.06):
    usable = np.ones(len(poses), bool) if usable is None else usable
    return predict_pairs([MODEL] * len(poses), poses, usable, fallback)


# ---- predictions from the poses -----------------------------------------------------------


def test_working_depth_is_where_the_axes_meet():
    poses = arc([-20.0, 0.0, 25.0], distance=0.06)
    np.testing.assert_allclose(working_depths(poses, np.ones(3, bool), 1.0), 0.06, rtol=1e-9)
    # axes that never meet in front of both cameras give the fallback
    away = np.array([look_at([0.0, 0.0, 0.06], [0.0, 0.0, 0.2]),
                     look_at([0.02, 0.0, 0.06], [0.04, 0.0, 0.2])])
    np.testing.assert_allclose(working_depths(away, np.ones(2, bool), 0.07), 0.07)
    # parallel axes meet nowhere; an unusable camera neither gets nor gives a depth
    parallel = np.array([look_at([x, 0.0, 0.06], [x, 0.0, 0.0], up=(0.0, 1.0, 0.0))
                         for x in (0.0, 0.01)])
    np.testing.assert_allclose(working_depths(parallel, np.ones(2, bool), 0.05), 0.05)
    np.testing.assert_allclose(working_depths(poses, np.array([True, False, True]), 1.0),
                               [0.06, 1.0, 0.06], rtol=1e-9)


def test_angles_baselines_and_conditioning_follow_the_geometry():
    """On the arc the view angle of a pair is the difference of its angles and the baseline
    over the working depth 2 sin(angle / 2); the conditioning factor is 1 up to FULL_ANGLE,
    falls linearly to 0 at MAX_ANGLE, and is 0 for a baseline ratio below the minimum."""
    angles = [0.0, 20.0, 40.0, 52.5, 70.0, 80.0]
    pred = predict(arc(angles))
    for i, j in itertools.combinations(range(len(angles)), 2):
        phi = abs(angles[j] - angles[i])
        assert pred.angle_deg[i, j] == pytest.approx(phi, abs=1e-6)
        assert pred.baseline_ratio[i, j] == pytest.approx(2 * np.sin(np.radians(phi) / 2))
        expected = np.clip((MAX_ANGLE_DEG - phi) / (MAX_ANGLE_DEG - FULL_ANGLE_DEG), 0, 1)
        assert pred.conditioning[i, j] == pytest.approx(expected, abs=1e-6)
    assert pred.conditioning[0, 3] == pytest.approx(0.5, abs=1e-6)  # 52.5 deg, half-way
    np.testing.assert_array_equal(np.diag(pred.conditioning), 0.0)
    np.testing.assert_allclose(pred.depth, 0.06, rtol=1e-9)
    # nearly the same place: full shared view, but no parallax -> not a usable pair
    tiny = np.radians(np.degrees(MIN_BASELINE_RATIO) / 2)  # baseline ratio ~ half the minimum
    close = predict(arc([0.0, np.degrees(tiny)]))
    assert close.baseline_ratio[0, 1] < MIN_BASELINE_RATIO
    assert close.overlap[0, 1] > 0.8 and close.conditioning[0, 1] == 0.0


def test_shared_view_facing_the_same_point_each_other_and_away():
    centre = [0.0, 0.0, 0.0]
    poses = np.array([
        look_at([0.0, -0.01, 0.06], centre),  # 0, 1: side by side, facing the same point
        look_at([0.0, 0.01, 0.06], centre),
        look_at([0.0, 0.01, -0.06], centre),  # 2: facing camera 1 from the other side
        look_at([0.0, 0.0, 0.09], [0.0, 0.0, 0.2]),  # 3: behind 0 and 1, facing away
    ])
    pred = predict(poses)
    np.testing.assert_allclose(pred.overlap, pred.overlap.T)  # symmetric (the smaller share)
    assert pred.overlap[0, 1] > 0.6 and pred.conditioning[0, 1] == 1.0
    # facing each other: camera 2 sees what camera 1 sees, but from the other side (the axes
    # 180 - 2 atan(10 / 60) deg apart): no descriptor matches -> conditioning 0
    assert pred.overlap[1, 2] > 0.2
    assert pred.angle_deg[1, 2] == pytest.approx(180 - 2 * np.degrees(np.arctan(1 / 6)))
    assert pred.conditioning[1, 2] == 0.0
    assert (pred.overlap[3, :3] == 0.0).all()  # facing away: nothing shared
    assert candidate_pairs(pred, min_overlap=0.2) == [(0, 1)]
    # an unusable camera shares nothing
    off = predict(poses, usable=np.array([True, False, True, True]))
    assert (off.overlap[1] == 0).all() and (off.overlap[:, 1] == 0).all()


def test_overlap_falls_as_cameras_turn_apart():
    pred = predict(arc([0.0, 10.0, 30.0, 50.0]))
    shares = pred.overlap[0, 1:]
    assert (np.diff(shares) < 0).all() and shares[0] > 0.7


# ---- groups and sequences -----------------------------------------------------------------


def test_plan_on_hand_made_weights():
    w = np.zeros((6, 6))
    for (i, j), value in {(2, 3): 5, (3, 4): 3, (2, 4): 4, (4, 5): 1, (3, 5): 2,
                          (0, 1): 7}.items():
        w[i, j] = value  # upper triangle only: the plan symmetrises
    plan = plan_pairs(w)
    assert plan.groups == [[2, 3, 4, 5], [0, 1]]  # larger group first
    # Prim from the best pair (2,3): camera 4 joins through (2,4) (4 > 3), camera 5 through
    # (3,5) (2 > 1); the other verified pairs follow by weight
    assert plan.sequences == [[(2, 3), (2, 4), (3, 5), (3, 4), (4, 5)], [(0, 1)]]
    np.testing.assert_array_equal(plan.weights, np.maximum(w, w.T))
    assert plan.pairs == [(2, 3), (2, 4), (3, 5), (3, 4), (4, 5), (0, 1)]
    lone = plan_pairs(np.zeros((3, 3)))
    assert lone.groups == [[0], [1], [2]] and lone.sequences == [[], [], []]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_sequence_starts_with_a_maximum_spanning_tree(seed):
    rng = np.random.default_rng(seed)
    n = 7
    w = np.triu(rng.uniform(1.0, 10.0, (n, n)) * (rng.random((n, n)) < 0.6), 1)
    w[np.arange(n - 1), np.arange(1, n)] += 0.5  # a chain keeps the graph connected
    plan = plan_pairs(w)
    sym = np.maximum(w, w.T)
    assert plan.groups == [list(range(n))]
    seq = plan.sequences[0]
    tree, rest = seq[: n - 1], seq[n - 1:]
    assert tree[0] == tuple(np.unravel_index(np.argmax(np.triu(sym)), sym.shape))
    joined = set(tree[0])
    for i, j in tree[1:]:  # every tree pair links one new camera to the joined ones
        assert (i in joined) != (j in joined)
        joined |= {i, j}
    # its total weight is the maximum over spanning trees (MST of weight -> max - weight)
    cost = np.where(sym > 0, sym.max() + 1.0 - sym, 0.0)
    mst = minimum_spanning_tree(np.triu(cost)).toarray()
    best = ((sym.max() + 1.0) * (n - 1)) - mst.sum()
    assert sum(sym[p] for p in tree) == pytest.approx(best)
    # then every other linked pair once, heaviest first
    assert sorted(seq) == sorted(zip(*np.nonzero(np.triu(sym)), strict=True))
    assert [sym[p] for p in rest] == sorted((sym[p] for p in rest), reverse=True)


def test_rig_facing_away_camera_is_its_own_group():
    """Predicted links (conditioning x shared view) of a ring of five cameras looking at the
    tissue plus one looking away: one group of five, the odd camera alone, and the
    sequence's first pair is the closest-together pair of the ring."""
    ring = arc([-40.0, -15.0, 0.0, 30.0, 60.0])
    poses = np.concatenate([ring, [look_at([0.0, 0.0, 0.08], [0.0, 0.05, 0.2])]])
    pred = predict(poses)
    plan = plan_pairs(pred.conditioning * pred.overlap)
    assert plan.groups == [[0, 1, 2, 3, 4], [5]]
    assert plan.sequences[0][0] == (1, 2)  # 15 deg apart, the smallest angle
    assert plan.sequences[1] == []
