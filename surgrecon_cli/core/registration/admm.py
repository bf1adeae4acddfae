"""ADMM for the sparse non-rigid energy (Yang et al. 2015; Boyd et al. 2011).

    E(X) = sum_i w_i rho_d(D_i X - G_i) + alpha sum_e c_e rho_s(B_e X) + beta sum_n |A_n - R_n|_F^2

rho = |.|_2 of the 3-vector residual (unsquared: the heavy-tailed, group-sparse l1-type
penalty of Yang et al. 2015 / RPTS, as in Su et al. 2019 section II.D) or |.|_2^2 (Gaussian, for
comparison). Splits C = DX - G and Z = BX with scaled multipliers U1, U2:

    X <- (mu1 D'D + mu2 B'B + 2 beta L'L + eps I)^-1 [mu1 D'(G + C - U1) + mu2 B'(Z - U2)
                                                     + 2 beta L'R + eps X0]
    C <- prox_{w rho_d / mu1}(DX - G + U1)        (group soft threshold for l1)
    Z <- prox_{alpha c rho_s / mu2}(BX + U2)
    U1 += DX - G - C;   U2 += BX - Z

The matrix depends only on the graph, the observed rows of D and mu: it is factorised once
per run (sparse LU in symmetric mode with a minimum-degree ordering) and reused for all
iterations, all outer steps and all three coordinate columns; the stacked operator [D; B]
and its penalty-scaled transpose are built with it (`factorise`). `eps` (ours) is a tiny
Tikhonov pull of every unknown, linear parts and translations, towards the rigid
pre-alignment X0: it only decides the directions no term sees (the derivative of the motion
along the surface normal, and a part of the graph that no data reaches, which therefore
stays where the rigid step put it instead of drifting by an arbitrary translation) and keeps
the system definite; a system that is still singular raises. Over-relaxation (Boyd et al.
2011, sec. 3.4.3) speeds convergence; the factor is ours.

Stopping (Boyd et al. 2011, sec. 3.3.1, with our tolerances): the primal residual RMS is
below `tol`, no node moved by more than `tol` in the last iteration (a max, not an RMS, so
that a slow corner of the graph cannot hide behind the rest), and the energy changed by less
than `ENERGY_RTOL` of itself.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as sla

from ...errors import GeometryError
from ..geometry.poses import nearest_rotation

EPS_REL = 1e-6  # ours: Tikhonov weight relative to the mean diagonal of the system
# ours: relative energy change of one iteration counted as converged (1e-4 costs ~17 % more
# registration time for the same error on a tuning log)
ENERGY_RTOL = 1e-3
PIVOT_RTOL = 1e-13  # ours: an LU pivot this small relative to the largest means singular


@dataclass
class AdmmState:
    """Warm-startable iterate: X (4M, 3), scaled duals U1 (P, 3) and U2 (E, 3)."""

    X: np.ndarray
    U1: np.ndarray
    U2: np.ndarray


@dataclass(frozen=True)
class AdmmProblem:
    """One ADMM run's fixed data (normalised units).

    D (P, 4M) observed rows, G (P, 3) targets, w (P,) data weights, B (E, 4M), c (E,) edge
    weights, L (3M, 4M) linear-part selector, X0 (4M, 3) prior (the rigid pre-alignment).
    """

    D: sp.csr_matrix
    G: np.ndarray
    w: np.ndarray
    B: sp.csr_matrix
    c: np.ndarray
    L: sp.csr_matrix
    X0: np.ndarray
    alpha: float
    beta: float
    data_l1: bool
    smooth_l1: bool


@dataclass(frozen=True)
class AdmmInfo:
    iterations: int
    primal: float  # RMS constraint violation, normalised units
    dual: float  # RMS change of the split variables in the last iteration, normalised units
    step: float  # largest node displacement in the last iteration, normalised units
    energy_change: float  # relative energy change in the last iteration
    factorisations: int
    converged: bool
    energy: float  # E(X) of the returned X (`energy`), normalised units


def row_norms2(v: np.ndarray) -> np.ndarray:
    """Squared norms (K,) of the rows of v (K, 3), by columns (a third of einsum's cost on
    the few-thousand-row arrays of an iteration)."""
    x, y, z = v[:, 0], v[:, 1], v[:, 2]
    return x * x + y * y + z * z


def shrink_rows(v: np.ndarray, tau: np.ndarray) -> np.ndarray:
    """Group soft threshold: v_i * max(0, 1 - tau_i / |v_i|) (prox of tau |.|_2), v (K, 3)."""
    norm = np.sqrt(row_norms2(v))
    scale = np.maximum(0.0, 1.0 - tau / np.maximum(norm, 1e-300))
    return v * scale[:, None]


def _prox(v: np.ndarray, weight: np.ndarray, mu: np.ndarray, l1: np.ndarray) -> np.ndarray:
    """Row-wise prox of weight_i rho(.) / mu_i: the group soft threshold where l1_i, else
    the l2 shrink; v (K, 3), weight, mu (K,), l1 (K,) bool."""
    if l1.all():
        return shrink_rows(v, weight / mu)
    quadratic = v * (mu / (2.0 * weight + mu))[:, None]
    if not l1.any():
        return quadratic
    return np.where(l1[:, None], shrink_rows(v, weight / mu), quadratic)


@dataclass(frozen=True)
class Factor:
    """The factorised X-step matrix for given penalties (mu1, mu2); `eps` its Tikhonov weight.
    With it, what every iteration multiplies by: stacked = [D; B] (P + E, 4M), back =
    [mu1 Dᵀ, mu2 Bᵀ] (4M, P + E) and the penalty of each stacked row, mu (P + E,)."""

    solve: Callable[[np.ndarray], np.ndarray]
    eps: float
    mu1: float
    mu2: float
    stacked: sp.csr_matrix
    back: sp.csr_matrix
    mu: np.ndarray


def factorise(D: sp.csr_matrix, B: sp.csr_matrix, L: sp.csr_matrix, beta: float, mu1: float,
              mu2: float) -> Factor:
    """Sparse LU (symmetric mode, minimum-degree ordering) of the X-step matrix; raises
    GeometryError when it is singular (a pivot vanishes or the factor is not finite)."""
    stacked = sp.vstack([D, B], format="csr")
    back, mu = _scaled(stacked, D.shape[0], mu1, mu2)
    K = back @ stacked  # mu1 DᵀD + mu2 BᵀB in one product
    if beta != 0.0:
        K = K + (2.0 * beta) * (L.T @ L)
    eps = EPS_REL * float(K.diagonal().mean())
    K = (K + eps * sp.identity(K.shape[0], format="csr")).tocsc()
    try:
        lu = sla.splu(K, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                      options={"SymmetricMode": True})
    except RuntimeError as exc:  # exactly singular
        raise GeometryError(f"registration system is singular ({exc})") from exc
    pivots = np.abs(lu.U.diagonal())
    if not np.isfinite(pivots).all() or pivots.min() <= PIVOT_RTOL * pivots.max():
        raise GeometryError(
            f"registration system is singular (smallest LU pivot {pivots.min():.3g}, "
            f"largest {pivots.max():.3g})")
    return Factor(solve=lu.solve, eps=eps, mu1=mu1, mu2=mu2, stacked=stacked, back=back, mu=mu)


def _sq(v: np.ndarray) -> float:
    """Sum of squares of all entries."""
    flat = v.ravel()
    return float(flat @ flat)


def _scaled(stacked: sp.csr_matrix, n_data: int, mu1: float,
            mu2: float) -> tuple[sp.csr_matrix, np.ndarray]:
    """[mu1 Dᵀ, mu2 Bᵀ] from stacked = [D; B] (D its first n_data rows), and the penalty of
    each row (mu1 for D's, mu2 for B's)."""
    mu = np.where(np.arange(stacked.shape[0]) < n_data, mu1, mu2)
    scaled = stacked.copy()
    scaled.data *= np.repeat(mu, np.diff(stacked.indptr))
    return scaled.T.tocsr(), mu


def energy(prob: AdmmProblem, X: np.ndarray) -> float:
    """E(X) above (without the beta term), normalised units."""
    return _energy(prob, prob.D @ X, prob.B @ X)


def _energy(prob: AdmmProblem, DX: np.ndarray, BX: np.ndarray) -> float:
    d = np.concatenate([DX - prob.G, BX])
    return _energy_rows(prob, np.sqrt(row_norms2(d)))


def _energy_rows(prob: AdmmProblem, norms: np.ndarray) -> float:
    """E(X) from the row norms (P + E,) of [DX - G; BX]."""
    r, s = norms[:len(prob.G)], norms[len(prob.G):]
    data = prob.w @ (r if prob.data_l1 else r * r)
    smooth = prob.alpha * (prob.c @ (s if prob.smooth_l1 else s * s))
    return float(data + smooth)


@dataclass(frozen=True)
class AdmmSettings:
    """How `run_admm` iterates: at most `max_iter` iterations, stopping tolerance `tol`
    (normalised units), over-relaxation factor `relax`; `mu_growth` > 1 multiplies both
    penalties every iteration while mu1 < `mu1_max`."""

    max_iter: int
    tol: float
    relax: float = 1.6
    mu_growth: float = 1.0
    mu1_max: float = np.inf


def run_admm(
    prob: AdmmProblem,
    state: AdmmState,
    factor: Factor,
    settings: AdmmSettings,
) -> tuple[AdmmState, AdmmInfo, Factor]:
    """Iterate until primal and dual RMS residuals are both below `settings.tol`.

    `factor` must be `factorise(prob.D, prob.B, prob.L, prob.beta, mu1, mu2)`; rows of D with
    w = 0 carry no data term (their split absorbs the residual), so one factor (with its
    stacked operators) serves every outer step whatever the correspondences. With
    `settings.mu_growth` > 1 the duals are rescaled and the matrix refactorised each time the
    penalties grow.
    Returns the new state, the info and the factor in use at the end.
    """
    max_iter, tol, relax = settings.max_iter, settings.tol, settings.relax
    mu_growth, mu1_max = settings.mu_growth, settings.mu1_max
    D, B, G, L = prob.D, prob.B, prob.G, prob.L
    n_data = len(G)
    # Both splits as one: rows [D; B] X - [G; 0] = [C; Z], multipliers [U1; U2], so that an
    # iteration is one sparse product each way (factor.stacked, factor.back) and one prox
    # over all rows.
    offset = np.concatenate([G, np.zeros((B.shape[0], 3))])
    weight = np.concatenate([prob.w, prob.alpha * prob.c])
    l1 = np.repeat([prob.data_l1, prob.smooth_l1], [n_data, B.shape[0]])
    solve, eps, mu1, mu2 = factor.solve, factor.eps, factor.mu1, factor.mu2
    stacked, back, mu = factor.stacked, factor.back, factor.mu
    n_fact = 0
    X, U = state.X, np.concatenate([state.U1, state.U2])
    SX = stacked @ X
    W = SX - offset
    rows = max(len(W), 1)
    prior = prob.X0
    primal = dual = step = change = np.inf
    e_prev = _energy(prob, SX[:n_data], SX[n_data:])
    pull = eps * prior  # constant between factorisations, as is the prox's threshold
    tau = weight / mu if l1.all() else None
    it = 0
    for it in range(1, max_iter + 1):  # noqa: B007 - `it` is reported after the loop
        rhs = back @ (offset + W - U) + pull
        if prob.beta > 0:
            A = X.reshape(-1, 4, 3)[:, :3, :]
            R = nearest_rotation(A).reshape(-1, 3)
            rhs += 2.0 * prob.beta * (L.T @ R)
        X_old = X
        X = solve(rhs)
        d = stacked @ X - offset  # [DX - G; BX]
        V = relax * d + (1.0 - relax) * W + U  # the over-relaxed split plus its multiplier
        W_old = W
        W = shrink_rows(V, tau) if tau is not None else _prox(V, weight, mu, l1)
        U = V - W
        primal = np.sqrt(_sq(d - W) / rows)
        dual = np.sqrt(_sq(W - W_old) / rows)
        moved = (X - X_old).reshape(-1, 4, 3)[:, 3, :]
        step = float(np.sqrt(np.max(row_norms2(moved))))
        e_now = _energy_rows(prob, np.sqrt(row_norms2(d)))
        change = abs(e_now - e_prev) / max(abs(e_now), 1e-300)
        e_prev = e_now
        if primal < tol and step < tol and change < ENERGY_RTOL:
            break
        if mu_growth > 1.0 and mu1 < mu1_max:
            U = U / mu_growth
            mu1, mu2 = mu1 * mu_growth, mu2 * mu_growth
            factor = factorise(D, B, L, prob.beta, mu1, mu2)
            solve, eps, back, mu = factor.solve, factor.eps, factor.back, factor.mu
            pull = eps * prior
            tau = weight / mu if l1.all() else None
            n_fact += 1
    if not np.isfinite(X).all():
        raise GeometryError("registration system gave a non-finite solution")
    U1, U2 = U[:n_data], U[n_data:]
    converged = bool(primal < tol and step < tol and change < ENERGY_RTOL)
    info = AdmmInfo(iterations=it, primal=float(primal), dual=float(dual), step=step,
                    energy_change=float(change), factorisations=n_fact, converged=converged,
                    energy=float(e_prev))
    return AdmmState(X=X, U1=U1, U2=U2), info, factor
