"""Stage `evaluate`: score a run against the simulator's ground truth (SPEC section 6).

Scores whatever parts the run has: the template (always), the registration (when `register`
is done) and the labels (when `classify` is done). Ground-truth frame k is the k-th
ingested frame. Writes atomically
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
from ..core.evaluation import error_summary, on_tool, registration_errors, true_point_labels
from ..core.scoring import distance_stats_mm, label_scores, map_to_surface
from ..errors import InputError, RunFolderError
from ..io.atomic import write_npz
from ..io.ground_truth import GroundTruth, load_ground_truth
from ..io.ingest_store import load_ingested
from ..io.metrics import finite_json, write_metrics_json
from ..io.run_folder import RunFolder
from .classify import labels_path, load_registration_frame
from .common import stage_run
from .register import load_template

logger = logging.getLogger(__name__)

STAGE = "evaluate"


def evaluation_path(run_dir: Path) -> Path:
    return Path(run_dir) / "metrics" / "evaluation.json"


def errors_path(run_dir: Path) -> Path:
    return Path(run_dir) / "metrics" / "evaluation_errors.npz"


def run_evaluate(run_dir: Path, config: Config, gt_path: Path,
                 on_step: Callable[[int, int], None] | None = None) -> dict[str, Any]:
    """Evaluate the run against `gt_path`; returns the evaluation (as written to JSON).

    `on_step(done, total)` reports progress over the frames."""
    run_dir = Path(run_dir)
    run = RunFolder(run_dir)
    step = on_step or (lambda _d, _t: None)
    with stage_run(run_dir, STAGE, config, needs=("ingest", "build-template")) as info:
        gt = load_ground_truth(gt_path)
        log = load_ingested(run_dir / "ingest")
        if gt.n_frames != log.n_frames:
            raise InputError(
                f"{gt.path} has {gt.n_frames} frames but {run_dir} ingested {log.n_frames}; "
                "ground-truth frame k must be the k-th ingested frame (wrong file, or a "
                "truncated log?)")
        template, _ = load_template(run_dir)
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
        }
        n_frames, n = log.n_frames, len(template)
        errors = np.full((n_frames, n), np.nan, np.float32)
        truth = true_point_labels(mapping, gt.faces, gt.labels).astype(np.uint8)
        if run.is_done("register"):
            result["registration"] = _registration_part(run_dir, gt, mapping, errors, step)
        if run.is_done("classify"):
            result["labels"] = _labels_part(run_dir, truth)
        write_npz(errors_path(run_dir),
                  template_error_mm=(mapping.distance * 1e3).astype(np.float32),
                  on_tool=np.zeros(n, bool) if tool_mask is None else tool_mask,
                  registration_error_mm=errors, true_labels=truth)
        result = finite_json(result)
        write_metrics_json(evaluation_path(run_dir), result)
        step(n_frames, n_frames)
        info.update(ground_truth=result["ground_truth"],
                    parts=[p for p in ("template", "registration", "labels") if result[p]])
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
                           "shaft_radius_mm": config.tool.shaft_radius * 1e3}
        part["error_off_tool"] = distance_stats_mm(distance_m[~tool_mask])
    return part


def _registration_part(run_dir: Path, gt: GroundTruth, mapping: Any, errors: np.ndarray,
                       step: Callable[[int, int], None]) -> dict[str, Any]:
    n_frames, n = errors.shape
    per_frame = []
    for k in range(1, n_frames):
        reg = load_registration_frame(run_dir, k, n)
        err_m = registration_errors(mapping, gt.vertices[k], gt.faces, reg["registered"])
        errors[k] = err_m * 1e3
        per_frame.append({"frame": k, **error_summary(err_m)})
        step(k, n_frames)
    return {"overall": error_summary(errors[1:].astype(float) * 1e-3), "per_frame": per_frame}


def _labels_part(run_dir: Path, truth: np.ndarray) -> dict[str, Any]:
    path = labels_path(run_dir)
    try:
        with np.load(path, allow_pickle=False) as z:
            labels = z["labels"]
    except (OSError, KeyError, ValueError) as exc:
        raise RunFolderError(f"{path}: unreadable ({exc}); re-run classify") from exc
    if labels.shape != truth.shape:
        raise RunFolderError(f"{path}: labels {labels.shape} do not match the run "
                             f"{truth.shape}; re-run classify")
    per_frame = [{"frame": k, **label_scores(labels[k], truth[k])} for k in range(1, len(labels))]
    overall = label_scores(labels[1:], truth[1:]) if len(labels) > 1 else None
    return {"frames": "1..", "overall": overall, "per_frame": per_frame}
