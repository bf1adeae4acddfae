"""Report layer 2: the run in numbers, from `RunData`. Pure; no I/O.

`measure` gives, from the per-frame figures gathered (report/frames.py), one row per frame
(FRAME_COLUMNS, for frames.csv), the run summary (summary.json) and the measured noise.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from .. import __version__
from ..config import Config
from ..core.classify.labels import STATUS_NAMES
from ..core.classify.quality import GOOD_2SIGMA, Verdict, pooled_within_2sigma, verdict
from ..io.run.metrics import finite_json
from .caveats import run_caveats
from .frames import CLASS_CODES, STATUS_CODES, FrameFigures, stats
from .gather import RunData

CLASS_COLUMNS = tuple(CLASS_CODES)
STATUS_COLUMNS = tuple(STATUS_NAMES[k] for k in STATUS_CODES)
FRAME_COLUMNS = (
    "frame", "time_s", "points", *CLASS_COLUMNS, *STATUS_COLUMNS,
    "residual_median_mm", "residual_p95_mm",
    "displacement_median_mm", "displacement_p95_mm", "displacement_max_mm",
    "deform_floor_median_mm", "seconds_target", "seconds_register",
    "observed_fraction", "unobserved_fraction", "outlier_fraction", "unknown_fraction",
    "sigma_median_mm", "residual_over_sigma", "residual_within_2sigma", "failed",
    "converged", "trustworthy",
    "error_median_mm", "error_p95_mm", "error_max_mm", "macro_f1",
)
# The stages the report times, in pipeline order (the report itself is not one of them).
TIMED_STAGES = ("ingest", "build-template", "register", "classify", "measure", "evaluate")


@dataclass(frozen=True)
class Metrics:
    """rows: one dict per frame (FRAME_COLUMNS; None where a stage is not done); summary:
    the run at a glance (strict JSON); noise: the measured noise (`noise_figures`), None
    before registration; verdict: the run's statement on its accuracy (None before
    registration); caveats: what damaged or altered the run (report/caveats.py)."""

    rows: list[dict[str, Any]]
    summary: dict[str, Any]
    noise: dict[str, Any] | None
    verdict: Verdict | None = None
    caveats: tuple[str, ...] = ()


def measure(data: RunData, config: Config) -> Metrics:
    """Everything the report computes from the run."""
    noise = None
    if data.frames is not None:
        noise = noise_figures(data.log.report, data.log.cameras, data.template_summary,
                              data.frames.tracking_px[1:])
    rows = frame_rows(data)
    judged = None if data.frames is None else run_verdict(data)
    caveats = tuple(run_caveats(data.run, data.log.report))
    summary = run_summary(data, noise, rows, config)
    summary["caveats"] = list(caveats)
    if judged is not None:
        summary["quality"]["verdict"] = {"fits": judged.fits, "basis": judged.basis,
                                         "text": judged.text}
    return Metrics(rows, summary, noise, judged, caveats)


def run_verdict(data: RunData) -> Verdict:
    """The verdict from the evaluation's calibration when there is ground truth, else from
    the registration residuals against their σ; a truth that covers only part of the
    template (holes, a border) is said to."""
    assert data.frames is not None
    quality = data.frames.quality
    share, ratio = pooled_within_2sigma(quality)
    labels = (data.evaluation or {}).get("labels") or {}
    judged = verdict(share, ratio, labels.get("calibration_2sigma"),
                     labels.get("sigma_scale_95"),
                     flagged=sum(bool(q.warnings) for q in quality), frames=len(quality))
    covered = labels.get("truth_covered_fraction")
    if judged.basis == "ground truth" and covered is not None and covered < 1.0:
        judged = replace(judged, text=f"{judged.text} {truth_coverage_words(covered)}")
    return judged


def calibration_tile(labels: dict[str, Any]) -> tuple[str, str, str] | None:
    """The overview's tile (label, value, "good" / "bad") of an evaluation's 2σ calibration
    (its `labels` part), saying how much of the template the truth covers; None without."""
    calibration, covered = labels.get("calibration_2sigma"), labels.get("truth_covered_fraction")
    if calibration is None:
        return None
    where = f", of the {covered:.0%} it covers" if covered is not None and covered < 1.0 else ""
    return (f"labelled points within 2σ of the truth (95 % expected{where})",
            f"{calibration:.0%}", "good" if calibration >= GOOD_2SIGMA else "bad")


def truth_coverage_words(covered: float) -> str:
    """What a calibration over the covered share (0-1) of the template leaves out."""
    return (f"The truth covers {covered:.0%} of the template points; the others lie over its "
            "holes or beyond its border, where its own error is the hole's, and are not "
            "counted.")


def noise_figures(ingest_report: dict[str, Any], cameras: tuple[str, ...],
                  template_summary: dict[str, Any] | None,
                  tracking_px: np.ndarray) -> dict[str, Any]:
    """The run's measured noise: pixel noise px (template) with its localisation part and
    each camera's systematic offset (px: a calibration error or a tracked camera's frame-0
    pose error), tracker jitter per camera (mm, deg; ingest) and tracking noise px (median
    over the frames' tracking_px)."""
    stats = (template_summary or {}).get("stats", {})
    cams = ingest_report.get("cameras", {})
    tracking = tracking_px[np.isfinite(tracking_px)]
    offsets = stats.get("calibration_offset_px") or []
    return {
        "pixel_px": stats.get("pixel_noise_px"),
        "localisation_px": stats.get("localisation_px"),
        "calibration_offset_px": dict(zip(cameras, offsets, strict=False)),
        "tracking_px": float(np.median(tracking)) if tracking.size else None,
        "tracker_jitter_mm": {c: r.get("tracker_jitter_mm") for c, r in cams.items()},
        "tracker_jitter_deg": {c: r.get("tracker_jitter_deg") for c, r in cams.items()},
    }


def frame_rows(data: RunData) -> list[dict[str, Any]]:
    """One dict per frame with the FRAME_COLUMNS (missing parts are None)."""
    log, frames, counts = data.log, data.frames, data.class_counts
    t0 = log.stamps_ns[0] if log.n_frames else 0
    reg_eval = _per_frame(data.evaluation, "registration")
    label_eval = _per_frame(data.evaluation, "labels")
    rows = []
    for k in range(log.n_frames):
        row: dict[str, Any] = {"frame": k, "time_s": round(float(log.stamps_ns[k] - t0) / 1e9, 6)}
        if data.template is not None:
            row["points"] = len(data.template)
        if counts is not None:
            row.update(zip(CLASS_COLUMNS, (int(c) for c in counts[k]), strict=True))
        if frames is not None and k > 0:
            row.update(zip(STATUS_COLUMNS, (int(c) for c in frames.status_counts[k]),
                           strict=True))
            row["residual_median_mm"], row["residual_p95_mm"] = (
                float(x) for x in frames.residual_mm[k, :2])
            row["seconds_target"], row["seconds_register"] = (float(x) for x in frames.seconds[k])
            row.update({key: value for key, value in frames.quality[k - 1].row().items()
                        if key != "frame"})
        if frames is not None:
            (row["displacement_median_mm"], row["displacement_p95_mm"],
             row["displacement_max_mm"]) = (float(x) for x in frames.displacement_mm[k])
            if frames.deform_floor_mm is not None and k > 0:
                row["deform_floor_median_mm"] = float(frames.deform_floor_mm[k])
        if k in reg_eval:
            e = reg_eval[k]
            row["error_median_mm"], row["error_p95_mm"], row["error_max_mm"] = (
                e.get("median_mm"), e.get("p95_mm"), e.get("max_mm"))
        if k in label_eval:
            row["macro_f1"] = label_eval[k].get("macro_f1")
        rows.append(row)
    return rows


def median_deform_floor_mm(frames: FrameFigures | None) -> float | None:
    """The median over frames 1.. of each frame's median deformation floor (mm: the
    rigid-fit RMS a departure along the lines of sight needs to count as deforming); None
    before classify or without labelled points."""
    floors = None if frames is None or frames.deform_floor_mm is None else (
        frames.deform_floor_mm[1:])
    if floors is None or not np.isfinite(floors).any():
        return None
    return float(np.nanmedian(floors))


def floor_words(floor_mm: float | None, deform_mm: float) -> str:
    """What the run's deformation floor (mm, `deform_floor_mm`) means for its labels; "" when
    it is deform_mm itself (within 5 %) or unknown."""
    if floor_mm is None or floor_mm <= deform_mm * 1.05:
        return ""
    return (f"Along the direction each point is measured worst (on a stereo rig, its line "
            f"of sight), a bend counts as deforming once its neighbourhood's rigid-fit RMS "
            f"reaches {floor_mm:.2f} mm (median over frames and labelled points, "
            f"metrics/frames.csv deform_floor_median_mm), not {deform_mm:g} mm: smaller bends "
            "along it are labelled shifting.")


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


def run_summary(data: RunData, noise: dict[str, Any] | None, rows: list[dict[str, Any]],
                config: Config) -> dict[str, Any]:
    """The run at a glance (summary.json): counts, timings, template, classes, registration,
    evaluation, quality and the classify settings; NaN as None. The run's residual and
    displacement median and p95 pool the sampled frames (all frames of a log of at most
    report/frames.SAMPLED_FRAMES), their maxima every frame."""
    run, log, frames = data.run, data.log, data.frames
    later = rows[1:]
    summary: dict[str, Any] = {
        "surgrecon": __version__,
        "input": run.get("input", {}),
        "frames": log.n_frames,
        "cameras": list(log.cameras),
        "template_points": None if data.template is None else len(data.template),
        # the stages before the report (this file is the report's: run.json has its status)
        "stages": {k: v.get("status") for k, v in run.get("stages", {}).items()
                   if k != "report"},
        "seconds": stage_seconds(run),
    }
    if data.template_summary:
        summary["camera_pairs"] = data.template_summary.get("pairs", {})
        summary["template"] = data.template_summary.get("stats", {})
    if data.class_counts is not None:
        counts = {name: int(sum(r[name] for r in later)) for name in CLASS_COLUMNS}
        total = max(sum(counts.values()), 1)
        summary["classes_frames_1_on"] = {
            "counts": counts, "fractions": {k: v / total for k, v in counts.items()}}
    if frames is not None and log.n_frames > 1:
        summary["status_frames_1_on"] = {name: int(sum(r[name] for r in later))
                                         for name in STATUS_COLUMNS}
        for key, sample, largest in (
                ("residual_mm", frames.residual_sampled, frames.residual_max_mm),
                ("displacement_mm", frames.displacement_sampled, frames.displacement_max_mm)):
            med, p95, _ = stats(np.concatenate(sample))
            summary[key] = {"median": med, "p95": p95, "max": largest}
        seconds = frames.seconds
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
    if data.deformation_summary is not None:
        summary["deformation"] = data.deformation_summary
        scores = (data.evaluation or {}).get("deformation")
        if scores:
            summary.setdefault("evaluation", {})["deformation"] = {
                k: scores[k] for k in ("onset_error_frames", "release_error_frames",
                                       "indentation_error_mm", "area_error_share", "goals")}
    if frames is not None:
        summary["noise"] = noise
        summary["quality"] = {
            "residual_within_2sigma": pooled_within_2sigma(frames.quality)[0],
            "per_frame": [q.row() for q in frames.quality],
            "warnings": [w for q in frames.quality for w in q.warnings],
            "untrustworthy_frames": [q.frame for q in frames.quality if q.warnings],
        }
    summary["classify"] = {"static_mm": config.classify.static_mm,
                           "significance": config.classify.significance,
                           "max_sigma_mm": config.classify.max_sigma_mm,
                           "deform_mm": config.classify.deform_mm,
                           "deform_floor_mm": median_deform_floor_mm(frames),
                           "measure": config.classify.measure}
    return finite_json(summary)
