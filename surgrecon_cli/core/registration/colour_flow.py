"""Along-surface shifts pooled over deformation nodes from the target's colour field
(`register_pair`, with colour used; issue 28).

A nearest match in position + colour pins one point along the surface to about sqrt(2) s / g
(colour noise s against a texture gradient g, 0.7-0.9 mm on the stray tissues) and follows
the point when it is slid (0.6 of the slide): a cell of points settles at its matches' noise
/ (1 - follow). Here the target's colour around each moved point is a local linear model on
the target's tangent plane (colour and its 2D gradient, weighted least squares over the
FLOW_TARGET_NEIGHBOURS nearest target points), and each deformation node takes the
tangential shift t that minimises the robust sum over its blended points of
|source colour - model colour at x + t|^2 / noise^2 (one Gauss-Newton step; Cauchy weights at
the 99.9 % quantile of the misfit under noise alone, so strays do not decide it). A node
moves only where the step lowers that sum by more than FLOW_MIN_GAIN (chi-square with 2
degrees of freedom, 99 %: on flat texture, or with too few points, it does not move), by at
most one target spacing per step; points take the blend of their nodes' shifts.
Inputs and outputs in metres, colours 0..1.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy import sparse
from scipy.spatial import cKDTree

from . import graph

from .colour import ColourDecision
from .overlap import ColouredPoints, MotionTest

FLOW_TARGET_NEIGHBOURS = 16  # target points each local colour model is fitted over
FLOW_SIGMA_SPACINGS = 1.5  # Gaussian weight of the local fit, in target spacings
FLOW_STEPS = 3
FLOW_ROBUST = 16.27  # chi-square, 3 degrees of freedom, 99.9 %: the Cauchy scale
FLOW_MIN_GAIN = 9.21  # chi-square, 2 degrees of freedom, 99 %: a node's least gain
FLOW_MAX_STEP_SPACINGS = 1.0
FLOW_DEBIAS = 1.0
FLOW_STRIDE = 2  # every 2nd supported point is a data point  # a node's largest shift per step, in target spacings


def tangent_bases(normal: np.ndarray) -> np.ndarray:
    """(P, 3, 2) orthonormal bases of the planes with unit normals normal (P, 3)."""
    axis = np.where(np.abs(normal[:, :1]) < 0.9, np.array([[1.0, 0, 0]]),
                    np.array([[0, 1.0, 0]]))
    e1 = axis - (axis * normal).sum(axis=1)[:, None] * normal
    e1 /= np.linalg.norm(e1, axis=1)[:, None]
    return np.stack([e1, np.cross(normal, e1)], axis=2)


def local_colour_model(positions: np.ndarray, target: ColouredPoints, spacing_m: float
                       ) -> tuple[np.ndarray, ...]:
    """At positions (P, 3) m: the target's colour (P, 3), its gradient (P, 2, 3) per metre
    along the tangent basis (P, 3, 2) of the nearest target point's plane, the variance
    factor of the fitted colour (P,) and the covariance factor of the gradient (P, 2, 2)
    per metre^2 (their covariance / a target point's colour variance); a weighted
    least-squares plane through the FLOW_TARGET_NEIGHBOURS nearest target points' colours."""
    assert target.normal is not None
    k = min(FLOW_TARGET_NEIGHBOURS, len(target.xyz))
    d, j = target.tree.query(positions, k=k)
    d, j = d.reshape(len(positions), k), j.reshape(len(positions), k)
    basis = tangent_bases(target.normal[j[:, 0]])
    offset = target.xyz[j] - positions[:, None, :]
    u = (offset * basis[:, None, :, 0]).sum(axis=2) / spacing_m  # (P, k), spacings
    v = (offset * basis[:, None, :, 1]).sum(axis=2) / spacing_m
    w = np.exp(-0.5 * (d / (FLOW_SIGMA_SPACINGS * spacing_m)) ** 2) + 1e-9
    w /= w.sum(axis=1)[:, None]
    # centred on the weighted mean position: colour = mean + gradient (x - mean)
    u -= (w * u).sum(axis=1)[:, None]
    v -= (w * v).sum(axis=1)[:, None]
    mean_u, mean_v = (w * u).sum(axis=1), (w * v).sum(axis=1)  # ~0, kept for exactness
    suu, suv, svv = (w * u * u).sum(axis=1), (w * u * v).sum(axis=1), (w * v * v).sum(axis=1)
    det = np.maximum(suu * svv - suv**2, 1e-12)
    inv = np.stack([np.stack([svv, -suv], axis=1), np.stack([-suv, suu], axis=1)],
                   axis=1) / det[:, None, None]  # (P, 2, 2)
    rgb = target.rgb[j]  # (P, k, 3)
    mean_rgb = np.einsum("pk,pkc->pc", w, rgb)
    moments = np.stack([np.einsum("pk,pkc->pc", w * u, rgb),
                        np.einsum("pk,pkc->pc", w * v, rgb)], axis=1)  # (P, 2, 3)
    grad = inv @ moments  # per spacing
    # the mean position lies at -(mean of the offsets) from the point
    centre = np.stack([mean_u, mean_v], axis=1)
    back = -(offset * w[:, :, None]).sum(axis=1) / spacing_m
    back = np.stack([(back * basis[:, :, 0]).sum(axis=1),
                     (back * basis[:, :, 1]).sum(axis=1)], axis=1) - centre
    colour = mean_rgb + (back[:, :, None] * grad).sum(axis=1)
    # covariances with independent noise of unit variance
    w2 = w * w
    quad = np.stack([np.stack([(w2 * u * u).sum(axis=1), (w2 * u * v).sum(axis=1)], axis=1),
                     np.stack([(w2 * u * v).sum(axis=1), (w2 * v * v).sum(axis=1)], axis=1)],
                    axis=1)
    cov_g = inv @ quad @ inv
    var = w2.sum(axis=1) + np.einsum("pi,pij,pj->p", back, cov_g, back)
    return colour, grad / spacing_m, basis, var, cov_g / spacing_m**2


def colour_flow(test: MotionTest, target: ColouredPoints, decision: ColourDecision,
                nodes: NodeBlend) -> np.ndarray:
    """(N, 3) m: the supported points of test (registered positions, source colours) shifted
    along the target's surface by their nodes' pooled colour shifts (module docstring);
    nodes: `register`'s deformation nodes (`node_blend`); a node's shift pools its
    smoothness neighbours' points too. Points not supported do not move and do not count."""
    pos = test.registered.copy()
    have = np.flatnonzero(test.supported)
    if len(have) == 0 or target.normal is None or len(target.xyz) < FLOW_TARGET_NEIGHBOURS:
        return pos
    h = max(decision.spacing_m, 1e-9)
    s2 = max(decision.noise, 1e-6) ** 2
    n_nodes, k = nodes.pool.shape[0], nodes.idx.shape[1]
    weights = sparse.csr_matrix((nodes.w[have].ravel(), nodes.idx[have].ravel(),
                                 np.arange(0, len(have) * k + 1, k)), shape=(len(have), n_nodes))
    # the data: a spread sample of the supported points (every FLOW_STRIDE-th)
    data = np.arange(0, len(have), FLOW_STRIDE)
    pooled = (nodes.pool @ weights[data].T).tocsr()  # sample points to their nodes' pools
    rgb = test.source_rgb[have[data]]
    for _ in range(FLOW_STEPS):
        colour, grad, basis, var, cov_g = local_colour_model(pos[have[data]], target, h)
        resid = rgb - colour  # (P, 3)
        noise2 = s2 * (1.0 + var)
        u = (resid**2).sum(axis=1) / noise2
        rho = 1.0 / (1.0 + u / FLOW_ROBUST) / noise2
        # in the point's tangent basis: J^T J (2x2) less the expected part of the fitted
        # gradient's own noise (s^2 cov_g over the three channels: it would shrink the
        # shifts towards 0), and J^T r (2)
        jtj = grad @ grad.transpose(0, 2, 1) - FLOW_DEBIAS * s2 * cov_g
        jtr = (grad @ resid[:, :, None])[:, :, 0]
        hess = pooled @ (rho[:, None, None] * (basis @ jtj @ basis.transpose(0, 2, 1))
                         ).reshape(-1, 9)
        grad_n = pooled @ (rho[:, None] * (basis @ jtr[:, :, None])[:, :, 0])
        # the node's normal: the main axis of its points' normals (their signs are arbitrary)
        normal = np.cross(basis[:, :, 0], basis[:, :, 1])
        spread = pooled @ (normal[:, :, None] * normal[:, None, :]).reshape(-1, 9)
        normal = np.linalg.eigh(spread.reshape(-1, 3, 3) + 1e-12 * np.eye(3))[1][:, :, 2]
        nb = tangent_bases(normal)
        h2 = nb.transpose(0, 2, 1) @ hess.reshape(-1, 3, 3) @ nb
        b2 = (nb.transpose(0, 2, 1) @ grad_n[:, :, None])[:, :, 0]
        h2 += 1e-9 * (np.trace(h2, axis1=1, axis2=2)[:, None, None] + 1e-30) * np.eye(2)
        t2 = np.linalg.solve(h2, b2[:, :, None])[:, :, 0]
        lowest = np.linalg.eigvalsh(h2)[:, 0]
        gain = (t2 * b2).sum(axis=1)  # the Gauss-Newton decrease of the summed misfit
        size = np.linalg.norm(t2, axis=1)
        cap = FLOW_MAX_STEP_SPACINGS * h
        t2 *= np.minimum(1.0, cap / np.maximum(size, 1e-30))[:, None]
        t2[(gain <= FLOW_MIN_GAIN) | (lowest <= 0)] = 0.0
        if not t2.any():
            break
        shift = weights @ (nb @ t2[:, :, None])[:, :, 0]
        pos[have] += shift
    return pos


@dataclasses.dataclass(frozen=True)
class NodeBlend:
    """Each point's deformation nodes idx (N, k) and blend weights w (N, k), and pool
    (M, M): each node's sum over itself and its smoothness neighbours (`register`'s graph)."""

    idx: np.ndarray
    w: np.ndarray
    pool: sparse.csr_matrix


def node_blend(source: np.ndarray, max_nodes: int, interp_neighbors: int,
               k_neighbors: int) -> NodeBlend:
    """The deformation nodes of source (N, 3) m as `register` samples, blends and links
    them (`graph.sample_nodes`, `graph.interpolation`, `graph.neighbour_edges`; the same
    nodes at any scale and offset); one node per point when max_nodes is 0 or the cloud is
    that small."""
    n = len(source)
    if max_nodes <= 0 or n <= max_nodes:
        nodes = source
        idx, w = np.arange(n)[:, None], np.ones((n, 1))
        tree = cKDTree(nodes)
    else:
        nodes = source[graph.sample_nodes(source, max_nodes)]
        tree = cKDTree(nodes)
        idx, w = graph.interpolation(source, nodes, tree, interp_neighbors)
    a, b = graph.neighbour_edges(nodes, tree, k_neighbors)
    m = len(nodes)
    pool = sparse.csr_matrix((np.ones(len(a) + m), (np.r_[a, np.arange(m)],
                                                    np.r_[b, np.arange(m)])), shape=(m, m))
    return NodeBlend(idx, w, pool)
