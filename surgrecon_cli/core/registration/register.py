"""`register`: sparse non-rigid registration of a source cloud P to a target cloud G.

Su et al. 2019 (section II.D: per-point affines, heavy-tailed data and smoothness
penalties, ADMM) after Yang et al. 2015 and RPTS:
robust rigid pre-alignment (kept only if it beats the identity), then outer steps that
(1) re-estimate correspondences (known ids, else gated nearest neighbours in position +
colour, the colour weight measured on the target's texture, strays left out), (2) reweight
the l1 data term, (3) run ADMM on the energy of `admm.py` with the smoothness weight annealed
from stiff to flexible. In the last step an observed point with no target surface within
the support gate (tied to the target's spacing and noise) loses its match: it is reported
unsupported and only weakly pulled towards not moving (UNSUPPORTED_PULL).
Inputs in metres; config thresholds in millimetres. Pure numpy/scipy, no I/O.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from ...config import RegistrationConfig
from ...errors import GeometryError
from . import graph
from .admm import AdmmProblem, AdmmSettings, AdmmState, factorise, run_admm
from .correspondences import KnownPairs, build_matcher, match
from .residuals import along_surface, surface_distance
from .rigid import PrealignSettings, SourcePoints, rigid_prealign, rigid_where_better
from .surface import analyse_target, colour_weight

Callback = Callable[[int, dict[str, Any]], None]
MU_GROWTH_LIMIT = 64.0  # ours: with mu_growth > 1, mu stops growing at 64 x its start
SUPPORT_SPACINGS = 3.0  # ours: support gate in target spacings (see `register`)
# ours: data weight pulling an observed point with no target surface near it (past the edge
# of a partial target) towards its source position: its neighbours decide near the edge, and
# far from it the extrapolated motion fades to none instead of growing with distance
UNSUPPORTED_PULL = 0.1


@dataclass(frozen=True)
class RegistrationResult:
    """What `register` returns (metres).

    transforms (N, 3, 4): per-point affine T_i, registered_i = T_i @ [p_i, 1].
    registered (N, 3); residuals (N,): for a known pair (target_ids, landmarks) the distance
    to its target point, else the distance to the target's local surface near the
    registered point (residuals.surface_distance); NaN for points without a data weight or
    without target surface near them (not `supported`);
    correspondences (N,): target index or -1 (unobserved, or no match passed the gates);
    outliers (N,) bool: supported, but farther than `outlier_mm` from the target's surface;
    supported (N,) bool: has a weight and the target's surface within the support gate of
    it in the last step; observed points that are not supported got no data term there and
    followed their neighbours (no target surface there, e.g. cut away);
    along_surface (N,): estimate of the error along the surface where colour decided the
    matches (residuals.along_surface), NaN elsewhere;
    stats: one dict per step: step 0 the rigid pre-alignment (rotation, translation_m, nodes,
    seconds), then one per outer step (alpha, ADMM iterations, residuals in mm, seconds);
    the last carries total_seconds.
    """

    transforms: np.ndarray
    registered: np.ndarray
    residuals: np.ndarray
    correspondences: np.ndarray
    outliers: np.ndarray
    stats: list[dict[str, Any]]
    supported: np.ndarray
    along_surface: np.ndarray | None = None


def _points(name: str, a: Any, n: int | None = None) -> np.ndarray:
    arr = np.asarray(a, dtype=float)
    if arr.ndim != 2 or arr.shape[1] != 3 or (n is not None and len(arr) != n):
        want = f"({n}, 3)" if n is not None else "(N, 3)"
        raise GeometryError(f"{name}: expected shape {want}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise GeometryError(f"{name}: contains {int((~np.isfinite(arr)).any(1).sum())} "
                            "non-finite rows")
    return arr


def _colours(name: str, a: Any, n: int) -> np.ndarray | None:
    if a is None:
        return None
    raw = np.asarray(a)
    arr = _points(name, raw, n)
    # uint8 (or any integer) colours are 0..255; floats are taken as 0..1
    return arr / 255.0 if np.issubdtype(raw.dtype, np.integer) else arr


def _validate_extras(n: int, m: int, target_ids: Any, weights: Any, landmarks: Any):
    ids = w = lm = None
    if target_ids is not None:
        ids = np.asarray(target_ids)
        if ids.shape != (m,) or not np.issubdtype(ids.dtype, np.integer):
            raise GeometryError(
                f"target_ids: expected ({m},) integers, got {ids.shape} {ids.dtype}")
        if ids.size and ids.max() >= n:
            raise GeometryError(f"target_ids: id {int(ids.max())} >= number of source points {n}")
        ids = ids.astype(np.int64)
    if weights is not None:
        w = np.asarray(weights, dtype=float)
        if w.shape != (n,) or not np.all(np.isfinite(w)) or np.any(w < 0):
            raise GeometryError(f"weights: expected ({n},) finite values >= 0")
    if landmarks is not None:
        lm = np.asarray(landmarks)
        if lm.size == 0:
            lm = None
        elif lm.ndim != 2 or lm.shape[1] != 2 or not np.issubdtype(lm.dtype, np.integer):
            raise GeometryError(f"landmarks: expected (L, 2) integers, got {lm.shape} {lm.dtype}")
        elif lm.min() < 0 or lm[:, 0].max() >= n or lm[:, 1].max() >= m:
            raise GeometryError("landmarks: index out of range")
        else:
            lm = lm.astype(np.int64)
    return ids, w, lm


def _global_node_transforms(X: np.ndarray, nodes_q: np.ndarray, norm: graph.Normalisation):
    """Node blocks (normalised, node-local, row-vector) -> (M, 3, 4) transforms in metres."""
    blocks = X.reshape(-1, 4, 3)
    A, t = blocks[:, :3, :], blocks[:, 3, :]  # y = u A + t, u = q - g
    lin = np.swapaxes(A, 1, 2)  # column form
    c = norm.centre
    trans = c - c @ A - norm.unit * np.einsum("mi,mij->mj", nodes_q, A) + norm.unit * t
    return np.concatenate([lin, trans[:, :, None]], axis=2)


def register(
    source_xyz: np.ndarray,
    target_xyz: np.ndarray,
    source_rgb: np.ndarray | None = None,
    target_rgb: np.ndarray | None = None,
    config: RegistrationConfig | None = None,
    *,
    target_ids: np.ndarray | None = None,
    weights: np.ndarray | None = None,
    landmarks: np.ndarray | None = None,
    callback: Callback | None = None,
) -> RegistrationResult:
    """Register source (N, 3) to target (M, 3), metres; see the module docstring.

    source_rgb / target_rgb: (N, 3) / (M, 3), uint8 0..255 or float 0..1 (colour is used for
    matching only when both are given). target_ids (M,) int: source index a target point is
    known to be (-1 = unknown). weights (N,) >= 0: data weight per source point (0 = not
    observed; the point follows its neighbours). landmarks (L, 2) int: (source, target)
    pairs always matched with full weight. callback(step, state) after the rigid step (0)
    and every outer step (1..outer_iterations).
    """
    cfg = config or RegistrationConfig()
    t_start = time.perf_counter()
    src = _points("source_xyz", source_xyz)
    tgt = _points("target_xyz", target_xyz)
    n, m = len(src), len(tgt)
    if n < 4 or m < 3:
        raise GeometryError(f"need >= 4 source and >= 3 target points, got {n} and {m}")
    src_rgb = _colours("source_rgb", source_rgb, n)
    tgt_rgb = _colours("target_rgb", target_rgb, m)
    ids, user_w, lm = _validate_extras(n, m, target_ids, weights, landmarks)

    # --- normalisation, nodes, operators ---
    src_tree = cKDTree(src)
    ref_nodes = cfg.max_nodes if cfg.max_nodes > 0 else n
    norm = graph.normalisation(src, src_tree, ref_nodes)
    q, tq = norm.to_internal(src), norm.to_internal(tgt)
    per_point = cfg.max_nodes == 0 or n <= cfg.max_nodes
    node_idx = np.arange(n) if per_point else graph.sample_nodes(q, cfg.max_nodes)
    nodes_q = q[node_idx]
    node_tree = cKDTree(nodes_q)
    n_nodes = len(nodes_q)
    if per_point:
        interp_idx, interp_w = np.arange(n)[:, None], np.ones((n, 1))
    else:
        interp_idx, interp_w = graph.interpolation(q, nodes_q, node_tree, cfg.interp_neighbors)
    D_full = graph.data_operator(q, nodes_q, interp_idx, interp_w)
    ea, eb = graph.neighbour_edges(nodes_q, node_tree, cfg.k_neighbors)
    B = graph.smoothness_operator(nodes_q, ea, eb)
    L = graph.linear_selector(n_nodes)
    # Edge weights (ours): gradient-like, so the smoothness means the same at any node
    # density: c_e = (N / M) (1 / d_e)^p, p = 1 for l1, 2 for l2 (reference spacing = 1).
    d_e = np.maximum(np.linalg.norm(nodes_q[ea] - nodes_q[eb], axis=1), 1e-9)
    smooth_l1 = cfg.smooth_penalty == "l1"
    c_e = (n / n_nodes) * (1.0 / d_e) ** (1 if smooth_l1 else 2)

    # --- data weights, correspondences ---
    base_w = np.ones(n) if user_w is None else user_w.copy()
    if lm is not None:
        base_w[lm[:, 0]] = 1.0
    is_landmark = np.zeros(n, bool)
    if lm is not None:
        is_landmark[lm[:, 0]] = True
    observed = base_w > 0
    if src_rgb is None or tgt_rgb is None:  # colour is used only when both clouds have it
        src_rgb = tgt_rgb = None
    tgt_tree = cKDTree(tq)
    surf = analyse_target(tq, tgt_tree)
    tgt_spacing = surf.spacing
    gate = norm.mm(cfg.max_correspondence_mm)
    # support: how far a registered point may be from the target's surface and still be
    # supported by it (ours: SUPPORT_SPACINGS x the target spacing, or 2 sigma of its noise)
    support = SUPPORT_SPACINGS * max(tgt_spacing, 2.0 * surf.noise)
    colour_scale = 0.0
    if tgt_rgb is not None:
        colour_scale = (norm.mm(cfg.color_weight_mm) if cfg.color_weight_mm > 0 else
                        colour_weight(tq, tgt_rgb, tgt_tree, ~surf.stray, gate))
    matcher = build_matcher(tq, n, tgt_rgb, colour_scale, KnownPairs(ids, lm),
                            usable=~surf.stray)
    usable_idx = np.flatnonzero(~surf.stray)
    usable_tree = cKDTree(tq[usable_idx])
    mutual = cfg.mutual_spacings * max(norm.spacing, tgt_spacing)

    # --- rigid pre-alignment, X initialised to it ---
    t_rigid = time.perf_counter()
    source = SourcePoints(q, src_rgb, observed)
    if cfg.rigid_iterations > 0:
        R, t = rigid_prealign(source, matcher, tgt_tree, PrealignSettings(
            iterations=cfg.rigid_iterations, keep=cfg.rigid_trim, spacing=norm.spacing,
            target_spacing=tgt_spacing, gate=gate, support=support,
            global_init=cfg.global_init))
    else:
        R, t = np.eye(3), np.zeros(3)
    rigid_nodes = rigid_where_better(source, matcher, (R, t), support, interp_idx[:, 0],
                                     n_nodes)
    X: np.ndarray = np.zeros((n_nodes, 4, 3))
    X[:, :3, :] = np.where(rigid_nodes[:, None, None], R.T, np.eye(3))
    X[:, 3, :] = np.where(rigid_nodes[:, None], nodes_q @ R.T + t, nodes_q)
    X = X.reshape(-1, 3)
    X0 = X.copy()
    stats: list[dict[str, Any]] = [{
        "step": 0, "stage": "rigid", "rotation": R / np.cbrt(np.linalg.det(R)),
        "scale": float(np.cbrt(np.linalg.det(R))), "translation_m": t * norm.unit,
        "colour_weight_mm": colour_scale * norm.unit * 1e3, "target_strays": int(surf.stray.sum()),
        "nodes": n_nodes, "seconds": time.perf_counter() - t_rigid,
        "setup_seconds": t_rigid - t_start,
    }]
    if callback is not None:
        callback(0, {"total": cfg.outer_iterations, **stats[0]})

    # --- outer loop: correspondences, reweighting, ADMM with annealed alpha ---
    data_l1 = cfg.data_penalty == "l1"
    tol = norm.mm(cfg.tolerance_mm)
    reweight = norm.mm(cfg.reweight_mm) if data_l1 else 0.0
    if not observed.any():
        raise GeometryError("no source point has a data term (all weights are 0)")
    # Rows of D: every observed point, fixed for the whole run so that the X-step matrix is
    # factorised once; a row whose match is gated out gets w = 0 in that outer step.
    rows = np.flatnonzero(observed)
    D_obs = D_full[rows]
    mu1, mu2 = cfg.mu, cfg.mu * n / n_nodes
    factor = factorise(D_obs, B, L, cfg.beta, mu1, mu2)
    U1 = np.zeros((len(rows), 3))
    U2 = np.zeros((len(ea), 3))
    corr = np.full(n, -1, np.int64)
    off_surface = np.zeros(n, bool)
    alpha_prev = None
    moved = D_full @ X
    for step in range(cfg.outer_iterations):
        t_step = time.perf_counter()
        frac = step / max(cfg.outer_iterations - 1, 1)
        alpha = cfg.alpha_start * (cfg.alpha / cfg.alpha_start) ** frac
        # the last step keeps only matches on the target's surface near the point: the others
        # (beyond the edge of a partial target) lose theirs and follow their neighbours
        last = step == cfg.outer_iterations - 1
        corr = match(matcher, moved, src_rgb, gate, mutual, observed)
        if last:  # the gate also allows for what the registration has not converged on
            near = usable_tree.query(moved, k=1)[0]
            reach = max(support, SUPPORT_SPACINGS * float(np.median(near[observed])))
            off_surface = (near > reach) & (matcher.known < 0)
            corr[off_surface] = -1
        matched = corr[rows] >= 0
        G = np.where(matched[:, None], tq[np.maximum(corr[rows], 0)], moved[rows])
        w = np.where(matched, base_w[rows], 0.0)
        if last:  # no target surface near: a weak pull towards not moving (see the top)
            rest = off_surface[rows]
            G[rest] = q[rows[rest]]
            w[rest] = UNSUPPORTED_PULL * base_w[rows[rest]]
        if reweight > 0 and step > 0:
            r = np.linalg.norm(moved[rows] - G, axis=1)
            w = np.where(is_landmark[rows], w, w * reweight / (r + reweight))
        U1[~matched] = 0.0
        if alpha_prev is not None:
            U2 = U2 * (alpha / alpha_prev)
        alpha_prev = alpha
        prob = AdmmProblem(D=D_obs, G=G, w=w, B=B, c=c_e, L=L, X0=X0, alpha=alpha,
                           beta=cfg.beta, data_l1=data_l1, smooth_l1=smooth_l1)
        state, info, factor = run_admm(
            prob, AdmmState(X=X, U1=U1, U2=U2), factor,
            AdmmSettings(max_iter=cfg.final_admm_iterations if last else cfg.admm_iterations,
                         tol=tol, relax=cfg.relaxation, mu_growth=cfg.mu_growth,
                         mu1_max=cfg.mu * MU_GROWTH_LIMIT))
        X, U1, U2 = state.X, state.U1, state.U2
        moved = D_full @ X
        res = np.linalg.norm(moved[rows[matched]] - G[matched], axis=1) * norm.unit * 1e3
        record = {
            "step": step + 1, "stage": "nonrigid", "alpha": alpha,
            "admm_iterations": info.iterations,
            "factorisations": info.factorisations, "converged": info.converged,
            "primal_mm": info.primal * norm.unit * 1e3, "dual_mm": info.dual * norm.unit * 1e3,
            "step_mm": info.step * norm.unit * 1e3, "energy_change": info.energy_change,
            "correspondences": int(matched.sum()),
            "median_residual_mm": float(np.median(res)) if len(res) else float("nan"),
            "energy": info.energy, "seconds": time.perf_counter() - t_step,
        }
        stats.append(record)
        if callback is not None:
            callback(step + 1, {"total": cfg.outer_iterations, **record})

    # --- outputs in metres ---
    node_T = _global_node_transforms(X, nodes_q, norm)
    transforms = np.einsum("pk,pkij->pij", interp_w, node_T[interp_idx])
    registered = norm.to_metres(moved)
    has = (corr >= 0) & observed
    corr = np.where(has, corr, -1)
    supported = observed & ~off_surface
    residuals = np.full(n, np.nan)
    residuals[supported] = norm.unit * surface_distance(moved[supported], surf, usable_idx,
                                                        usable_tree)
    pinned = has & (matcher.known >= 0)  # a known pair: the distance to that target point
    residuals[pinned] = np.linalg.norm(registered[pinned] - tgt[corr[pinned]], axis=1)
    outliers = supported & (residuals > cfg.outlier_mm * 1e-3)
    along = np.full(n, np.nan)
    if colour_scale > 0 and src_rgb is not None:
        along = norm.unit * along_surface(moved, corr, surf, tq, interp_idx, interp_w)
    stats[-1]["total_seconds"] = time.perf_counter() - t_start
    return RegistrationResult(transforms=transforms, registered=registered, residuals=residuals,
                              correspondences=corr, outliers=outliers, stats=stats,
                              supported=supported, along_surface=along)


def apply_transforms(
    result: RegistrationResult, source_xyz: np.ndarray, query_xyz: np.ndarray, k: int = 4
) -> np.ndarray:
    """Move other points (Q, 3) with the registration: each takes the inverse-distance blend
    of the transforms of its k nearest source points (N, 3), metres."""
    src = _points("source_xyz", source_xyz, len(result.transforms))
    qry = _points("query_xyz", query_xyz)
    if k < 1:
        raise GeometryError(f"k must be >= 1, got {k}")
    k = min(k, len(src))
    d, idx = cKDTree(src).query(qry, k=k)
    d, idx = d.reshape(len(qry), k), idx.reshape(len(qry), k)
    w = 1.0 / np.maximum(d, 1e-12)
    exact = d[:, 0] <= 1e-12
    w[exact] = 0.0
    w[exact, 0] = 1.0
    w /= w.sum(axis=1, keepdims=True)
    T = np.einsum("qk,qkij->qij", w, result.transforms[idx])
    return np.einsum("qij,qj->qi", T[:, :, :3], qry) + T[:, :, 3]
