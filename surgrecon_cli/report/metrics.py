"""Report layer 2: the run in numbers, from `RunData`. Pure; no I/O.

`measure` gives the per-point figures of a registered run (`Measures`: residuals,
displacements, per-frame quality, measured noise), one row per frame (FRAME_COLUMNS, for
frames.csv) and the run summary (summary.json).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from .. import __version__
from ..config import Config
from ..core.labels import DEFORMING, SHIFTING, STATIC, STATUS_NAMES, UNKNOWN
from ..core.quality import FrameQuality, frame_quality
from ..io.metrics import finite_json
from .gather import RegisteredFrames, RunData

CLASS_COLUMNS = ("static", "shifting", "deforming", "unknown")
STATUS_COLUMNS = tuple(STATUS_NAMES[k] for k in sorted(STATUS_NAMES))
FRAME_COLUMNS = (
    "frame", "time_s", "points", *CLASS_COLUMNS, *STATUS_COLUMNS,
    "residual_median_mm", "residual_p95_mm",
    "displacement_median_mm", "displacement_p95_mm", "displacement_max_mm",
    "seconds_target", "seconds_register",
    "observed_fraction", "unobserved_fraction", "outlier_fraction", "unknown_fraction",
    "sigma_median_mm", "residual_over_sigma", "failed", "converged", "trustworthy",
    "error_median_mm", "error_p95_mm", "error_max_mm", "macro_f1",
)
# The stages the report times, in pipeline order (the report itself is not one of them).
TIMED_STAGES = ("ingest", "build-template", "register", "classify", "evaluate")
_CODES = {"static": STATIC, "shifting": SHIFTING, "deforming": DEFORMING, "unknown": UNKNOWN}


@dataclass(frozen=True)
class Measures:
    """Figures of a registered run, T frames x N points: residual_mm per frame (points with a
    target; frame 0 empty), displacement_mm (T, N) from the template, quality of frames
    1.., and the measured noise (`noise_figures`)."""

    residual_mm: list[np.ndarray]
    displacement_mm: np.ndarray
    quality: list[FrameQuality]
    noise: dict[str, Any]


@dataclass(frozen=True)
class Metrics:
    """rows: one dict per frame (FRAME_COLUMNS; None where a stage is not done); summary:
    the run at a glance (strict JSON); measures: None before registration."""

    rows: list[dict[str, Any]]
    summary: dict[str, Any]
    measures: Measures | None


def measure(data: RunData, config: Config) -> Metrics:
    """Everything the report computes from the run."""
    measures = None
    if data.registered is not None and data.template is not None:
        measures = registration_measures(data.registered, data.template, data.labels,
                                         data.log.report, data.template_summary)
    rows = frame_rows(data, measures)
    return Metrics(rows, run_summary(data, measures, rows, config), measures)


def registration_measures(reg: RegisteredFrames, template: np.ndarray,
                          labels: np.ndarray | None, ingest_report: dict[str, Any],
                          template_summary: dict[str, Any] | None) -> Measures:
    """Residuals, displacements (mm), per-frame quality and noise of the registered frames;
    labels (T, N) or None before classify."""
    n_frames = len(reg.positions)
    residual = [reg.residual[k][reg.has_target[k]].astype(float) * 1e3 for k in range(n_frames)]
    quality = [
        frame_quality(k, reg.status[k], None if labels is None else labels[k],
                      reg.sigma[k].astype(float), reg.residual[k].astype(float),
                      reg.target_sigma[k].astype(float), bool(reg.failed[k]),
                      bool(reg.converged[k]), reg.errors[k])
        for k in range(1, n_frames)]
    return Measures(residual, np.linalg.norm(reg.positions - template, axis=2) * 1e3, quality,
                    noise_figures(ingest_report, template_summary, reg.tracking_px[1:]))


def noise_figures(ingest_report: dict[str, Any], template_summary: dict[str, Any] | None,
                  tracking_px: np.ndarray) -> dict[str, Any]:
    """The run's measured noise: pixel noise px (template), tracker jitter per camera (mm,
    deg; ingest) and tracking noise px (median over the frames' tracking_px)."""
    stats = (template_summary or {}).get("stats", {})
    cams = ingest_report.get("cameras", {})
    tracking = tracking_px[np.isfinite(tracking_px)]
    return {
        "pixel_px": stats.get("pixel_noise_px"),
        "tracking_px": float(np.median(tracking)) if tracking.size else None,
        "tracker_jitter_mm": {c: r.get("tracker_jitter_mm") for c, r in cams.items()},
        "tracker_jitter_deg": {c: r.get("tracker_jitter_deg") for c, r in cams.items()},
    }


def stats(values: np.ndarray) -> tuple[float, float, float]:
    """Median, 95th percentile and maximum of the finite values (NaN if none)."""
    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    if not v.size:
        return float("nan"), float("nan"), float("nan")
    return float(np.median(v)), float(np.percentile(v, 95)), float(v.max())


def frame_rows(data: RunData, measures: Measures | None) -> list[dict[str, Any]]:
    """One dict per frame with the FRAME_COLUMNS (missing parts are None)."""
    log = data.log
    t0 = log.stamps_ns[0] if log.n_frames else 0
    reg_eval = _per_frame(data.evaluation, "registration")
    label_eval = _per_frame(data.evaluation, "labels")
    reg = data.registered
    rows = []
    for k in range(log.n_frames):
        row: dict[str, Any] = {"frame": k, "time_s": round(float(log.stamps_ns[k] - t0) / 1e9, 6)}
        if data.template is not None:
            row["points"] = len(data.template)
        if data.labels is not None:
            for name in CLASS_COLUMNS:
                row[name] = int((data.labels[k] == _CODES[name]).sum())
        if reg is not None and measures is not None and k > 0:
            for code, name in STATUS_NAMES.items():
                row[name] = int((reg.status[k] == code).sum())
            row["residual_median_mm"], row["residual_p95_mm"], _ = stats(measures.residual_mm[k])
            row["seconds_target"], row["seconds_register"] = (float(x) for x in reg.seconds[k])
            row.update({key: value for key, value in measures.quality[k - 1].row().items()
                        if key != "frame"})
        if measures is not None:
            (row["displacement_median_mm"], row["displacement_p95_mm"],
             row["displacement_max_mm"]) = stats(measures.displacement_mm[k])
        if k in reg_eval:
            e = reg_eval[k]
            row["error_median_mm"], row["error_p95_mm"], row["error_max_mm"] = (
                e.get("median_mm"), e.get("p95_mm"), e.get("max_mm"))
        if k in label_eval:
            row["macro_f1"] = label_eval[k].get("macro_f1")
        rows.append(row)
    return rows


def _per_frame(evaluation: dict[str, Any] | None, part: str) -> dict[int, dict[str, Any]]:
    """{frame: scores} of one part ("registration", "labels") of the evaluation."""
    if not evaluation:
        return {}
    return {r["frame"]: r for r in (evaluation.get(part) or {}).get("per_frame", [])}


def stage_seconds(run: dict[str, Any]) -> dict[str, float]:
    """Wall time s of each timed stage that ran (run.json; a pipeline's own record else)."""
    stages = run.get("stages", {})
    piped = run.get("pipeline", {}).get("seconds", {})
    out = {}
    for name in TIMED_STAGES:
        seconds = stages.get(name, {}).get("seconds", piped.get(name))
        if seconds is not None:
            out[name] = float(seconds)
    return out


def run_summary(data: RunData, measures: Measures | None, rows: list[dict[str, Any]],
                config: Config) -> dict[str, Any]:
    """The run at a glance (summary.json): counts, timings, template, classes, registration,
    evaluation, quality and the classify settings; NaN as None."""
    run, log = data.run, data.log
    later = rows[1:]
    summary: dict[str, Any] = {
        "surgrecon": __version__,
        "input": run.get("input", {}),
        "frames": log.n_frames,
        "cameras": list(log.cameras),
        "template_points": None if data.template is None else len(data.template),
        "stages": {k: v.get("status") for k, v in run.get("stages", {}).items()},
        "seconds": stage_seconds(run),
    }
    if data.template_summary:
        summary["camera_pairs"] = data.template_summary.get("pairs", {})
        summary["template"] = data.template_summary.get("stats", {})
    if data.labels is not None:
        counts = {name: int(sum(r[name] for r in later)) for name in CLASS_COLUMNS}
        total = max(sum(counts.values()), 1)
        summary["classes_frames_1_on"] = {
            "counts": counts, "fractions": {k: v / total for k, v in counts.items()}}
    if data.registered is not None and measures is not None and log.n_frames > 1:
        summary["status_frames_1_on"] = {name: int(sum(r[name] for r in later))
                                         for name in STATUS_COLUMNS}
        med, p95, mx = stats(np.concatenate(measures.residual_mm[1:]))
        summary["residual_mm"] = {"median": med, "p95": p95, "max": mx}
        med, p95, mx = stats(measures.displacement_mm[1:])
        summary["displacement_mm"] = {"median": med, "p95": p95, "max": mx}
        seconds = data.registered.seconds
        summary["seconds_per_frame"] = {"target_mean": float(np.nanmean(seconds[1:, 0])),
                                        "register_mean": float(np.nanmean(seconds[1:, 1]))}
    if data.evaluation:
        ev = data.evaluation
        summary["evaluation"] = {
            "template_error_mm": ev["template"]["error"],
            "template_on_tool": ev["template"].get("on_tool"),
            "registration_error_mm": (ev.get("registration") or {}).get("overall"),
            "macro_f1": ((ev.get("labels") or {}).get("overall") or {}).get("macro_f1"),
        }
    if measures is not None:
        summary["noise"] = measures.noise
        summary["quality"] = {
            "per_frame": [q.row() for q in measures.quality],
            "warnings": [w for q in measures.quality for w in q.warnings],
            "untrustworthy_frames": [q.frame for q in measures.quality if q.warnings],
        }
    summary["classify"] = {"static_mm": config.classify.static_mm,
                           "significance": config.classify.significance,
                           "max_sigma_mm": config.classify.max_sigma_mm,
                           "deform_mm": config.classify.deform_mm,
                           "measure": config.classify.measure}
    return finite_json(summary)
