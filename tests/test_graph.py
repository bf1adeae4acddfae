"""Nodes, neighbour graph and the operators D, B, L of the registration energy
(core/registration/graph.py), checked against brute force and against exact identities:
a global affine motion has zero smoothness residual and is reproduced exactly by D.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree
from scipy.spatial.distance import cdist

from surgrecon_cli.core.registration import graph
from surgrecon_cli.errors import GeometryError


def grid(nx: int, ny: int, h: float = 1.0) -> np.ndarray:
    gx, gy = np.meshgrid(np.arange(nx) * h, np.arange(ny) * h, indexing="ij")
    return np.column_stack([gx.ravel(), gy.ravel(), np.zeros(nx * ny)])


def edges(nodes: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    return graph.neighbour_edges(nodes, cKDTree(nodes), k)


def knn_sets(nodes: np.ndarray, k: int) -> list[set[int]]:
    """Brute force: the k nearest other nodes of each node (no ties in random points)."""
    d = cdist(nodes, nodes)
    np.fill_diagonal(d, np.inf)
    return [set(np.argsort(row)[:k].tolist()) for row in d]


def affine_field(nodes: np.ndarray, A: np.ndarray, t: np.ndarray) -> np.ndarray:
    """X (4M, 3) of the global map y = q A + t (row vectors) in node-local coordinates:
    X_n = [A; g_n A + t], so that [q - g_n, 1] X_n = q A + t."""
    X = np.zeros((len(nodes), 4, 3))
    X[:, :3, :] = A
    X[:, 3, :] = nodes @ A + t
    return X.reshape(-1, 3)


@pytest.fixture(scope="module")
def cloud() -> np.ndarray:
    return np.random.default_rng(1).uniform(-1.0, 1.0, (80, 3))


# ---- neighbour graph ----------------------------------------------------------------------


@pytest.mark.parametrize("k", [1, 3, 8])
def test_edges_are_the_symmetrised_knn_graph(cloud, k):
    a, b = edges(cloud, k)
    pairs = set(zip(a.tolist(), b.tolist(), strict=True))
    assert len(pairs) == len(a)  # no duplicates
    assert all(i != j for i, j in pairs)  # no self loops
    assert pairs == {(j, i) for i, j in pairs}  # symmetric
    nn = knn_sets(cloud, k)
    expected = {(i, j) for i in range(len(cloud)) for j in nn[i]}
    assert pairs == expected | {(j, i) for i, j in expected}
    # hence: every node has at least k neighbours, and an edge is never longer than the
    # k-th neighbour distance of one of its ends
    degree = np.bincount(a, minlength=len(cloud))
    assert degree.min() >= k
    d = cdist(cloud, cloud)
    np.fill_diagonal(d, np.inf)
    r_k = np.sort(d, axis=1)[:, k - 1]
    length = np.linalg.norm(cloud[a] - cloud[b], axis=1)
    assert (length <= np.maximum(r_k[a], r_k[b]) + 1e-12).all()


def test_k_at_least_the_node_count_gives_the_complete_graph():
    nodes = np.random.default_rng(2).normal(size=(6, 3))
    a, _ = edges(nodes, 10)
    assert len(a) == 6 * 5
    assert edges(nodes[:1], 4)[0].size == 0  # a single node has no edge


def test_grid_graph_is_connected_and_holds_the_grid_neighbours():
    nodes = grid(8, 6, h=0.5)
    a, b = edges(nodes, 4)
    adjacency = np.zeros((len(nodes), len(nodes)), bool)
    adjacency[a, b] = True
    assert connected_components(adjacency, directed=False)[0] == 1
    d = cdist(nodes, nodes)
    axis_neighbours = np.isclose(d, 0.5)
    assert adjacency[axis_neighbours].all()  # every grid neighbour is linked
    # a corner's 4th nearest is two cells away (2 at h, 1 at h sqrt 2, then 2 h); none farther
    assert (np.linalg.norm(nodes[a] - nodes[b], axis=1) <= 2 * 0.5 + 1e-12).all()


def test_far_apart_clusters_are_not_linked():
    rng = np.random.default_rng(3)
    left = rng.normal(0.0, 0.1, (20, 3))
    right = rng.normal(0.0, 0.1, (20, 3)) + np.array([10.0, 0.0, 0.0])
    nodes = np.vstack([left, right])
    a, b = edges(nodes, 5)
    assert ((a < 20) == (b < 20)).all()
    adjacency = np.zeros((40, 40), bool)
    adjacency[a, b] = True
    assert connected_components(adjacency, directed=False)[0] == 2


# ---- operators ----------------------------------------------------------------------------


def test_smoothness_of_a_global_affine_motion_is_zero(cloud):
    """Row e of B is T_a(g_a) - T_b(g_a): zero for any one affine map, whatever the graph."""
    a, b = edges(cloud, 6)
    B = graph.smoothness_operator(cloud, a, b)
    assert B.shape == (len(a), 4 * len(cloud))
    rng = np.random.default_rng(4)
    A, t = rng.normal(size=(3, 3)), rng.normal(size=3)
    np.testing.assert_allclose(B @ affine_field(cloud, A, t), 0.0, atol=1e-12)
    # incidence structure: the translation entries of each row are +1 (a) and -1 (b)
    dense = B.toarray()
    translation = dense[:, 3::4]
    np.testing.assert_array_equal(translation.sum(axis=1), 0.0)
    np.testing.assert_array_equal(translation[np.arange(len(a)), a], 1.0)
    np.testing.assert_array_equal(translation[np.arange(len(a)), b], -1.0)
    # the linear part of b is weighted by the edge vector g_a - g_b
    for e in range(0, len(a), 17):
        np.testing.assert_allclose(dense[e, 4 * b[e]: 4 * b[e] + 3], -(cloud[a[e]] - cloud[b[e]]))


def test_smoothness_sees_exactly_the_edges_of_a_moved_node(cloud):
    a, b = edges(cloud, 6)
    B = graph.smoothness_operator(cloud, a, b)
    X = affine_field(cloud, np.eye(3), np.zeros(3)).reshape(-1, 4, 3)
    shift = np.array([0.0, 0.2, -0.1])
    X[7, 3, :] += shift  # node 7 alone translated
    residual = B @ X.reshape(-1, 3)
    touches = (a == 7) | (b == 7)
    np.testing.assert_allclose(residual[~touches], 0.0, atol=1e-12)
    np.testing.assert_allclose(residual[a == 7], np.tile(shift, ((a == 7).sum(), 1)), atol=1e-12)
    np.testing.assert_allclose(residual[b == 7], np.tile(-shift, ((b == 7).sum(), 1)), atol=1e-12)


def test_data_operator_reproduces_an_affine_motion_of_blended_points(cloud):
    """Blend weights are convex (>= 0, sum 1, nearest node first and heaviest), so D moves
    every point by a global affine map exactly."""
    points = np.random.default_rng(5).uniform(-1.0, 1.0, (200, 3))
    tree = cKDTree(cloud)
    idx, w = graph.interpolation(points, cloud, tree, 4)
    assert idx.shape == w.shape == (200, 4)
    assert (w >= 0).all()
    np.testing.assert_allclose(w.sum(axis=1), 1.0, atol=1e-12)
    np.testing.assert_array_equal(idx[:, 0], tree.query(points)[1])
    assert (np.diff(w, axis=1) <= 1e-12).all()  # weights fall with the distance
    D = graph.data_operator(points, cloud, idx, w)
    rng = np.random.default_rng(6)
    A, t = rng.normal(size=(3, 3)), rng.normal(size=3)
    np.testing.assert_allclose(D @ affine_field(cloud, A, t), points @ A + t, atol=1e-12)


def test_blend_weights_are_continuous_where_the_node_set_changes(cloud):
    """A node's weight falls to 0 as it leaves a point's k nearest, so the blended field has
    no seams: along a fine path through the cloud no weight jumps."""
    s = np.linspace(0.0, 1.0, 4001)[:, None]
    path = (1 - s) * np.array([-0.9, -0.8, -0.7]) + s * np.array([0.9, 0.8, 0.6])
    idx, w = graph.interpolation(path, cloud, cKDTree(cloud), 4)
    dense = np.zeros((len(path), len(cloud)))
    np.put_along_axis(dense, idx, w, axis=1)
    changes = (np.sort(idx, axis=1)[1:] != np.sort(idx, axis=1)[:-1]).any(axis=1).sum()
    assert changes >= 10  # the path crosses many changes of the node set
    assert np.abs(np.diff(dense, axis=0)).max() < 0.02


def test_linear_selector_picks_the_linear_parts(cloud):
    X = np.random.default_rng(7).normal(size=(len(cloud), 4, 3))
    L = graph.linear_selector(len(cloud))
    np.testing.assert_array_equal(L @ X.reshape(-1, 3), X[:, :3, :].reshape(-1, 3))


# ---- nodes and normalisation --------------------------------------------------------------


def test_sample_nodes_spreads_the_requested_count_evenly():
    rng = np.random.default_rng(8)
    points = np.column_stack([rng.uniform(0, 1, 4000), rng.uniform(0, 1, 4000),
                              0.05 * rng.normal(size=4000)])
    nodes = graph.sample_nodes(points, 100)
    assert np.array_equal(nodes, np.unique(nodes))
    assert 80 <= len(nodes) <= 120
    # every point is near a node: within ~ one cell of a square cell per node (1 / sqrt(100))
    gap = cKDTree(points[nodes]).query(points)[0]
    assert gap.max() < 2.0 / np.sqrt(len(nodes))
    # the same node positions whatever the order of the points
    order = rng.permutation(len(points))
    again = graph.sample_nodes(points[order], 100)
    assert {tuple(p) for p in points[nodes]} == {tuple(p) for p in points[order][again]}
    np.testing.assert_array_equal(graph.sample_nodes(points[:50], 100), np.arange(50))


def test_mean_spacing_and_normalisation():
    nodes = grid(10, 10, h=0.002)  # 2 mm grid, metres
    assert graph.mean_spacing(nodes) == pytest.approx(0.002)
    norm = graph.normalisation(nodes, cKDTree(nodes), reference_nodes=25)
    # unit: the spacing a 25-node sampling of the same surface has, h sqrt(N / 25)
    assert norm.unit == pytest.approx(0.002 * np.sqrt(100 / 25))
    assert norm.spacing == pytest.approx(0.5)
    np.testing.assert_allclose(norm.centre, nodes.mean(axis=0))
    q = norm.to_internal(nodes)
    np.testing.assert_allclose(q.mean(axis=0), 0.0, atol=1e-12)
    np.testing.assert_allclose(norm.to_metres(q), nodes, atol=1e-15)
    assert norm.mm(4.0) == pytest.approx(1.0)  # 4 mm = one 4 mm unit
    with pytest.raises(GeometryError):
        graph.mean_spacing(np.zeros((5, 3)))
