"""core.geometry.poses: quaternion order and sign conventions, slerp, batched shapes."""

from __future__ import annotations

import numpy as np

from surgrecon_cli.core.geometry.poses import make_pose, matrix_to_quat, quat_to_matrix, slerp
from surgrecon_cli.core.geometry.triangulate import (
    smallest_eigenvector,
    spd_solve,
    symmetric3_inverse,
)

HALF = np.sqrt(0.5)


def test_quaternions_are_x_y_z_w_with_w_non_negative():
    quarter_z = np.array([0.0, 0.0, HALF, HALF])  # +90 degrees about z
    np.testing.assert_allclose(quat_to_matrix(quarter_z) @ [1, 0, 0], [0, 1, 0], atol=1e-15)
    np.testing.assert_allclose(matrix_to_quat(quat_to_matrix(-quarter_z)), quarter_z, atol=1e-15)
    rng = np.random.default_rng(0)
    q = rng.normal(size=(2, 5, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    back = matrix_to_quat(quat_to_matrix(q))
    assert back.shape == (2, 5, 4) and (back[..., 3] >= 0).all()
    np.testing.assert_allclose(back, q * np.sign(q[..., 3:]), atol=1e-12)
    assert make_pose(np.zeros((2, 5, 3)), q).shape == (2, 5, 4, 4)


def test_invalid_quaternion_gives_nan_matrix():
    R = quat_to_matrix(np.array([[0.0, 0, 0, 0], [np.nan, 0, 0, 1], [0, 0, 0, 2]]))
    assert np.isnan(R[:2]).all()
    np.testing.assert_allclose(R[2], np.eye(3))  # normalised


def test_slerp_takes_the_shorter_arc_from_q0():
    q0 = np.tile([0.0, 0, 0, 1], (3, 1))
    q1 = -np.array([[0.0, 0, HALF, HALF]] * 3)  # the same rotation, other sign
    q = slerp(q0, q1, np.array([0.0, 0.5, 1.0]))
    np.testing.assert_allclose(q[0], q0[0], atol=1e-15)
    np.testing.assert_allclose(q[1], [0, 0, np.sin(np.pi / 8), np.cos(np.pi / 8)], atol=1e-15)
    np.testing.assert_allclose(q[2], -q1[2], atol=1e-15)  # in q0's hemisphere


def test_symmetric3_inverse_is_lapack_s_inverse():
    """symmetric3_inverse (cofactors over the determinant) equals np.linalg.inv on
    symmetric positive definite 3x3 matrices of very different scales per axis (the
    information of a triangulated point), to rounding; not finite where singular."""
    rng = np.random.default_rng(5)
    rows = rng.normal(size=(500, 4, 3)) * np.array([1.0, 30.0, 1e3])
    info = np.matmul(rows.transpose(0, 2, 1), rows)
    expected = np.linalg.inv(info)
    scale = np.abs(expected).max((1, 2), keepdims=True)
    assert (np.abs(symmetric3_inverse(info) - expected) <= 1e-9 * scale).all()
    assert not np.isfinite(symmetric3_inverse(np.zeros((1, 3, 3)))).any()


def test_batched_cholesky_solves_as_lapack():
    """spd_solve: the solutions of a batch of positive definite systems (well and poorly
    conditioned) equal np.linalg.solve's to rounding; NaN for a system that is not
    positive definite."""
    rng = np.random.default_rng(3)
    design = rng.normal(size=(200, 36, 6)) * np.logspace(0, -4, 6)
    normal = np.matmul(design.transpose(0, 2, 1), design)
    rhs = rng.normal(size=(200, 6, 3))
    expected = np.linalg.solve(normal, rhs)
    assert np.allclose(spd_solve(normal, rhs), expected, rtol=1e-6,
                       atol=1e-9 * np.abs(expected).max())
    indefinite = np.array([[[1.0, 2.0], [2.0, 1.0]]])
    assert np.isnan(spd_solve(indefinite, np.ones((1, 2, 1)))).all()
    assert spd_solve(np.zeros((0, 6, 6)), np.zeros((0, 6, 3))).shape == (0, 6, 3)


def test_smallest_eigenvector_is_the_dlt_null_vector_of_eigh():
    """smallest_eigenvector (inverse iteration) gives the DLT's point as LAPACK's eigh does,
    to rounding, for noisy constraints of points in front of the cameras; NaN for a zero
    system."""
    rng = np.random.default_rng(2)
    points = np.concatenate([rng.normal(size=(300, 3)) * 0.02 + [0.0, 0.0, 0.08],
                             np.ones((300, 1))], axis=1)
    rows = rng.normal(size=(300, 6, 4))
    along = np.einsum("nkj,nj->nk", rows, points) / (points * points).sum(1)[:, None]
    rows = rows - along[:, :, None] * points[:, None, :] + 1e-5 * rng.normal(size=rows.shape)
    system = np.matmul(rows.transpose(0, 2, 1), rows)
    expected = np.linalg.eigh(system)[1][:, :, 0]
    found = smallest_eigenvector(system)
    assert np.allclose(found[:, :3] / found[:, 3:], expected[:, :3] / expected[:, 3:],
                       rtol=0, atol=1e-12)
    assert np.isnan(smallest_eigenvector(np.zeros((1, 4, 4)))).all()
