"""The neighbourhood rigid fit weighted by each member's full information
(core/classify/labels.rigid_fit_residuals with `information`): on a narrow stereo
baseline each point knows its depth far worse than its position across the line of sight;
a fit with one scalar weight per point lets the depth errors tilt it, and the residuals
across the lines of sight, which the labels count fully, then show motion that is not
there."""

from __future__ import annotations

import numpy as np

from surgrecon_cli.core.classify.labels import rigid_fit_residuals

SIGMA_ALONG = 1.0e-3  # m: depth error of a 4 mm stereo pair at ~90 mm, 360x288
SIGMA_ACROSS = 0.02e-3  # m: across the line of sight


def _neighbourhoods(count: int, members: int, seed: int):
    """`count` neighbourhoods of `members` points in 5 mm discs ~90 mm from a camera at the
    origin, moved rigidly (2°, 1 mm) and measured with the anisotropic noise above: template
    (P, 3), measured (P, 3), information (P, 3, 3), index (count, members), lines of sight
    (P, 3)."""
    rng = np.random.default_rng(seed)
    centres = np.column_stack([rng.uniform(-0.03, 0.03, (count, 2)), np.full(count, 0.09)])
    offsets = rng.uniform(-0.0035, 0.0035, (count, members, 3)) * [1, 1, 0.3]
    template = (centres[:, None] + offsets).reshape(-1, 3)
    angle = np.radians(2.0)
    turn = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0],
                     [0, 0, 1]])
    moved = template @ turn.T + [0.001, -0.0005, 0.0008]
    sight = moved / np.linalg.norm(moved, axis=1, keepdims=True)
    across = np.eye(3) - np.einsum("pi,pj->pij", sight, sight)
    cov = SIGMA_ALONG**2 * np.einsum("pi,pj->pij", sight, sight) + SIGMA_ACROSS**2 * across
    noise = np.einsum("pij,pj->pi", np.linalg.cholesky(cov + 1e-18 * np.eye(3)),
                      rng.normal(size=moved.shape))
    index = np.arange(count * members).reshape(count, members)
    return template, moved + noise, np.linalg.inv(cov), index, sight


def _across_rms(residual: np.ndarray, sight: np.ndarray, index: np.ndarray) -> np.ndarray:
    """RMS (count,) m of each neighbourhood's residuals across its members' lines of sight."""
    s = sight[index]
    across = residual - np.einsum("nki,nki->nk", residual, s)[..., None] * s
    return np.sqrt((across**2).sum(2).mean(1))


def test_information_keeps_depth_errors_out_of_the_well_measured_directions():
    template, measured, info, index, sight = _neighbourhoods(300, 8, seed=0)
    mask = np.ones(index.shape, bool)
    weight = np.trace(info, axis1=1, axis2=2) / 3.0
    scalar, _ = rigid_fit_residuals(template, measured, index, mask, weights=weight)
    full, keep = rigid_fit_residuals(template, measured, index, mask, weights=weight,
                                     information=info)
    assert keep.all()
    # 6 of 24 degrees of freedom go to the fit: the across residuals keep ~sqrt(3/4) of σ
    assert np.median(_across_rms(full, sight, index)) < 1.5 * SIGMA_ACROSS
    assert np.median(_across_rms(scalar, sight, index)) > 4 * SIGMA_ACROSS
    # and the Mahalanobis residual is what one rigid motion and the stated noise leave
    stat = np.einsum("nki,nkij,nkj->n", full, info[index], full)
    assert np.median(stat / (3 * 8 - 6)) < 1.2
