"""Stage `evaluate`: score a run against the simulator's ground truth (docs/accuracy.md).

Scores whatever parts the run has: the template (always), the registration (when `register`
is done), the labels (when `classify` is done) and the contact and indentation measures
(when `measure` is done; core/evaluate/deformation_scoring.py: the same definitions on the true
surface, with the true tool poses, or the ingested ones for ground truth written before
they were recorded). Ground-truth frame k is the k-th ingested frame. Writes atomically
  RUN/metrics/evaluation.json         the scores (mm)
  RUN/metrics/evaluation_errors.npz   template_error_mm (N,), on_tool (N,) bool,
                                      registration_error_mm (T, N) (frame 0: NaN),
                                      true_labels (T, N) uint8 (for the report's plots)
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from ..config import Config
from ..core.classify.labels import UNKNOWN
from ..core.evaluate.deformation_scoring import score_deformation, true_deformation
from ..core.evaluate.evaluation import (
    error_summary,
    on_tool,
    registration_errors,
    true_point_labels,
)
from ..core.evaluate.scoring import (
    distance_stats_mm,
    label_scores,
    map_to_surface,
    on_mesh_rim,
)
from ..core.measure.indentation import NOT_MEASURED, camera_viewpoint, tool_known
from ..errors import InputError
from ..io.logs.ground_truth import GroundTruth, load_ground_truth
from ..io.run.artefacts import read_deformation, read_labels, read_registration, read_template
from ..io.run.atomic import write_npz
from ..io.run.folder import RunFolder
from ..io.run.ingest_store import IngestedLog, load_ingested
from ..io.run.layout import RunLayout
from ..io.run.metrics import finite_json, write_metrics_json
from .common import stage_run
from .registry import StageContext

logger = logging.getLogger(__name__)

STAGE = "evaluate"
UNSUPPORTED_MM = 5.0  # the bound: a labelled point without data this far off is a lie


def run_evaluate(run_dir: Path, config: Config, gt_path: Path,
                 on_step: Callable[[int, int], None] | None = None) -> dict[str, Any]:
    """Evaluate the run against `gt_path`; returns the evaluation (as written to JSON).

    `on_step(done, total)` reports progress over the frames."""
    layout = RunLayout(run_dir)
    run = RunFolder(layout.root)
    step = on_step or (lambda _d, _t: None)
    with stage_run(layout.root, STAGE, config) as info:
        gt = load_ground_truth(gt_path)
        log = load_ingested(layout.ingest_dir)
        if gt.n_frames != log.n_frames:
            if log.n_frames > gt.n_frames:
                raise InputError(
                    f"{gt.path} has {gt.n_frames} frames but {run_dir} ingested "
                    f"{log.n_frames}; ground-truth frame k must be the k-th ingested frame "
                    "(wrong file?)")
            # a part of the log (ingest.start_s / duration_s / every, or a truncated log)
            gt = gt.at_stamps(log.stamps_ns, round(config.ingest.sync_tolerance_ms * 1e6))
        template = read_template(layout).points
        mapping = map_to_surface(template, gt.vertices[0], gt.faces)
        tool_mask = on_tool(template, log.tool_poses[0], config.tool)
        result: dict[str, Any] = {
            "ground_truth": {"path": str(gt.path.resolve()), "sha256": gt.sha256,
                             "frames": gt.n_frames, "vertices": int(gt.vertices.shape[1])},
            "frames": log.n_frames,
            "stamp_difference_max_ms": float(np.abs(gt.stamps_ns - log.stamps_ns).max() / 1e6),
            "template": _template_part(mapping.distance, tool_mask, config),
            "registration": None,
            "labels": None,
            "deformation": None,
        }
        n_frames, n = log.n_frames, len(template)
        errors = np.full((n_frames, n), np.nan, np.float32)
        sigma = np.full((n_frames, n), np.nan, np.float32)
        has_data = np.zeros((n_frames, n), bool)
        truth = true_point_labels(mapping, gt.faces, gt.labels).astype(np.uint8)
        if run.is_done("register"):
            result["registration"] = _registration_part(layout, gt, mapping, errors, sigma,
                                                        has_data, step)
        if run.is_done("classify"):
            labels = read_labels(layout, truth.shape).labels
            result["labels"] = _labels_part(labels, truth)
            if result["registration"] is not None:
                covered = ~on_mesh_rim(mapping, gt.faces)
                _honesty_part(result, labels, (errors, sigma, has_data), covered)
        if run.is_done("measure"):
            result["deformation"] = _deformation_part(layout, gt, log, config, len(template))
        write_npz(layout.evaluation_errors,
                  template_error_mm=(mapping.distance * 1e3).astype(np.float32),
                  on_tool=np.zeros(n, bool) if tool_mask is None else tool_mask,
                  registration_error_mm=errors, true_labels=truth)
        result = finite_json(result)
        write_metrics_json(layout.evaluation_json, result)
        step(n_frames, n_frames)
        info.update(ground_truth=result["ground_truth"],
                    parts=[p for p in ("template", "registration", "labels", "deformation")
                           if result[p]])
    return result


def _template_part(distance_m: np.ndarray, tool_mask: np.ndarray | None,
                   config: Config) -> dict[str, Any]:
    part: dict[str, Any] = {"points": len(distance_m), "error": distance_stats_mm(distance_m)}
    if tool_mask is None:
        part["on_tool"] = None
        logger.warning("frame-0 tool pose unknown: template points on the tool not counted")
    else:
        part["on_tool"] = {"count": int(tool_mask.sum()),
                           "fraction": float(tool_mask.mean()) if len(tool_mask) else 0.0,
                           "shaft_radius_mm": config.tool.shaft_radius_m * 1e3}
        part["error_off_tool"] = distance_stats_mm(distance_m[~tool_mask])
    return part


def _registration_part(layout: RunLayout, gt: GroundTruth, mapping: Any, errors: np.ndarray,
                       sigma: np.ndarray, has_data: np.ndarray,
                       step: Callable[[int, int], None]) -> dict[str, Any]:
    """Registration errors per frame; fills errors (T, N) mm, sigma (T, N) mm (the run's
    reported uncertainty) and has_data (T, N) (the point had a target) for later parts."""
    n_frames, n = errors.shape
    per_frame = []
    for k in range(1, n_frames):
        reg = read_registration(layout, k, n)
        err_m = registration_errors(mapping, gt.vertices[k], gt.faces, reg.registered)
        errors[k] = err_m * 1e3
        sigma[k] = reg.sigma * 1e3
        has_data[k] = np.isfinite(reg.target_sigma)
        per_frame.append({"frame": k, **error_summary(err_m)})
        step(k, n_frames)
    return {"overall": error_summary(errors[1:].astype(float) * 1e-3), "per_frame": per_frame}


def _honesty_part(result: dict[str, Any], labels: np.ndarray,
                  frames: tuple[np.ndarray, np.ndarray, np.ndarray], covered: np.ndarray
                  ) -> None:
    """Does the run know what it does not know? Over frames >= 1 (frames: errors (T, N) mm,
    sigma (T, N) mm, has_data (T, N) of `_registration_part`): the registration error of
    labelled points; the share of labelled points whose true error is within the reported
    2σ (calibration) and the factor 2σ would need to cover 95 % of them (`sigma_scale_95`,
    above 1 when σ understates the error), both over the points the truth covers (covered
    (N,): not mapped to the rim of a truth with holes, `on_mesh_rim`, whose error there is
    the truth's; `truth_covered_fraction`); the share unknown; labelled points with no data
    that are more than `UNSUPPORTED_MM` off (extrapolated and still labelled)."""
    errors, sigma, has_data = frames
    labelled = labels[1:] != UNKNOWN
    err, sig = errors[1:].astype(float), sigma[1:].astype(float)
    result["registration"]["labelled"] = error_summary(np.where(labelled, err, np.nan) * 1e-3)
    result["labels"]["truth_covered_fraction"] = float(np.mean(covered))
    checked = labelled & np.isfinite(err) & covered[None, :]
    within = (err <= 2.0 * sig)[checked]
    result["labels"]["calibration_2sigma"] = float(within.mean()) if within.size else None
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = (err / (2.0 * sig))[checked]
    result["labels"]["sigma_scale_95"] = (float(np.percentile(scale, 95))
                                          if within.size else None)
    result["labels"]["unknown_fraction"] = float((~labelled).mean()) if labelled.size else None
    result["registration"]["unsupported_moved"] = int(
        (labelled & ~has_data[1:] & (err > UNSUPPORTED_MM)).sum())


def _deformation_part(layout: RunLayout, gt: GroundTruth, log: IngestedLog, config: Config,
                      n_points: int) -> dict[str, Any]:
    """Contact and indentation scores (core/evaluate/deformation_scoring.py)."""
    measured = read_deformation(layout, (log.n_frames, n_points)).series
    poses = gt.tool_poses if gt.tool_poses is not None else log.tool_poses
    view = camera_viewpoint(log.poses[0], log.usable[0], gt.vertices[0])
    truth = true_deformation(gt.vertices, poses, view, config)
    part = score_deformation(measured, truth.series, gt.indentation_m)
    part["tool_poses"] = "ground truth" if gt.tool_poses is not None else "ingested"
    if not tool_known(log.tool_poses).any():  # no robot in the log: contact not measured
        part["goals"] = dict.fromkeys(part["goals"], NOT_MEASURED)
    return part


def _labels_part(labels: np.ndarray, truth: np.ndarray) -> dict[str, Any]:
    per_frame = [{"frame": k, **label_scores(labels[k], truth[k])} for k in range(1, len(labels))]
    overall = label_scores(labels[1:], truth[1:]) if len(labels) > 1 else None
    return {"frames": "1..", "overall": overall, "per_frame": per_frame}


def pipeline_step(ctx: StageContext, progress: Callable[[float], None]) -> None:
    """The stage within `surgrecon run` (only with ground truth)."""
    if ctx.ground_truth is not None:
        ctx.evaluation = run_evaluate(ctx.run_dir, ctx.config, ctx.ground_truth,
                                      on_step=lambda d, t: progress(d / t))
