"""Report layer 1b: the registered frames reduced, one frame at a time, to the figures the
report shows (report/gather.py feeds `FrameAccumulator` as it reads). Pure; no I/O.

What is kept grows with the frames only by a few numbers a frame (counts, statistics,
quality); per-point values are kept for at most `SAMPLED_FRAMES` frames, evenly spaced
(all frames of a shorter log): the per-frame box plots and the run's median and 95th
percentile of residual and displacement come from them (their maxima from every frame).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..core.classify.labels import DEFORMING, SHIFTING, STATIC, STATUS_NAMES, UNKNOWN
from ..core.classify.quality import FrameFit, FrameQuality, frame_quality
from ..io.run.artefacts import FrameRegistration

SAMPLED_FRAMES = 200
CLASS_CODES = {"static": STATIC, "shifting": SHIFTING, "deforming": DEFORMING,
               "unknown": UNKNOWN}
STATUS_CODES = tuple(sorted(STATUS_NAMES))


def sampled_frames(n_frames: int) -> np.ndarray:
    """Frames 1.. whose per-point values are kept: all up to `SAMPLED_FRAMES`, else that
    many evenly spaced, the first and the last included (K,) int."""
    if n_frames - 1 <= SAMPLED_FRAMES:
        return np.arange(1, max(n_frames, 1))
    return np.unique(np.linspace(1, n_frames - 1, SAMPLED_FRAMES).round().astype(int))


def stats(values: np.ndarray) -> tuple[float, float, float]:
    """Median, 95th percentile and maximum of the finite values (NaN if none)."""
    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    if not v.size:
        return float("nan"), float("nan"), float("nan")
    return float(np.median(v)), float(np.percentile(v, 95)), float(v.max())


@dataclass(frozen=True)
class FrameFigures:
    """The registered frames in numbers, T frames (frame 0 the template: not solved).

    status_counts (T, S) points per reprojection status (STATUS_CODES order; frame 0: 0);
    residual_mm (T, 3) median, p95, max of the points with a target (frame 0: NaN);
    displacement_mm (T, 3) of ‖registered − template‖; failed, converged (T,) bool, errors
    (T,) how each solve went; tracking_px (T,); seconds (T, 2) target and registration s
    (frame 0: NaN); quality of frames 1..; sampled (K,) frames with their per-point
    residual_sampled and displacement_sampled (mm, K arrays); residual_max_mm and
    displacement_max_mm over every frame 1..; class_counts (T, 4) points per class
    (CLASS_CODES order) or None before classify; deform_floor_mm (T,) the median over the
    labelled points of the rigid-fit RMS a bend along the lines of sight needs to be
    labelled deforming (labels.npz floor_mm; NaN for frame 0, without labelled points or
    in a run classified before the floor was stored), None before classify;
    floor_sampled the sampled frames' per-point floors (mm, K arrays of the labelled
    points; empty without a stored floor), None before classify."""

    status_counts: np.ndarray
    residual_mm: np.ndarray
    displacement_mm: np.ndarray
    failed: np.ndarray
    converged: np.ndarray
    errors: tuple[str, ...]
    tracking_px: np.ndarray
    seconds: np.ndarray
    quality: list[FrameQuality]
    sampled: np.ndarray
    residual_sampled: list[np.ndarray]
    displacement_sampled: list[np.ndarray]
    residual_max_mm: float
    displacement_max_mm: float
    class_counts: np.ndarray | None
    deform_floor_mm: np.ndarray | None
    floor_sampled: list[np.ndarray] | None


@dataclass
class FrameAccumulator:
    """Collects `FrameFigures` from frames 0, 1, ... given one at a time (`add`)."""

    template: np.ndarray
    n_frames: int
    classified: bool
    _sampled: set[int] = field(default_factory=set)
    _lists: dict[str, list] = field(default_factory=dict)

    def __post_init__(self) -> None:
        t = self.n_frames
        self.status_counts = np.zeros((t, len(STATUS_CODES)), np.int64)
        self.residual = np.full((t, 3), np.nan)
        self.displacement = np.full((t, 3), np.nan)
        self.failed, self.converged = np.zeros(t, bool), np.ones(t, bool)
        self.tracking_px, self.seconds = np.full(t, np.nan), np.full((t, 2), np.nan)
        self.class_counts = np.zeros((t, len(CLASS_CODES)), np.int64)
        self.deform_floor_mm = np.full(t, np.nan)
        self._sampled = set(sampled_frames(t).tolist())
        self._lists = {"errors": [""] * t, "quality": [], "residual": [], "displacement": [],
                       "floor": []}
        self.maxima = [np.nan, np.nan]

    def add(self, k: int, reg: FrameRegistration | None, labels: np.ndarray | None,
            floor_mm: np.ndarray | None = None) -> None:
        """Frame k: its registration (None for frame 0), labels (N,) and deformation floor
        (N,) mm (None before classify)."""
        if labels is not None:
            found = np.bincount(labels, minlength=256)
            self.class_counts[k] = [found[c] for c in CLASS_CODES.values()]
        floor = None if floor_mm is None else floor_mm[np.isfinite(floor_mm)]
        if k > 0 and floor is not None:
            self.deform_floor_mm[k] = float(np.median(floor)) if floor.size else np.nan
        if reg is None:
            self.displacement[k] = 0.0
            return
        status = reg.status
        found = np.bincount(status, minlength=256)
        self.status_counts[k] = [found[c] for c in STATUS_CODES]
        residual = reg.residual[reg.has_target].astype(float) * 1e3
        displacement = np.linalg.norm(reg.registered - self.template, axis=1) * 1e3
        self.residual[k], self.displacement[k] = stats(residual), stats(displacement)
        self.maxima = [np.fmax(m, s[2]) for m, s in zip(self.maxima, (self.residual[k],
                                                                      self.displacement[k]),
                                                        strict=True)]
        if k in self._sampled:
            self._lists["residual"].append(residual)
            self._lists["displacement"].append(displacement)
            if floor is not None:
                self._lists["floor"].append(floor)
        self.failed[k], self.converged[k] = reg.failed, reg.converged
        self._lists["errors"][k] = reg.error
        self.tracking_px[k] = reg.tracking_px
        self.seconds[k] = [reg.seconds_target, reg.seconds_register]
        self._lists["quality"].append(frame_quality(k, FrameFit(
            status, reg.sigma.astype(float), reg.residual.astype(float),
            reg.target_sigma.astype(float), bool(reg.failed), bool(reg.converged), reg.error),
            labels))

    def result(self) -> FrameFigures:
        lists = self._lists
        return FrameFigures(
            self.status_counts, self.residual, self.displacement, self.failed,
            self.converged, tuple(lists["errors"]), self.tracking_px, self.seconds,
            lists["quality"], np.array(sorted(self._sampled), int), lists["residual"],
            lists["displacement"], float(self.maxima[0]), float(self.maxima[1]),
            self.class_counts if self.classified else None,
            self.deform_floor_mm if self.classified else None,
            lists["floor"] if self.classified else None)
