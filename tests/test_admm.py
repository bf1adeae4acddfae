"""The ADMM solver of the non-rigid energy (core/registration/admm.py) on tiny problems whose
answers are known from the math: an l2 problem is a linear least-squares problem (solved
directly here), and an l1 problem with a sharp step has a known minimiser (the step kept,
every point on its target) whose energy is counted by hand.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as sla
from scipy.spatial import cKDTree

from surgrecon_cli.core.registration import graph
from surgrecon_cli.core.registration.admm import (
    AdmmProblem,
    AdmmSettings,
    AdmmState,
    energy,
    factorise,
    run_admm,
    shrink_rows,
)

E_Z = np.array([0.0, 0.0, 1.0])


def identity_field(nodes: np.ndarray) -> np.ndarray:
    """X (4M, 3) of the identity map in node-local coordinates: A = I, t = g."""
    X = np.zeros((len(nodes), 4, 3))
    X[:, :3, :] = np.eye(3)
    X[:, 3, :] = nodes
    return X.reshape(-1, 3)


def operators(points: np.ndarray, nodes: np.ndarray, k_graph: int, k_interp: int = 1):
    """D (points blended from their k_interp nearest nodes), B (k_graph-NN graph), L, edges."""
    tree = cKDTree(nodes)
    if k_interp == 1 and len(points) == len(nodes):
        idx, w = np.arange(len(nodes))[:, None], np.ones((len(nodes), 1))
    else:
        idx, w = graph.interpolation(points, nodes, tree, k_interp)
    D = graph.data_operator(points, nodes, idx, w)
    a, b = graph.neighbour_edges(nodes, tree, k_graph)
    B = graph.smoothness_operator(nodes, a, b)
    return D, B, graph.linear_selector(len(nodes)), a, b


def fresh_state(prob: AdmmProblem) -> AdmmState:
    return AdmmState(X=prob.X0.copy(), U1=np.zeros_like(prob.G), U2=np.zeros((prob.B.shape[0], 3)))


def solve(prob: AdmmProblem, mu: float = 2.0, **kwargs):
    factor = factorise(prob.D, prob.B, prob.L, prob.beta, mu, mu)
    state, info, factor = run_admm(prob, fresh_state(prob), factor, AdmmSettings(**kwargs))
    return state.X, info, factor


# ---- l2: ADMM == the direct least-squares solution ----------------------------------------


@pytest.fixture(scope="module")
def l2_problem() -> AdmmProblem:
    """60 points in a 3 x 3 x 3 box blended from 20 nodes (a volume, so that every node's
    neighbour offsets span 3D and the l2 energy alone is strictly convex), a smooth warp plus
    noise as targets, random data and edge weights, and some points without data (w = 0)."""
    rng = np.random.default_rng(3)
    points = rng.uniform(0.0, 3.0, (60, 3))
    nodes = points[:20]
    D, B, L, a, _ = operators(points, nodes, k_graph=6, k_interp=3)
    G = points + 0.3 * np.sin(points[:, [1, 2, 0]]) + rng.normal(0, 0.02, points.shape)
    w = rng.uniform(0.5, 2.0, len(points))
    w[rng.choice(len(points), 10, replace=False)] = 0.0
    return AdmmProblem(D=D.tocsr(), G=G, w=w, B=B, c=rng.uniform(0.5, 1.5, len(a)), L=L,
                       X0=identity_field(nodes), alpha=0.3, beta=0.0, data_l1=False,
                       smooth_l1=False)


def _normal_matrix(prob: AdmmProblem) -> sp.csr_matrix:
    """K = D'WD + alpha B'CB: half the Hessian of the l2 energy."""
    smooth = prob.B.T @ sp.diags(prob.c) @ prob.B
    return prob.D.T @ sp.diags(prob.w) @ prob.D + prob.alpha * smooth


def direct_l2(prob: AdmmProblem, tikhonov: float = 0.0) -> np.ndarray:
    """argmin sum w |DX - G|^2 + alpha sum c |BX|^2 + tikhonov |X - X0|^2, by its normal
    equations (K + tikhonov I) X = D'WG + tikhonov X0."""
    K = (_normal_matrix(prob) + tikhonov * sp.identity(prob.D.shape[1])).tocsc()
    return sla.spsolve(K, prob.D.T @ (prob.w[:, None] * prob.G) + tikhonov * prob.X0)


@pytest.mark.parametrize(("relax", "mu_growth"), [(1.6, 1.0), (1.0, 1.0), (1.6, 1.5)])
def test_l2_solution_is_the_least_squares_solution(l2_problem, relax, mu_growth):
    X, info, factor = solve(l2_problem, mu=1.0, max_iter=3000, tol=1e-12, relax=relax,
                            mu_growth=mu_growth, mu1_max=30.0)
    assert info.converged
    assert (info.factorisations > 0) == (mu_growth > 1.0)
    # The solver minimises E + (eps / 2) |X - X0|^2 (the X-step's Tikhonov pull is eps I in the
    # normal equations of (mu / 2)-scaled terms): equal to its direct solution to round-off.
    exact = direct_l2(l2_problem, tikhonov=factor.eps / 2)
    np.testing.assert_allclose(X, exact, rtol=0, atol=1e-9)
    # ... and, the pull being tiny, close to the minimiser of E itself: the pull tau moves it
    # by (K + tau I)^-1 tau (X0 - X), at most tau / (lambda_min(K) + tau) |X0 - X| per column.
    plain = direct_l2(l2_problem)
    tau = factor.eps / 2
    lam = np.linalg.eigvalsh(_normal_matrix(l2_problem).toarray()).min()
    bound = tau / (lam + tau) * np.linalg.norm(l2_problem.X0 - plain, axis=0)
    assert (np.linalg.norm(X - plain, axis=0) <= bound * (1 + 1e-6) + 1e-12).all()
    assert tau / (lam + tau) < 2e-3  # tiny: lambda_min ~ 0.1 here, tau ~ 1e-6 x mu (mu <= 30)
    e_min = energy(l2_problem, plain)
    assert e_min <= energy(l2_problem, X) <= e_min * (1 + 1e-6)


def test_energy_decreases_to_the_minimum(l2_problem):
    """Warm-started chunks of iterations: the energy falls from the start's and ends at the
    least-squares minimum."""
    factor = factorise(l2_problem.D, l2_problem.B, l2_problem.L, 0.0, 1.0, 1.0)
    state = fresh_state(l2_problem)
    energies = [energy(l2_problem, state.X)]
    for _ in range(6):
        state, _, factor = run_admm(l2_problem, state, factor,
                                   AdmmSettings(max_iter=5, tol=0.0))
        energies.append(energy(l2_problem, state.X))
    e_min = energy(l2_problem, direct_l2(l2_problem))
    assert energies[0] > 10 * e_min  # the identity is far from the targets
    assert energies[-1] < energies[1] < energies[0]
    assert abs(energies[-1] - e_min) < 0.01 * (energies[0] - e_min)


def test_zero_weight_rows_carry_no_data(l2_problem):
    """Rows of D with w = 0 are the same as rows that are not there (register relies on it to
    factorise once whatever the correspondences): moving their targets changes nothing."""
    off = l2_problem.w == 0
    moved = AdmmProblem(**{**l2_problem.__dict__, "G": np.where(off[:, None], 1e3, l2_problem.G)})
    X_a, *_ = solve(l2_problem, mu=1.0, max_iter=3000, tol=1e-12)
    X_b, *_ = solve(moved, mu=1.0, max_iter=3000, tol=1e-12)
    np.testing.assert_allclose(X_a, X_b, rtol=0, atol=1e-9)


def test_one_factor_serves_outer_steps_with_other_data(l2_problem):
    """register's path: one factor (with its stacked operators) reused, warm-started, for a
    second problem with other targets, weights and smoothness: it ends at that problem's
    direct least-squares solution, as a fresh factorisation does; the reported energy is the
    energy of the returned X."""
    rng = np.random.default_rng(5)
    w = l2_problem.w.copy()
    w[rng.choice(np.flatnonzero(w > 0), 8, replace=False)] = 0.0
    second = AdmmProblem(**{**l2_problem.__dict__, "w": w, "alpha": 0.1,
                            "G": l2_problem.G + rng.normal(0, 0.05, l2_problem.G.shape)})
    factor = factorise(l2_problem.D, l2_problem.B, l2_problem.L, 0.0, 1.0, 1.0)
    state, info, factor = run_admm(l2_problem, fresh_state(l2_problem), factor,
                                   AdmmSettings(max_iter=5, tol=0.0))
    assert info.energy == pytest.approx(energy(l2_problem, state.X), rel=1e-12)
    state, info, _ = run_admm(second, state, factor, AdmmSettings(max_iter=3000, tol=1e-12))
    assert info.converged and info.factorisations == 0
    assert info.energy == pytest.approx(energy(second, state.X), rel=1e-12)
    X_fresh, *_ = solve(second, mu=1.0, max_iter=3000, tol=1e-12)
    exact = direct_l2(second, tikhonov=factor.eps / 2)
    np.testing.assert_allclose(state.X, exact, rtol=0, atol=1e-9)
    np.testing.assert_allclose(X_fresh, exact, rtol=0, atol=1e-9)


# ---- l1: a sharp step is kept, l2 smooths it ----------------------------------------------

NX, NY, STEP = 10, 3, 1.0  # a 10 x 3 grid of unit spacing; the half x >= 5 moves 1 unit in z


@pytest.fixture(scope="module")
def step_problem():
    gx, gy = np.meshgrid(np.arange(NX, dtype=float), np.arange(NY, dtype=float), indexing="ij")
    nodes = np.column_stack([gx.ravel(), gy.ravel(), np.zeros(NX * NY)])
    D, B, L, a, b = operators(nodes, nodes, k_graph=4)
    moved = nodes[:, 0] >= NX / 2
    G = nodes + STEP * moved[:, None] * E_Z

    def problem(l1: bool, alpha: float = 0.3) -> AdmmProblem:
        return AdmmProblem(D=D, G=G, w=np.ones(len(nodes)), B=B, c=np.ones(len(a)), L=L,
                           X0=identity_field(nodes), alpha=alpha, beta=0.0, data_l1=l1,
                           smooth_l1=l1)

    return problem, nodes, moved, a, b


def _jump(X: np.ndarray) -> np.ndarray:
    """Per grid row, the z step of the moved positions across the edge x = 4 -> 5."""
    tz = X.reshape(-1, 4, 3)[:, 3, 2].reshape(NX, NY)
    return tz[NX // 2] - tz[NX // 2 - 1]


def test_l1_keeps_a_sharp_step(step_problem):
    problem, nodes, moved, a, b = step_problem
    prob = problem(l1=True)
    X, info, _ = solve(prob, max_iter=3000, tol=1e-6)
    assert info.converged
    # Keeping the step exactly (every point on its target, every transform the identity or
    # the identity shifted by the step) costs alpha * d for each directed edge across it; it
    # is optimal here (moving a point off its target costs w = 1 per unit, more than the
    # 2 alpha it could save), so the minimum energy is that count.
    crossing = moved[a] != moved[b]
    e_step = prob.alpha * STEP * crossing.sum()
    assert crossing.sum() == 2 * NY  # k = 4 on the grid: one edge pair per row crosses
    e = energy(prob, X)
    assert e_step * (1 - 1e-4) <= e <= e_step * (1 + 1e-4)
    assert e < energy(prob, prob.X0) / 5
    np.testing.assert_allclose(_jump(X), STEP, atol=1e-4)
    np.testing.assert_allclose(X.reshape(-1, 4, 3)[:, 3, :], prob.G, atol=1e-4)
    # Group sparsity: neighbouring transforms differ only at the step's two columns.
    residual = np.linalg.norm(prob.B @ X, axis=1)
    at_step = np.isin(nodes[a, 0], [NX // 2 - 1, NX // 2]) | np.isin(nodes[b, 0],
                                                                     [NX // 2 - 1, NX // 2])
    assert residual[~at_step].max() < 1e-4
    np.testing.assert_allclose(residual.sum(), STEP * crossing.sum(), rtol=1e-4)


def test_l2_smooths_the_same_step(step_problem):
    problem, _, moved, a, b = step_problem
    prob = problem(l1=False)
    X, info, factor = solve(prob, max_iter=3000, tol=1e-9)
    assert info.converged
    # (on a flat grid nothing sees the motion's derivative along the normal: the pull of eps
    # decides it, and is part of the direct solution)
    np.testing.assert_allclose(X, direct_l2(prob, tikhonov=factor.eps / 2), atol=1e-8)
    # The quadratic penalty spreads the step: less than 0.8 of it across the step's edge,
    # points beside it pulled off their targets, differences on edges away from the step.
    assert (_jump(X) < 0.8 * STEP).all()
    off_target = np.linalg.norm(X.reshape(-1, 4, 3)[:, 3, :] - prob.G, axis=1)
    assert off_target.max() > 0.1 * STEP
    residual = np.linalg.norm(prob.B @ X, axis=1)
    assert (residual > 1e-3).sum() > 2 * (moved[a] != moved[b]).sum()


def test_too_stiff_l1_gives_up_the_step(step_problem):
    """Above the point where the step's smoothness cost exceeds the data cost of moving
    points, even l1 bends the step (so the step test above depends on alpha, as it must)."""
    problem, *_ = step_problem
    prob = problem(l1=True, alpha=1.0)
    X, *_ = solve(prob, max_iter=3000, tol=1e-6)
    assert energy(prob, X) < prob.alpha * STEP * 2 * NY  # cheaper than keeping the step
    assert (_jump(X) < 0.9 * STEP).all()


# ---- the group soft threshold -------------------------------------------------------------


def test_shrink_rows_is_the_prox_of_the_row_norm():
    v = np.array([[3.0, 4.0, 0.0], [0.3, 0.0, 0.4], [0.0, 0.0, 0.0], [-6.0, 0.0, 8.0]])
    tau = np.array([2.0, 1.0, 1.0, 5.0])
    expected = np.array([[1.8, 2.4, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [-3.0, 0.0, 4.0]])
    np.testing.assert_allclose(shrink_rows(v, tau), expected, atol=1e-15)
    # prox property: the result minimises tau |y| + |y - v|^2 / 2 (check against nearby y)
    rng = np.random.default_rng(0)
    y = shrink_rows(v, tau)
    cost = tau * np.linalg.norm(y, axis=1) + 0.5 * np.sum((y - v) ** 2, axis=1)
    for _ in range(50):
        z = y + rng.normal(0, 0.05, y.shape)
        assert (tau * np.linalg.norm(z, axis=1) + 0.5 * np.sum((z - v) ** 2, axis=1)
                >= cost - 1e-12).all()
