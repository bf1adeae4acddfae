"""Transform nodes, their neighbour graph and the sparse operators D and B of the energy.

Unknowns: one affine X_n (4x3, acting on the row vector [u 1]) per *node*. With one node per
point this is exactly the per-point model of Su et al. 2019 (section II.D). Larger clouds are
solved on a subsampled deformation graph (Yang et al. 2015 and its follow-up RPTS both
register with a deformation graph, coarse to fine); each point's transform is then the
convex blend of its nearest nodes' transforms, so every point still owns one affine.

Coordinates inside the solver are *normalised*: centred on the source centroid and divided by
the reference length `unit` (metres), see `normalisation`. Each node uses local coordinates
u = q - g_n (q: normalised point, g_n: normalised node position); then every entry of X_n is
O(1) and the system is well conditioned whatever the cloud's scale.

- D (P x 4M): row i gives the moved point i, sum_j phi_ij [q_i - g_nj, 1] X_nj.
- B (E x 4M): row e = (a -> b) gives T_a(g_a) - T_b(g_a) = [0 0 0 1] X_a - [g_a - g_b, 1] X_b,
  the smoothness residual p~_a (X_a - X_b) of eq. (RPTS) written in node-local coordinates.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from ...errors import GeometryError


@dataclass(frozen=True)
class Normalisation:
    """q = (p - centre) / unit; `unit` in metres, `spacing` = mean neighbour spacing in units."""

    centre: np.ndarray  # (3,) metres
    unit: float  # metres
    spacing: float  # mean nearest-neighbour spacing of the source, normalised units

    def to_internal(self, xyz: np.ndarray) -> np.ndarray:
        return (xyz - self.centre) / self.unit

    def to_metres(self, q: np.ndarray) -> np.ndarray:
        return q * self.unit + self.centre

    def mm(self, value_mm: float) -> float:
        """A length in millimetres expressed in normalised units."""
        return value_mm * 1e-3 / self.unit


def mean_spacing(xyz: np.ndarray, tree: cKDTree | None = None) -> float:
    """Mean distance of each point to its nearest other point (same unit as `xyz`)."""
    tree = tree or cKDTree(xyz)
    d, _ = tree.query(xyz, k=2)
    pos = d[:, 1][d[:, 1] > 0]
    if pos.size == 0:
        raise GeometryError("all source points coincide")
    return float(np.mean(pos))


def normalisation(source_xyz: np.ndarray, tree: cKDTree, reference_nodes: int) -> Normalisation:
    """Reference length: the node spacing a `reference_nodes`-node sampling of this surface has.

    For a surface sampled with mean spacing h by N points that is h * sqrt(N / reference_nodes):
    it depends on the surface's size, not on how densely it is sampled, so the smoothness
    weight means the same for a 2k and a 50k cloud of the same tissue (our choice).
    """
    centre = source_xyz.mean(axis=0)
    h = mean_spacing(source_xyz, tree)
    unit = h * np.sqrt(max(len(source_xyz), 1) / reference_nodes)
    return Normalisation(centre=centre, unit=float(unit), spacing=float(h / unit))


def sample_nodes(q: np.ndarray, n_nodes: int) -> np.ndarray:
    """Indices of about `n_nodes` points spread evenly (one per occupied voxel).

    The point nearest each voxel's centre is kept, so the choice does not depend on the
    order of the points. The voxel size is adjusted a few times to hit the count.
    """
    n = len(q)
    if n_nodes >= n:
        return np.arange(n)
    lo = q.min(axis=0)
    extent = np.ptp(q, axis=0).max()
    size = extent / np.sqrt(n_nodes)  # a surface: count ~ area / size^2
    best = np.arange(n)
    for attempt in range(8):
        cells = np.floor((q - lo) / size).astype(np.int64)
        dims = cells.max(axis=0) + 1
        keys = cells[:, 0] + dims[0] * (cells[:, 1] + dims[1] * cells[:, 2])
        found = len(np.unique(keys))
        if attempt == 0 or abs(found - n_nodes) < abs(len(best) - n_nodes):
            # within each voxel keep the point nearest the voxel centre
            dist = np.linalg.norm(q - (lo + (cells + 0.5) * size), axis=1)
            pick = np.lexsort((dist, keys))
            keep = np.ones(n, bool)
            keep[1:] = keys[pick[1:]] != keys[pick[:-1]]
            best = np.sort(pick[keep])
        if abs(found - n_nodes) <= 0.05 * n_nodes:
            break
        size *= np.sqrt(found / n_nodes)
    return best


def interpolation(
    q: np.ndarray, nodes_q: np.ndarray, node_tree: cKDTree, k: int
) -> tuple[np.ndarray, np.ndarray]:
    """Blend weights of the k nearest nodes of each point, (P, k) indices and weights.

    Weights (1 - d / d_max)^2 with d_max the distance to the (k+1)-th node, normalised
    (embedded deformation, Sumner et al. 2007): they fall to 0 as a node leaves the set, so
    the blended transform field is continuous.
    """
    m = len(nodes_q)
    if m == 1:
        return np.zeros((len(q), 1), np.int64), np.ones((len(q), 1))
    kk = min(k + 1, m)
    d, idx = node_tree.query(q, k=kk)
    d = d.reshape(len(q), kk)
    idx = idx.reshape(len(q), kk)
    dmax = d[:, -1:] if kk == k + 1 else d[:, -1:] * 1.5 + 1e-12
    w = np.clip(1.0 - d[:, : min(k, m)] / np.maximum(dmax, 1e-12), 0.0, None) ** 2
    idx = idx[:, : min(k, m)]
    w[:, 0] = np.where(w.sum(axis=1) <= 0, 1.0, w[:, 0])
    return idx.astype(np.int64), w / w.sum(axis=1, keepdims=True)


def neighbour_edges(nodes_q: np.ndarray, node_tree: cKDTree, k: int) -> tuple[np.ndarray, ...]:
    """Directed edges (a, b) of the symmetrised k-nearest-neighbour graph of the nodes."""
    m = len(nodes_q)
    kk = min(k + 1, m)
    if kk < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    _, idx = node_tree.query(nodes_q, k=kk)
    a = np.repeat(np.arange(m, dtype=np.int64), kk - 1)
    b = idx[:, 1:].ravel().astype(np.int64)
    keys = np.unique(np.concatenate([a * m + b, b * m + a]))
    a, b = keys // m, keys % m
    keep = a != b
    return a[keep], b[keep]


def data_operator(
    q: np.ndarray, nodes_q: np.ndarray, idx: np.ndarray, w: np.ndarray
) -> sp.csr_matrix:
    """D (P x 4M): row i = sum_j w_ij [q_i - g_idx_ij, 1] placed in block idx_ij."""
    p, k = idx.shape
    u = q[:, None, :] - nodes_q[idx]  # (P, k, 3)
    vals = np.concatenate([u, np.ones((p, k, 1))], axis=2) * w[:, :, None]
    cols = 4 * idx[:, :, None] + np.arange(4)
    rows = np.broadcast_to(np.arange(p)[:, None, None], cols.shape)
    return sp.csr_matrix(
        (vals.ravel(), (rows.ravel(), cols.ravel())), shape=(p, 4 * len(nodes_q))
    )


def smoothness_operator(nodes_q: np.ndarray, a: np.ndarray, b: np.ndarray) -> sp.csr_matrix:
    """B (E x 4M): row e = [0 0 0 1] in block a_e minus [g_a - g_b, 1] in block b_e."""
    e = len(a)
    vals_b = -np.concatenate([nodes_q[a] - nodes_q[b], np.ones((e, 1))], axis=1)
    rows = np.concatenate([np.arange(e), np.repeat(np.arange(e), 4)])
    cols = np.concatenate([4 * a + 3, (4 * b[:, None] + np.arange(4)).ravel()])
    vals = np.concatenate([np.ones(e), vals_b.ravel()])
    return sp.csr_matrix((vals, (rows, cols)), shape=(e, 4 * len(nodes_q)))


def linear_selector(m: int) -> sp.csr_matrix:
    """L (3M x 4M): picks the 3x3 linear part (rows 0..2) of every node block."""
    cols = (4 * np.arange(m)[:, None] + np.arange(3)).ravel()
    return sp.csr_matrix((np.ones(3 * m), (np.arange(3 * m), cols)), shape=(3 * m, 4 * m))


@dataclass(frozen=True)
class NodeBlend:
    """Deformation nodes of a cloud: each point's nodes idx (N, k) and blend weights w (N, k)
    (`interpolation`), the directed smoothness edges a, b (E,) (`neighbour_edges`) and the
    node count."""

    idx: np.ndarray
    w: np.ndarray
    a: np.ndarray
    b: np.ndarray
    count: int


def node_blend(xyz: np.ndarray, max_nodes: int, interp_neighbors: int,
               k_neighbors: int) -> NodeBlend:
    """The deformation nodes of xyz (N, 3) as `register` samples, blends and links them
    (the same nodes at any scale and offset of the cloud); one node per point when max_nodes
    is 0 or the cloud is that small."""
    n = len(xyz)
    if max_nodes <= 0 or n <= max_nodes:
        nodes, idx, w = xyz, np.arange(n)[:, None], np.ones((n, 1))
        tree = cKDTree(nodes)
    else:
        nodes = xyz[sample_nodes(xyz, max_nodes)]
        tree = cKDTree(nodes)
        idx, w = interpolation(xyz, nodes, tree, interp_neighbors)
    a, b = neighbour_edges(nodes, tree, k_neighbors)
    return NodeBlend(idx, w, a, b, len(nodes))
