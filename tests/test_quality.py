"""Labels only where the frame's evidence supports them (core/quality.unsupported_points)."""

from __future__ import annotations

import numpy as np

from surgrecon_cli.core.classify.labels import (
    DEFORMING,
    INTER,
    INTRA,
    OUTLIER,
    SHIFTING,
    STATIC,
    UNOBSERVED,
)
from surgrecon_cli.core.classify.quality import FrameFit, frame_quality, unsupported_points


def _frame(status, residual_ratio):
    n = len(status)
    sigma = np.full(n, 2e-4)
    has = np.isin(status, (INTRA, INTER))
    residual = np.where(has, residual_ratio * sigma, np.nan)
    target_sigma = np.where(has, sigma, np.nan)
    return frame_quality(3, FrameFit(status, sigma, residual, target_sigma, False, True))


def _labels(n):
    return np.resize(np.array([STATIC, SHIFTING, DEFORMING], np.uint8), n)


def test_a_well_observed_frame_keeps_every_label():
    status = np.array([INTRA] * 60 + [INTER] * 20 + [OUTLIER] * 10 + [UNOBSERVED] * 10)
    assert not unsupported_points(_frame(status, 1.0), status, _labels(100)).any()


def test_a_mostly_unobserved_frame_drops_deforming_without_a_target():
    status = np.array([INTRA] * 20 + [INTER] * 10 + [OUTLIER] * 40 + [UNOBSERVED] * 30)
    labels = _labels(100)
    q = _frame(status, 1.0)
    assert q.warnings  # the report calls it untrustworthy; its labels must agree
    np.testing.assert_array_equal(unsupported_points(q, status, labels),
                                  np.isin(status, (OUTLIER, UNOBSERVED)) & (labels == DEFORMING))


def test_residuals_beyond_the_noise_leave_nothing_labelled():
    status = np.array([INTRA] * 70 + [INTER] * 30)
    assert unsupported_points(_frame(status, 5.0), status, _labels(100)).all()
