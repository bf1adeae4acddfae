"""Dents at the tolerance (issue 24, unseen `default` seeds): the registered field is smoother
than the tissue, so a dent just over `deform_mm` registers just under it; there the measured
positions, their noise taken out, decide too (`departure.measured_rms_mm`). Expected
magnitudes and labels come from the constructed truth and the stated noise."""

from __future__ import annotations

import numpy as np

from surgrecon_cli.config import ClassifyConfig
from surgrecon_cli.core.classify.departure import Measured, measured_rms_mm, resolved_rms_mm
from surgrecon_cli.core.classify.labels import (
    DEFORMING,
    SHIFTING,
    label_rule,
    radius_neighbourhoods,
)
from surgrecon_cli.core.classify.rules import (
    Evidence,
    RegisteredFrame,
    classify_frame,
    rigid_rms_mm,
    template_neighbourhoods,
)

CFG = ClassifyConfig()
SIGMA_M = 0.08e-3  # isotropic position noise, a wide multi-camera rig
SHIFT_M = np.array([0.002, 0.0, -0.0015])  # the whole patch moves 2.5 mm (shifting)


def _patch(half_mm: float) -> np.ndarray:
    """A square patch on a 1.5 mm grid, 65 mm from the camera (metres)."""
    g = np.arange(-half_mm, half_mm, 1.5) * 1e-3
    xx, yy = np.meshgrid(g, g)
    return np.column_stack([xx.ravel(), yy.ravel(), np.full(xx.size, 0.065)])


def _dents(template: np.ndarray, centres_mm: list[tuple[float, float]]) -> np.ndarray:
    """(N, 3) m: Gaussian dents 1.5 mm deep, σ 3 mm, pressed along the line of sight."""
    dent = np.zeros_like(template)
    for cx, cy in centres_mm:
        r2 = (template[:, 0] - cx * 1e-3) ** 2 + (template[:, 1] - cy * 1e-3) ** 2
        dent[:, 2] -= 1.5e-3 * np.exp(-r2 / (2 * 0.003**2))
    return dent


def _cov(n: int) -> np.ndarray:
    return np.broadcast_to(np.eye(3) * SIGMA_M**2, (n, 3, 3)).copy()


def test_measured_rms_takes_the_noise_out_of_the_departure():
    template = _patch(10.0)
    n = len(template)
    truth = template + SHIFT_M + _dents(template, [(0.0, 0.0)])
    nb = template_neighbourhoods(template, CFG.neighbourhood_mm, CFG.min_neighbours,
                                 CFG.max_neighbours)
    centre = np.array([int(np.argmin((template[:, :2] ** 2).sum(1)))])
    true_rms = rigid_rms_mm(template, truth, nb, centre)[0]
    assert 0.26 < true_rms < 0.35  # a dent just over the tolerance
    rng = np.random.default_rng(0)
    measured2, raw2, rigid2, rigid_raw2 = [], [], [], []
    for _ in range(200):
        noisy = truth + rng.normal(0.0, SIGMA_M, template.shape)
        measured2.append(measured_rms_mm(template, Measured(noisy, _cov(n), 1.0), nb, centre,
                                         CFG.deform_mm)[0] ** 2)
        raw2.append(resolved_rms_mm(template, noisy, _cov(n), nb, centre, CFG.deform_mm)[0] ** 2)
        still = template + SHIFT_M + rng.normal(0.0, SIGMA_M, template.shape)
        rigid2.append(measured_rms_mm(template, Measured(still, _cov(n), 1.0), nb, centre,
                                      CFG.deform_mm)[0] ** 2)
        rigid_raw2.append(resolved_rms_mm(template, still, _cov(n), nb, centre,
                                          CFG.deform_mm)[0] ** 2)
    # the noise adds its energy to the plain measure; taken out, the mean is the truth's
    assert np.mean(raw2) > true_rms**2 * 1.15
    np.testing.assert_allclose(np.mean(measured2), true_rms**2, rtol=0.06)
    # on a rigid motion what is left is the noise's scatter about zero (clipped at 0)
    assert np.mean(rigid2) < 0.2 * np.mean(rigid_raw2)
    # a noise scale that says the noise is larger takes more out
    noisy = truth + rng.normal(0.0, SIGMA_M, template.shape)
    assert (measured_rms_mm(template, Measured(noisy, _cov(n), 2.0), nb, centre, CFG.deform_mm)
            < measured_rms_mm(template, Measured(noisy, _cov(n), 1.0), nb, centre,
                              CFG.deform_mm)).all()


def test_a_dent_the_registration_smoothed_under_the_tolerance_is_still_deforming():
    template = _patch(30.0)
    n = len(template)
    dents = _dents(template, [(x, y) for x in (-20.0, 0.0, 20.0) for y in (-20.0, 0.0, 20.0)])
    truth = template + SHIFT_M + dents
    registered = template + SHIFT_M + 0.85 * dents  # the regulariser's shallower dents
    index, mask = radius_neighbourhoods(template, CFG.neighbourhood_mm * 1e-3)
    true_labels = label_rule(template, truth, index, mask, CFG.static_mm, CFG.deform_mm)
    deforming, shifting = true_labels == DEFORMING, true_labels == SHIFTING
    assert deforming.sum() > 40
    nb = template_neighbourhoods(template, CFG.neighbourhood_mm, CFG.min_neighbours,
                                 CFG.max_neighbours)
    # the premise: the registered field alone reaches the tolerance at a third of them
    registered_rms = resolved_rms_mm(template, registered, _cov(n), nb, np.arange(n),
                                     CFG.deform_mm)
    assert np.mean(registered_rms[deforming] >= CFG.deform_mm) < 0.4
    for seed in range(3):
        measured = truth + np.random.default_rng(seed).normal(0.0, SIGMA_M, template.shape)
        evidence = Evidence(sigma=np.full(n, SIGMA_M), template_sigma=np.zeros(n),
                            measured=measured, measured_sigma=np.full(n, SIGMA_M),
                            displacement_cov=_cov(n), departure_cov=_cov(n))
        labels = classify_frame(template, RegisteredFrame(registered), nb, CFG,
                                evidence=evidence).labels
        assert np.mean(labels[deforming] == DEFORMING) > 0.6
        assert np.mean(labels[shifting] == DEFORMING) < 0.01
