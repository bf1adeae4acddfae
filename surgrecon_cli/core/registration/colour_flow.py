"""Along-surface shifts pooled over deformation nodes from the target's colour field
(`register_pair` at a cut, with colour used; issue 28).

A nearest match in position + colour pins one point along the surface to about sqrt(2) s / g
(colour noise s against a texture gradient g, 0.7-0.9 mm on the stray tissues) and follows
the point when it is slid (0.6 of the slide): a cell of points settles at its matches' noise
/ (1 - follow). Here the target's colour around each moved point is a local linear model on
the tangent plane of its nearest target point (colour and 2D gradient, weighted least
squares over the FLOW_TARGET_NEIGHBOURS nearest target points; the fitted gradient's own
expected noise is taken off J^T J), and each deformation node takes the tangential shift t
that minimises the robust sum over the points blended to it and to its smoothness
neighbours of |source colour - model colour at x + t|^2 / noise^2 (one Gauss-Newton step per
iteration, FLOW_STEPS; Cauchy weights at the 99.9 % quantile of the misfit under noise
alone, so strays do not decide it; target rim points give no data). Each principal direction
of a node's pooled information moves only where its gain beats FLOW_MIN_GAIN (on flat
texture, or along the direction a one-way texture does not measure, it does not move), by
at most FLOW_MAX_STEP_SPACINGS target spacings per step; at the end a node keeps its shift
only where its pooled misfit fell by more than FLOW_MIN_DROP (scaled by its misfit per point
over the median node's where larger). Points take the blend of their nodes' shifts.
Inputs and outputs in metres, colours 0..1.
"""

from __future__ import annotations

import numpy as np
from scipy import sparse

from . import graph
from .colour import ColourDecision
from .overlap import ColouredPoints, MotionTest

FLOW_TARGET_NEIGHBOURS = 16  # target points each local colour model is fitted over
FLOW_SIGMA_SPACINGS = 1.5  # Gaussian weight of the local fit, in target spacings
FLOW_STEPS = 2  # Gauss-Newton steps
FLOW_ROBUST = 16.27  # chi-square, 3 degrees of freedom, 99.9 %: the Cauchy scale
FLOW_MIN_GAIN = 6.63  # chi-square, 1 degree of freedom, 99 %: least gain of a direction
FLOW_MAX_STEP_SPACINGS = 1.0  # a node's largest shift per step, in target spacings
FLOW_MIN_DROP = 9.21  # chi-square, 2 degrees of freedom, 99 %: a node's least final gain


def tangent_bases(normal: np.ndarray) -> np.ndarray:
    """(P, 3, 2) orthonormal bases of the planes with unit normals normal (P, 3)."""
    axis = np.where(np.abs(normal[:, :1]) < 0.9, np.array([[1.0, 0, 0]]),
                    np.array([[0, 1.0, 0]]))
    e1 = axis - (axis * normal).sum(axis=1)[:, None] * normal
    e1 /= np.linalg.norm(e1, axis=1)[:, None]
    return np.stack([e1, np.cross(normal, e1)], axis=2)


def local_colour_model(positions: np.ndarray, target: ColouredPoints,
                       spacing_m: float) -> tuple[np.ndarray, ...]:
    """At positions (P, 3) m: the target's colour (P, 3), its gradient (P, 2, 3) per metre
    along the tangent basis (P, 3, 2) of the nearest target point's plane, the variance
    factor of the fitted colour (P,), the covariance factor of the gradient (P, 2, 2) per
    metre^2 (their covariance / a target point's colour variance) and the nearest target
    point (P,); a weighted least-squares plane through the colours of the
    FLOW_TARGET_NEIGHBOURS target points nearest each position."""
    assert target.normal is not None
    k = min(FLOW_TARGET_NEIGHBOURS, len(target.xyz))
    d, j = target.tree.query(positions, k=k)
    d, j = d.reshape(len(positions), k), j.reshape(len(positions), k)
    offset = target.xyz[j] - positions[:, None, :]
    basis = tangent_bases(target.normal[j[:, 0]])
    uv = offset @ basis / spacing_m  # (P, k, 2), spacings
    w = np.exp(-0.5 * (d / (FLOW_SIGMA_SPACINGS * spacing_m)) ** 2) + 1e-9
    w /= w.sum(axis=1)[:, None]
    # centred on the weighted mean position: colour = mean + gradient (x - mean); the
    # position itself lies at back = -(the weighted mean offset)
    back = -(w[:, None, :] @ uv)  # (P, 1, 2)
    uv += back
    wuv = uv * w[:, :, None]
    s = wuv.transpose(0, 2, 1) @ uv  # (P, 2, 2)
    det = np.maximum(s[:, 0, 0] * s[:, 1, 1] - s[:, 0, 1] ** 2, 1e-12)
    inv = np.empty_like(s)
    inv[:, 0, 0], inv[:, 1, 1] = s[:, 1, 1] / det, s[:, 0, 0] / det
    inv[:, 0, 1] = inv[:, 1, 0] = -s[:, 0, 1] / det
    rgb = target.rgb[j]  # (P, k, 3)
    grad = inv @ (wuv.transpose(0, 2, 1) @ rgb)  # (P, 2, 3) per spacing
    colour = (w[:, None, :] @ rgb + back @ grad)[:, 0, :]
    # covariances with independent noise of unit variance
    cov_g = inv @ ((wuv * w[:, :, None]).transpose(0, 2, 1) @ uv) @ inv
    var = (w * w).sum(axis=1) + (back @ cov_g @ back.transpose(0, 2, 1))[:, 0, 0]
    return colour, grad / spacing_m, basis, var, cov_g / spacing_m**2, j[:, 0]


def colour_flow(test: MotionTest, target: ColouredPoints, decision: ColourDecision,
                nodes: graph.NodeBlend) -> np.ndarray:
    """(N, 3) m: the supported points of test (registered positions, source colours) shifted
    along the target's surface by their nodes' pooled colour shifts (module docstring);
    nodes: `register`'s deformation nodes (`graph.node_blend`); a node's shift pools its
    smoothness neighbours' points too. Points not supported do not move and do not count."""
    pos = test.registered.copy()
    have = np.flatnonzero(test.supported)
    if len(have) == 0 or target.normal is None or len(target.xyz) < FLOW_TARGET_NEIGHBOURS:
        return pos
    h = max(decision.spacing_m, 1e-9)
    s2 = max(decision.noise, 1e-6) ** 2
    n_nodes, k = nodes.count, nodes.idx.shape[1]
    pool = sparse.csr_matrix((np.ones(len(nodes.a) + n_nodes), (
        np.r_[nodes.a, np.arange(n_nodes)], np.r_[nodes.b, np.arange(n_nodes)])),
        shape=(n_nodes, n_nodes))  # each node with its smoothness neighbours
    weights = sparse.csr_matrix((nodes.w[have].ravel(), nodes.idx[have].ravel(),
                                 np.arange(0, len(have) * k + 1, k)), shape=(len(have), n_nodes))
    pooled = (pool @ weights.T).tocsr()  # the supported points to their nodes' pools
    rgb = test.source_rgb[have]
    start = pos[have].copy()
    moved = np.zeros((n_nodes, 3))  # each node's shift so far
    first = None
    for step in range(FLOW_STEPS + 1):
        colour, grad, basis, var, cov_g, near = local_colour_model(pos[have], target, h)
        resid = rgb - colour  # (P, 3)
        noise2 = s2 * (1.0 + var)
        u = (resid**2).sum(axis=1) / noise2
        seen = np.ones(len(u))
        if target.rim is not None:  # at the rim of a cut the fit extrapolates from one side
            seen[target.rim[near]] = 0.0
        # each node's pooled robust misfit (Cauchy), the same data at every step
        misfit = pooled @ (seen * FLOW_ROBUST * np.log1p(u / FLOW_ROBUST))
        if first is None:
            first = misfit
            # where the model explains the data worse than at the median node (texture
            # finer than the target resolves), the node's gains count in units of its own
            # misfit per point
            level = misfit / np.maximum(pooled @ seen, 1e-12)
            excess = np.maximum(level / max(float(np.median(level)), 1e-12), 1.0)
        if step == FLOW_STEPS:
            break
        rho = seen / (1.0 + u / FLOW_ROBUST) / noise2
        # in the point's tangent basis: J^T J (2x2) less the expected part of the fitted
        # gradient's own noise (s^2 cov_g over the three channels: it would shrink the
        # shifts towards 0), and J^T r (2)
        jtj = grad @ grad.transpose(0, 2, 1) - s2 * cov_g
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
        # along each principal direction of the pooled information on its own: the
        # component moves only where its gain beats noise (a texture that changes along
        # one direction only says nothing about the other)
        lam, vec = np.linalg.eigh(h2)
        along = (vec.transpose(0, 2, 1) @ b2[:, :, None])[:, :, 0]  # (M, 2)
        gain = along**2 / np.maximum(lam, 1e-30) / excess[:, None]
        comp = np.where((gain > FLOW_MIN_GAIN) & (lam > 0), along / np.maximum(lam, 1e-30),
                        0.0)
        t2 = (vec @ comp[:, :, None])[:, :, 0]
        size = np.linalg.norm(t2, axis=1)
        t2 *= np.minimum(1.0, FLOW_MAX_STEP_SPACINGS * h / np.maximum(size, 1e-30))[:, None]
        if not t2.any():
            break
        step_nodes = (nb @ t2[:, :, None])[:, :, 0]
        moved += step_nodes
        pos[have] += weights @ step_nodes
    # a node keeps its shift only where its pooled misfit fell by more than chance would
    # give a fitted 2D shift (the Gauss-Newton model may have misled it)
    keep = first - misfit > FLOW_MIN_DROP * excess
    pos[have] = start + weights @ (moved * keep[:, None])
    return pos
