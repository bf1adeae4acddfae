"""A quality signal without ground truth: how much of each frame the data support, and
whether the registration agrees with the measured noise. Pure numpy; no I/O.

Per frame: the shares of template points observed (intra/inter-camera inliers), unobserved,
outliers and labelled unknown; the median uncertainty σ (mm) of the labelled points; and
the median registration residual against its predicted size (residual / σ_target; about 1
when the registration agrees with the data as well as the noise allows). A frame gets a
plain-words warning when one of these says it should not be trusted.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .labels import DEFORMING, INTER, INTRA, OUTLIER, UNKNOWN, UNOBSERVED

# Ours: when a frame is flagged (the figures are reported whatever they are).
MIN_OBSERVED = 0.5  # less than half of the template observed
MAX_UNKNOWN = 0.2  # more than a fifth of the points unknown
MAX_RESIDUAL_RATIO = 3.0  # residuals 3x what the measured noise predicts


@dataclass(frozen=True)
class FrameQuality:
    """One frame's quality figures (fractions of the template's N points) and warnings."""

    frame: int
    observed: float
    unobserved: float
    outlier: float
    unknown: float
    sigma_median_mm: float
    residual_over_sigma: float
    failed: bool
    converged: bool
    warnings: tuple[str, ...]

    def row(self) -> dict[str, float | int | bool | str]:
        return {"frame": self.frame, "observed_fraction": self.observed,
                "unobserved_fraction": self.unobserved, "outlier_fraction": self.outlier,
                "unknown_fraction": self.unknown, "sigma_median_mm": self.sigma_median_mm,
                "residual_over_sigma": self.residual_over_sigma, "failed": self.failed,
                "converged": self.converged, "trustworthy": not self.warnings}


def frame_quality(frame: int, status: np.ndarray, labels: np.ndarray | None,
                  sigma: np.ndarray, residual: np.ndarray, target_sigma: np.ndarray,
                  failed: bool, converged: bool, error: str = "") -> FrameQuality:
    """Quality of frame k from its status (N,), labels (N,) (None before classify),
    registered σ (N,) m, residual to target (N,) m and target σ (N,) m."""
    n = max(len(status), 1)
    observed = float(np.isin(status, (INTRA, INTER)).sum() / n)
    unknown = float((labels == UNKNOWN).sum() / n) if labels is not None else float("nan")
    labelled = (labels != UNKNOWN) if labels is not None else np.isfinite(sigma)
    sig = sigma[labelled & np.isfinite(sigma)]
    sigma_median = float(np.median(sig) * 1e3) if sig.size else float("nan")
    has = np.isfinite(residual) & np.isfinite(target_sigma) & (target_sigma > 0)
    ratio = float(np.median(residual[has] / target_sigma[has])) if has.any() else float("nan")
    warnings = []
    if failed:
        warnings.append(f"frame {frame}: registration failed ({error}); all points unknown")
    else:
        if observed < MIN_OBSERVED:
            warnings.append(f"frame {frame}: only {observed:.0%} of the template was observed; "
                            "the rest is extrapolated")
        if labels is not None and unknown > MAX_UNKNOWN:
            warnings.append(f"frame {frame}: {unknown:.0%} of the points are unknown (too far "
                            "from any measurement)")
        if np.isfinite(ratio) and ratio > MAX_RESIDUAL_RATIO:
            warnings.append(f"frame {frame}: registration residuals are {ratio:.1f}x what the "
                            "measured noise predicts; positions are less accurate than σ says")
        if not converged:
            warnings.append(f"frame {frame}: the solver stopped before converging")
    return FrameQuality(
        frame=frame, observed=observed,
        unobserved=float((status == UNOBSERVED).sum() / n),
        outlier=float((status == OUTLIER).sum() / n), unknown=unknown,
        sigma_median_mm=sigma_median, residual_over_sigma=ratio, failed=failed,
        converged=converged, warnings=tuple(warnings))


def unsupported_points(quality: FrameQuality, status: np.ndarray,
                       labels: np.ndarray) -> np.ndarray:
    """(N,) bool: points of a frame whose label (N,) its evidence does not support, to be
    labelled unknown instead: every point when the registration residuals are more than
    MAX_RESIDUAL_RATIO times what the measured noise predicts (the positions are not what
    the data say); in a frame that observed less than MIN_OBSERVED of the template, the
    points called deforming without a target of their own there (outliers and unobserved
    points: a dent there would be the registration's extrapolation from a minority of the
    surface, not a measurement; static and shifting carry the motion last measured)."""
    status = np.asarray(status)
    if np.isfinite(quality.residual_over_sigma) and (quality.residual_over_sigma
                                                     > MAX_RESIDUAL_RATIO):
        return np.ones(len(status), bool)
    if quality.observed < MIN_OBSERVED:
        return ~np.isin(status, (INTRA, INTER)) & (np.asarray(labels) == DEFORMING)
    return np.zeros(len(status), bool)
