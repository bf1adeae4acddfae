"""The unknown rule tests the uncertainty of the displacement the labels are decided from
(issue 24): a template point's frame-0 error that tracking carries into its later
measurements cancels, a point far from any data stays unknown, and a point known loosely
but moved far beyond that looseness is moving. Expected figures come from the simulated
errors themselves."""

from __future__ import annotations

import numpy as np

from surgrecon_cli.config import ClassifyConfig
from surgrecon_cli.core.classify.labels import DEFORMING, SHIFTING, STATIC, UNKNOWN
from surgrecon_cli.core.classify.rules import (
    Evidence,
    RegisteredFrame,
    classify_frame,
    template_neighbourhoods,
)

DEPTH_M, LATERAL_M, LOCAL_M = 1.2e-3, 0.1e-3, 0.1e-3  # template error per axis; tracking's


def _carried(rng: np.random.Generator, template: np.ndarray, motion: np.ndarray):
    """True positions (template + motion), the frame-0 positions with their error and the
    later measurements, which carry the same error plus an independent localisation one;
    the template's covariance (N, 3, 3) m²."""
    n = len(template)
    scale = np.array([LATERAL_M, LATERAL_M, DEPTH_M])
    e0 = rng.standard_normal((n, 3)) * scale
    truth = template + motion
    measured = truth + e0 + rng.standard_normal((n, 3)) * LOCAL_M
    cov_t = np.broadcast_to(np.diag(scale**2), (n, 3, 3)).copy()
    return truth, template + e0, measured, cov_t


def _evidence(measured: np.ndarray, cov_t: np.ndarray, sigma: np.ndarray,
              has_target: np.ndarray | None = None) -> Evidence:
    """As stages/classify.frame_evidence: the target's covariance plus the template's where
    there is a target (default: everywhere), else isotropic from the registered σ."""
    t_var = np.trace(cov_t, axis1=1, axis2=2)
    cov = cov_t * 2 + np.eye(3) * LOCAL_M**2
    if has_target is not None:
        iso = (sigma**2 + t_var) / 3.0
        cov[~has_target] = iso[~has_target, None, None] * np.eye(3)
    return Evidence(sigma=sigma, template_sigma=np.sqrt(t_var), measured=measured,
                    measured_sigma=sigma, displacement_cov=cov, departure_cov=cov,
                    template_shared_var=t_var)


def test_displacement_sigma_matches_the_carried_error():
    rng = np.random.default_rng(11)
    template = rng.uniform(-0.02, 0.02, (4000, 3))
    truth, p0, measured, cov_t = _carried(rng, template, np.array([0.002, 0.0, 0.0]))
    position_sigma = np.sqrt(np.trace(cov_t, axis1=1, axis2=2) + 3 * LOCAL_M**2)
    sigma = _evidence(measured, cov_t, position_sigma).displacement_sigma()
    # the displacement's true error: measured − truth minus the template's own error
    error = (measured - p0) - (truth - template)
    rms = np.sqrt((error**2).sum(1).mean())
    assert abs(np.median(sigma) / rms - 1.0) < 0.1
    # the absolute position σ overstates it about (1.2 mm depth) / (0.17 mm) times
    assert np.median(position_sigma) > 5 * rms


def test_measured_points_are_labelled_and_far_ones_unknown():
    rng = np.random.default_rng(12)
    g = np.arange(-10, 10) * 1e-3
    xx, yy = np.meshgrid(g, g)
    template = np.column_stack([xx.ravel(), yy.ravel(), np.zeros(xx.size)])
    _, p0, measured, cov_t = _carried(rng, template, np.array([0.002, 0.0, 0.0]))
    n = len(template)
    position_sigma = np.sqrt(np.trace(cov_t, axis1=1, axis2=2) + 3 * LOCAL_M**2)
    # a corner without data, extrapolated from 5–13 mm away (σ grows 0.3 mm per mm)
    far = (template[:, 0] > 0.004) & (template[:, 1] > 0.004)
    distance = np.hypot(template[:, 0] - 0.004, template[:, 1] - 0.004) + 0.005
    sigma = np.where(far, np.hypot(position_sigma, 0.3 * distance), position_sigma)
    cfg = ClassifyConfig()
    assert np.median(position_sigma) * 1e3 > cfg.max_sigma_mm  # the old rule: all unknown
    nb = template_neighbourhoods(p0, cfg.neighbourhood_mm, cfg.min_neighbours,
                                 cfg.max_neighbours)
    labels = classify_frame(p0, RegisteredFrame(measured), nb, cfg,
                            evidence=_evidence(measured, cov_t, sigma, ~far)).labels
    # their 2 mm of extrapolated motion is within their σ (1.9-4.1 mm): unknown
    assert (labels[far] == UNKNOWN).all()
    # the measured points moved 2 mm rigidly: shifting, whatever their absolute depth error
    assert (labels[~far] == SHIFTING).mean() > 0.95
    assert n > far.sum() > 0


def test_loosely_measured_points_that_clearly_moved_are_moving():
    # A narrow stereo baseline far from the tissue: depth known to 2.5 mm, the directions
    # across the lines of sight to 0.1 mm, so the displacement's σ (2.5 mm) is above
    # classify.max_sigma_mm. The half of the tissue that slid 3 mm sideways has moved
    # beyond any doubt and is moving (shifting, or deforming at the fold); the still half's
    # displacement is within its noise and, known this loosely, not called static.
    rng = np.random.default_rng(13)
    g = np.arange(-10, 10) * 1e-3
    xx, yy = np.meshgrid(g, g)
    template = np.column_stack([xx.ravel(), yy.ravel(), np.full(xx.size, 0.06)])
    n = len(template)
    cov = np.broadcast_to(np.diag(np.array([0.1e-3, 0.1e-3, 2.5e-3]) ** 2), (n, 3, 3)).copy()
    slid = template[:, 0] < 0
    noise = rng.standard_normal((n, 3)) * np.array([0.1e-3, 0.1e-3, 2.5e-3])
    registered = template + noise + np.where(slid[:, None], [0.003, 0.0, 0.0], 0.0)
    sigma = np.full(n, 2.5e-3)
    evidence = Evidence(sigma=sigma, template_sigma=np.zeros(n), measured=registered,
                        measured_sigma=sigma, displacement_cov=cov, departure_cov=cov)
    cfg = ClassifyConfig()
    assert (evidence.displacement_sigma() * 1e3 > cfg.max_sigma_mm).all()
    nb = template_neighbourhoods(template, cfg.neighbourhood_mm, cfg.min_neighbours,
                                 cfg.max_neighbours)
    labels = classify_frame(template, RegisteredFrame(registered), nb, cfg,
                            evidence=evidence).labels
    assert np.isin(labels[slid], (SHIFTING, DEFORMING)).all()
    # beyond a neighbourhood's radius from the fold, the slid half moved as one piece
    inner = template[:, 0] < -(cfg.neighbourhood_mm + 0.5) * 1e-3
    assert (labels[inner] == SHIFTING).mean() > 0.95
    assert (labels[~slid] == UNKNOWN).mean() > 0.95
    assert not (labels == STATIC).any()
