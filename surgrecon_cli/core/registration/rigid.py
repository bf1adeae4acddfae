"""Robust rigid pre-alignment: trimmed point-to-plane ICP on a voxel subsample.

Trimmed ICP (Chetverikov et al. 2002) keeps the closest fraction of the mutually consistent
nearest-neighbour pairs; each step minimises the point-to-plane distance (Chen & Medioni
1992; linearised rotation) plus a small point-to-point term, which converges in a few steps
where point-to-point ICP creeps along smooth, nearly symmetric surfaces such as a dome.

Known pairs (template ids, landmarks) take part like nearest-neighbour pairs; with at least
`MIN_KNOWN` of them the pairs alone decide (an IRLS, l1-type fit, no nearest neighbours).
All lengths in the solver's normalised units.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..geometry.poses import fit_rigid
from .correspondences import MATCH_EPS, Matcher, match
from .globalinit import global_align
from .graph import mean_spacing as graph_spacing
from .graph import sample_nodes

# All numbers here are ours, tuned on synthetic domes (benchmarks/registration.py).
MIN_KNOWN = 6  # known pairs needed to skip nearest neighbours
MAX_POINTS = 500  # rigid alignment runs on at most this many (voxel-subsampled) source points
PLANE_POINT_MIX = 0.3  # weight of the point-to-point term in the point-to-plane step
CAUCHY_SCALE = 2.0  # Cauchy weight scale, x the median residual of the kept pairs
# clouds start "far apart" when the median nearest-target distance exceeds the gate and this
# fraction of the source's RMS radius (ours; the global search must then also beat the ICP
# from the identity clearly, globalinit.GLOBAL_MARGIN)
GLOBAL_SPREAD = 0.15
NODE_SAMPLES = 8  # ours: points per node (on average, at least) deciding rigid vs identity


class _Normals:
    """Target normals by PCA of the k nearest neighbours, computed on demand and cached."""

    def __init__(self, target_q: np.ndarray, tree: cKDTree, k: int = 10) -> None:
        self.q = target_q
        self.k = min(k, len(target_q))
        self.tree = tree
        self.cache = np.full((len(target_q), 3), np.nan)

    def __call__(self, which: np.ndarray) -> np.ndarray:
        todo = np.unique(which[np.isnan(self.cache[which, 0])])
        if len(todo):
            _, nn = self.tree.query(self.q[todo], k=self.k)
            nb = self.q[nn.reshape(len(todo), self.k)]
            nb = nb - nb.mean(axis=1, keepdims=True)
            _, vecs = np.linalg.eigh(np.einsum("pki,pkj->pij", nb, nb))
            self.cache[todo] = vecs[:, :, 0]
        return self.cache[which]


def _plane_step(src: np.ndarray, dst: np.ndarray, normals: np.ndarray, w: np.ndarray):
    """Small rigid motion (R, t) reducing sum w ((R s + t - d) . n)^2 + mix w |R s + t - d|^2."""
    c = (w @ src) / w.sum()
    s = src - c
    a = np.concatenate([np.cross(s, normals), normals], axis=1)  # (P, 6): [omega, tau]
    b = np.einsum("pi,pi->p", dst - src, normals)
    H = a.T @ (a * w[:, None])
    g = a.T @ (b * w)
    # point-to-point part: (omega x s + tau - (d - s)) for every axis
    skew = np.zeros((len(s), 3, 6))
    skew[:, 0, 1], skew[:, 0, 2] = s[:, 2], -s[:, 1]
    skew[:, 1, 0], skew[:, 1, 2] = -s[:, 2], s[:, 0]
    skew[:, 2, 0], skew[:, 2, 1] = s[:, 1], -s[:, 0]
    skew[:, :, 3:] = np.eye(3)
    H += PLANE_POINT_MIX * np.einsum("p,pki,pkj->ij", w, skew, skew)
    g += PLANE_POINT_MIX * np.einsum("p,pki,pk->i", w, skew, dst - src)
    x = np.linalg.solve(H + 1e-9 * np.trace(H) * np.eye(6), g)
    omega, tau = x[:3], x[3:]
    angle = np.linalg.norm(omega)
    K = np.array([[0, -omega[2], omega[1]], [omega[2], 0, -omega[0]], [-omega[1], omega[0], 0]])
    if angle > 1e-12:
        R = np.eye(3) + np.sin(angle) / angle * K + (1 - np.cos(angle)) / angle**2 * (K @ K)
    else:
        R = np.eye(3) + K
    return R, c + tau - R @ c


def _l1_fit(src: np.ndarray, dst: np.ndarray, iterations: int = 10):
    """Rigid fit minimising sum |R s + t - d| (IRLS; floor 0.1 x median residual, ours)."""
    R, t = fit_rigid(src, dst)
    for _ in range(iterations):
        r = np.linalg.norm(src @ R.T + t - dst, axis=1)
        delta = max(float(np.median(r)) * 0.1, 1e-9)
        R, t = fit_rigid(src, dst, 1.0 / np.maximum(r, delta))
    return R, t


def nearest_usable(matcher: Matcher, moved: np.ndarray,
                   rgb: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Nearest usable (free, non-stray) target of each moved point (P, 3) in position +
    colour: index into matcher.candidates (P,) and joint distance (P,)."""
    if matcher.target_rgb is not None and rgb is not None:
        moved = np.concatenate([moved, matcher.colour_scale * rgb], axis=1)
    d, j = matcher.tree.query(moved, k=1, eps=MATCH_EPS)  # type: ignore[union-attr]
    return j, d


def point_costs(matcher: Matcher, moved: np.ndarray, rgb: np.ndarray | None,
                support: float) -> np.ndarray:
    """Robust cost (P,) rho = d^2 / (d^2 + support^2) of moved points, d from
    `nearest_usable`: ~0 on the target's surface, -> 1 far from it."""
    d2 = nearest_usable(matcher, moved, rgb)[1] ** 2
    return d2 / (d2 + support**2)


@dataclass(frozen=True)
class SourcePoints:
    """The source cloud in normalised units: positions `q` (N, 3), colours `rgb` (N, 3) or
    None, and `observed` (N,) bool, the points with a data term."""

    q: np.ndarray
    rgb: np.ndarray | None
    observed: np.ndarray


@dataclass(frozen=True)
class PrealignSettings:
    """How `rigid_prealign` runs: at most `iterations` ICP steps fitting the closest `keep`
    fraction of the pairs; lengths in normalised units: `spacing`, `target_spacing` the mean
    point spacings of source and target, `gate` the correspondence distance gate, `support`
    the robust cost's scale (0 = no check against the identity); `global_init` 'auto', 'on'
    or 'off'."""

    iterations: int
    keep: float
    spacing: float
    target_spacing: float
    gate: float
    support: float = 0.0
    global_init: str = "off"


def rigid_prealign(
    source: SourcePoints,
    matcher: Matcher,
    target_tree: cKDTree,
    settings: PrealignSettings,
) -> tuple[np.ndarray, np.ndarray]:
    """Linear part A (3, 3) (a rotation, or s R after a global initialisation) and
    translation t (3,) with target ~ source @ A.T + t.

    `target_tree` indexes the target positions. With `settings.support` > 0 the result is
    kept only if it beats the identity significantly on the robust cost mean rho(d),
    rho = d^2 / (d^2 + support^2), d the position + colour distance of each subsampled point
    to its nearest usable target (so it cannot make things worse on that cost).
    `settings.global_init`: 'auto' searches coarse rotations and a scale (globalinit.py)
    when the clouds start far apart (GLOBAL_SPREAD), 'on' always, 'off' never.
    Pairs must pass a mutual check, then the closest `keep` fraction is fitted with Cauchy
    weights. Stops when a step moves the subsample by < 1 % of the point spacing (ours).
    """
    source_q, source_rgb, observed = source.q, source.rgb, source.observed
    iterations, keep, spacing = settings.iterations, settings.keep, settings.spacing
    target_spacing, gate = settings.target_spacing, settings.gate
    support, global_init = settings.support, settings.global_init
    known = np.flatnonzero((matcher.known >= 0) & observed)
    if len(known) >= MIN_KNOWN:
        return _l1_fit(source_q[known], matcher.target_q[matcher.known[known]])
    cand = np.flatnonzero(observed)
    if len(cand) < 3 or matcher.tree is None:
        return np.eye(3), np.zeros(3)
    sub = cand[sample_nodes(source_q[cand], MAX_POINTS)]
    pts = source_q[sub]
    rgb = source_rgb[sub] if source_rgb is not None else None
    sub_matcher = Matcher(target_q=matcher.target_q, candidates=matcher.candidates,
                          tree=matcher.tree, colour_scale=matcher.colour_scale,
                          target_rgb=matcher.target_rgb, known=matcher.known[sub])
    every = np.ones(len(sub), bool)
    normals = _Normals(matcher.target_q, target_tree)
    # mutual gate on the subsample: drops pairs onto the rim of a partial target (ours: 3x)
    sub_spacing = graph_spacing(pts)
    mutual = 3.0 * max(sub_spacing, target_spacing)
    usable = matcher.target_q[matcher.candidates]


    def nearest(moved: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return nearest_usable(matcher, moved, rgb)

    def robust_cost(A: np.ndarray, t: np.ndarray) -> np.ndarray:
        return point_costs(matcher, pts @ A.T + t, rgb, support)

    # Start from identity (clouds from one tracked world frame are close already). Far apart
    # (GLOBAL_SPREAD): search globally. Farther apart than the gate only: start from the
    # shift of the medians if it fits better: on a smooth cap the median shift includes a
    # tangential slide that ICP cannot undo, so it is a last resort (ours).
    A, t = np.eye(3), np.zeros(3)
    start = float(np.median(target_tree.query(pts, k=1)[0]))
    radius = float(np.sqrt(np.mean(np.sum((pts - pts.mean(axis=0)) ** 2, axis=1))))
    far = start > max(gate, GLOBAL_SPREAD * radius)
    if global_init == "on" or (global_init == "auto" and far):
        A, t = global_align(pts, usable, nearest, keep)
    elif start > gate:
        shift = np.median(usable, axis=0) - np.median(pts, axis=0)
        if np.median(target_tree.query(pts + shift, k=1)[0]) < start:
            t = shift
    for _ in range(iterations):
        moved = pts @ A.T + t
        corr = match(sub_matcher, moved, rgb, np.inf, mutual, every)
        ok = corr >= 0
        if ok.sum() < 3:
            break
        src_ok, dst_idx = moved[ok], corr[ok]
        r = np.linalg.norm(src_ok - matcher.target_q[dst_idx], axis=1)
        sel = r <= np.quantile(r, keep)
        if sel.sum() < 6:
            break
        # Cauchy weights on top of the trimming (scale ours: CAUCHY_SCALE x median residual)
        scale = CAUCHY_SCALE * max(float(np.median(r[sel])), 1e-12)
        w = 1.0 / (1.0 + (r[sel] / scale) ** 2)
        dR, dt = _plane_step(src_ok[sel], matcher.target_q[dst_idx[sel]],
                             normals(dst_idx[sel]), w)
        A_new, t_new = dR @ A, dR @ t + dt
        step = np.sqrt(np.mean(np.sum((pts @ A_new.T + t_new - moved) ** 2, axis=1)))
        A, t = A_new, t_new
        if step < 0.01 * spacing:
            break
    if support > 0:
        # paired per-point change of the cost: keep the motion only if it is lower by more
        # than twice its standard error (a drift that fits the noise better is no gain)
        gain = robust_cost(np.eye(3), np.zeros(3)) - robust_cost(A, t)
        if gain.mean() <= 2.0 * gain.std() / np.sqrt(len(gain)):
            return np.eye(3), np.zeros(3)
    return A, t


def rigid_where_better(source: SourcePoints, matcher: Matcher,
                       motion: tuple[np.ndarray, np.ndarray], support: float,
                       owner: np.ndarray, n_nodes: int) -> np.ndarray:
    """(M,) bool: nodes that start from the rigid pre-alignment `motion` (R (3, 3), t (3,));
    the others start from the identity. A node keeps the rigid motion unless the robust
    cost (point_costs, scale `support`) of its observed free points is lower without it: a
    rigid fit to a moving part must not drag a static part along (ours). `owner` (N,): each
    point's nearest node."""
    q, rgb, observed = source.q, source.rgb, source.observed
    R, t = motion
    use = np.ones(n_nodes, bool)
    free = np.flatnonzero(observed & (matcher.known < 0))
    if support <= 0 or matcher.tree is None or len(free) == 0 or (
            np.allclose(R, np.eye(3)) and not t.any()):
        return use
    free = free[:: max(len(free) // (NODE_SAMPLES * n_nodes), 1)]
    pts, col = q[free], rgb[free] if rgb is not None else None
    change = (point_costs(matcher, pts @ R.T + t, col, support)
              - point_costs(matcher, pts, col, support))
    total = np.bincount(owner[free], change, minlength=n_nodes)
    return total <= 0
