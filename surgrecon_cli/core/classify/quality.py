"""A quality signal without ground truth: how much of each frame the data support, and
whether the registration agrees with the measured noise. Pure numpy; no I/O.

Per frame: the shares of template points observed (intra/inter-camera inliers), unobserved,
outliers and labelled unknown; the median uncertainty σ (mm) of the labelled points; and
the median registration residual against its predicted size (residual / σ_target; about 1
when the registration agrees with the data as well as the noise allows) and the share of
residuals within 2σ_target (about 95 % expected). A frame gets a plain-words warning when one
of these says it should not be trusted. `verdict` words the run's overall statement from the
measured calibration (ground truth) or, without it, from these residual statistics: it never
claims a fit that the figures contradict.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .labels import DEFORMING, INTER, INTRA, OUTLIER, UNKNOWN, UNOBSERVED

# Ours: when a frame is flagged (the figures are reported whatever they are).
MIN_OBSERVED = 0.5  # less than half of the template observed
MAX_UNKNOWN = 0.2  # more than a fifth of the points unknown
MAX_RESIDUAL_RATIO = 3.0  # residuals 3x what the measured noise predicts
# A Gaussian 3D error lies within 2σ (σ = √trace Σ) 95-99 % of the time (core/noise/model.py); a
# share of at least GOOD_2SIGMA is read as "as expected", anything lower as σ understating it.
EXPECTED_2SIGMA = 0.95
GOOD_2SIGMA = 0.90
# Median residual / σ below this: the solve follows its targets more closely than their
# noise allows, so the residuals cannot tell how accurate the positions are.
TIGHT_RESIDUAL_RATIO = 0.3


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
    within_2sigma: float
    with_target: int
    failed: bool
    converged: bool
    warnings: tuple[str, ...]

    def row(self) -> dict[str, float | int | bool | str]:
        return {"frame": self.frame, "observed_fraction": self.observed,
                "unobserved_fraction": self.unobserved, "outlier_fraction": self.outlier,
                "unknown_fraction": self.unknown, "sigma_median_mm": self.sigma_median_mm,
                "residual_over_sigma": self.residual_over_sigma,
                "residual_within_2sigma": self.within_2sigma, "failed": self.failed,
                "converged": self.converged, "trustworthy": not self.warnings}


@dataclass(frozen=True)
class FrameFit:
    """One frame's registration as the quality figures read it: status (N,) reprojection
    check codes, registered σ (N,) m, residual to target (N,) m, target σ (N,) m, whether
    the registration failed (and why: `error`) and whether its solver converged."""

    status: np.ndarray
    sigma: np.ndarray
    residual: np.ndarray
    target_sigma: np.ndarray
    failed: bool
    converged: bool
    error: str = ""


def frame_quality(frame: int, fit: FrameFit, labels: np.ndarray | None = None
                  ) -> FrameQuality:
    """Quality of frame k from its registration `fit` and labels (N,) (None before
    classify)."""
    status, sigma, residual, target_sigma = fit.status, fit.sigma, fit.residual, fit.target_sigma
    failed, converged = fit.failed, fit.converged
    n = max(len(status), 1)
    observed = float(np.isin(status, (INTRA, INTER)).sum() / n)
    unknown = float((labels == UNKNOWN).sum() / n) if labels is not None else float("nan")
    labelled = (labels != UNKNOWN) if labels is not None else np.isfinite(sigma)
    sig = sigma[labelled & np.isfinite(sigma)]
    sigma_median = float(np.median(sig) * 1e3) if sig.size else float("nan")
    has = np.isfinite(residual) & np.isfinite(target_sigma) & (target_sigma > 0)
    ratios = residual[has] / target_sigma[has]
    ratio = float(np.median(ratios)) if has.any() else float("nan")
    within = float((ratios <= 2.0).mean()) if has.any() else float("nan")
    warnings = []
    if failed:
        warnings.append(f"frame {frame}: registration failed ({fit.error}); all points unknown")
    else:
        if observed < MIN_OBSERVED:
            warnings.append(f"frame {frame}: only {observed:.0%} of the template was observed; "
                            "the rest is extrapolated")
        if labels is not None and unknown > MAX_UNKNOWN:
            warnings.append(f"frame {frame}: {unknown:.0%} of the points are unknown "
                            f"({_unknown_reason(status, labels)})")
        if np.isfinite(ratio) and ratio > MAX_RESIDUAL_RATIO:
            warnings.append(f"frame {frame}: registration residuals are {ratio:.1f}x what the "
                            "measured noise predicts; positions are less accurate than σ says")
        if not converged:
            warnings.append(f"frame {frame}: the solver stopped before converging")
    return FrameQuality(
        frame=frame, observed=observed,
        unobserved=float((status == UNOBSERVED).sum() / n),
        outlier=float((status == OUTLIER).sum() / n), unknown=unknown,
        sigma_median_mm=sigma_median, residual_over_sigma=ratio, within_2sigma=within,
        with_target=int(has.sum()), failed=failed,
        converged=converged, warnings=tuple(warnings))


def _unknown_reason(status: np.ndarray, labels: np.ndarray) -> str:
    """Why a frame's unknown points are unknown, in words: mostly measured this frame (intra
    or inter-camera inliers: their σ exceeds classify.max_sigma_mm, as when the cameras are too
    far or their baseline too narrow for that precision) or mostly not (far from any data)."""
    unknown = labels == UNKNOWN
    measured = unknown & np.isin(status, (INTRA, INTER))
    if measured.sum() * 2 >= max(int(unknown.sum()), 1):
        return (f"{measured.sum() / max(int(unknown.sum()), 1):.0%} of them measured in this "
                "frame, but with an uncertainty σ above classify.max_sigma_mm: the cameras "
                "cannot place them that precisely")
    return "too far from any measurement"


@dataclass(frozen=True)
class Verdict:
    """The run's statement on its own accuracy: `fits` only when the figures it rests on
    (`basis`: "ground truth" or "residuals") agree with the noise model; `text` says so in
    plain words, with the figures."""

    fits: bool
    basis: str
    text: str


def pooled_within_2sigma(quality: list[FrameQuality]) -> tuple[float, float]:
    """Share of all residuals (frames 1.., points with a target) within 2σ_target, and the
    median over frames of the median residual / σ_target (NaN if none)."""
    counts = np.array([q.with_target for q in quality if np.isfinite(q.within_2sigma)], float)
    shares = np.array([q.within_2sigma for q in quality if np.isfinite(q.within_2sigma)])
    ratios = np.array([q.residual_over_sigma for q in quality])
    ratios = ratios[np.isfinite(ratios)]
    share = float((shares * counts).sum() / counts.sum()) if counts.sum() else float("nan")
    return share, float(np.median(ratios)) if ratios.size else float("nan")


def verdict(residual_within_2sigma: float, residual_ratio: float,
            calibration_2sigma: float | None = None,
            sigma_scale_95: float | None = None, flagged: int = 0,
            frames: int = 0) -> Verdict:
    """The run's verdict on its accuracy.

    With ground truth (`calibration_2sigma`: share of labelled points whose true error is
    within their reported 2σ; `sigma_scale_95`: the factor σ would need to cover 95 % of
    them), that measured calibration decides. Without it, the residuals to the targets
    (`residual_within_2sigma`, share within 2σ_target; `residual_ratio`, median residual /
    σ_target) decide, and the text says they cannot show the targets themselves are right;
    but when more than half of the `frames` registered frames (1..) are `flagged` not to
    trust (failed, mostly unobserved or unknown, ...), the run does not fit whatever the
    residuals of the rest say.
    """
    expected = f"{EXPECTED_2SIGMA:.0%} expected"
    if calibration_2sigma is not None and np.isfinite(calibration_2sigma):
        share = f"{calibration_2sigma:.0%} of labelled points are within 2σ of the truth"
        if calibration_2sigma >= GOOD_2SIGMA:
            return Verdict(True, "ground truth",
                           f"The reported uncertainty holds: {share} ({expected}).")
        scale = (f" σ would have to be {sigma_scale_95:.1f}× larger to cover 95 % of them."
                 if sigma_scale_95 is not None and np.isfinite(sigma_scale_95) else "")
        return Verdict(False, "ground truth",
                       f"The reported uncertainty understates the error: only {share} "
                       f"({expected}); positions are less accurate than σ says.{scale}")
    if not np.isfinite(residual_within_2sigma):
        return Verdict(False, "residuals",
                       "No frame has registration residuals to check against the noise model.")
    share = (f"{residual_within_2sigma:.0%} of registration residuals are within 2σ of their "
             f"targets ({expected})")
    if frames and 2 * flagged > frames:
        return Verdict(False, "residuals",
                       f"{flagged} of {frames} frames are not to be trusted (listed above), so "
                       f"the run is not: the residuals cannot vouch for it ({share}, median "
                       f"residual {residual_ratio:.2f}σ).")
    if residual_within_2sigma < GOOD_2SIGMA:
        return Verdict(False, "residuals",
                       f"Residuals are {residual_ratio:.1f}× larger than the noise model "
                       f"expects (median residual / σ; about 1 expected): only {share}. "
                       "Positions are less accurate than σ says.")
    caution = ("Without ground truth this checks the fit to the targets, not whether the "
               "targets themselves are right.")
    if np.isfinite(residual_ratio) and residual_ratio < TIGHT_RESIDUAL_RATIO:
        return Verdict(True, "residuals",
                       f"{share}, but the median residual is only {residual_ratio:.2f}σ: the "
                       "registration follows its targets more closely than their noise "
                       f"allows, so the residuals say little about accuracy. {caution}")
    return Verdict(True, "residuals", f"{share}: the registration agrees with the data as "
                                      f"well as the noise allows. {caution}")
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
