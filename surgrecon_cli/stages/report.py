"""Stage `report`: per-frame metrics table, run summary and the HTML report.

Uses whatever stages are done and writes atomically
  RUN/metrics/frames.csv     one row per frame (FRAME_COLUMNS)
  RUN/metrics/summary.json   the run at a glance (counts, timings, template, evaluation)
  RUN/report.html            self-contained (figures embedded as PNG), readable offline
"""

from __future__ import annotations

import dataclasses
import logging
import re
from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime, timezone
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from .. import __version__
from ..config import Config, ToolConfig
from ..core.cameras import in_image, project
from ..core.labels import CLASS_NAMES, DEFORMING, SHIFTING, STATIC, STATUS_NAMES, UNKNOWN
from ..core.quality import FrameQuality, frame_quality
from ..core.tool import tool_pixel_mask
from ..errors import RunFolderError
from ..executors import Executor, Task
from ..executors.serial import SerialExecutor
from ..io import plots
from ..io import report_html as rh
from ..io.artefacts import (
    FrameRegistration,
    read_json,
    read_labels,
    read_registration,
    read_template,
)
from ..io.atomic import write_text
from ..io.ingest_store import IngestedLog, load_ingested
from ..io.metrics import finite_json, write_csv, write_metrics_json
from ..io.run_folder import RunFolder
from ..io.run_layout import DESCRIBED_FILES, RunLayout
from .common import stage_run
from .registry import StageContext

logger = logging.getLogger(__name__)

STAGE = "report"
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
_CODES = {"static": STATIC, "shifting": SHIFTING, "deforming": DEFORMING, "unknown": UNKNOWN}
_STAGE_ORDER = ("ingest", "build-template", "register", "classify", "evaluate")


@dataclass(frozen=True)
class ReportFiles:
    """Where the report stage wrote its outputs."""

    html: Path
    frames_csv: Path
    summary_json: Path


@dataclass
class _RunData:
    """Everything the report shows, gathered from the run folder (None = stage not done)."""

    run: dict[str, Any]
    log: IngestedLog
    template: np.ndarray | None = None
    template_summary: dict[str, Any] | None = None
    labels: np.ndarray | None = None          # (T, N)
    status: np.ndarray | None = None          # (T, N), frame 0 unused
    registered: np.ndarray | None = None      # (T, N, 3)
    residual_mm: list[np.ndarray] | None = None     # per frame, points with a target
    displacement_mm: np.ndarray | None = None  # (T, N)
    seconds: np.ndarray | None = None          # (T, 2) target, register
    evaluation: dict[str, Any] | None = None
    errors: dict[str, np.ndarray] | None = None
    quality: list[FrameQuality] | None = None  # frames >= 1
    noise: dict[str, Any] | None = None        # the run's measured noise figures


def run_report(run_dir: Path, config: Config,
               on_step: Callable[[int, int], None] | None = None,
               executor: Executor | None = None) -> ReportFiles:
    """Write frames.csv, summary.json and report.html for a run (any stages done); the
    figures are drawn as tasks on `executor` (default: serial)."""
    run_dir = Path(run_dir)
    layout = RunLayout(run_dir)
    step = on_step or (lambda _d, _t: None)
    with stage_run(run_dir, STAGE, config) as info:
        data = _gather(run_dir)
        step(1, 4)
        rows = frame_rows(data)
        files = ReportFiles(layout.report_html, layout.frames_csv, layout.summary_json)
        write_csv(files.frames_csv, FRAME_COLUMNS, rows)
        summary = _summary(data, rows, config)
        write_metrics_json(files.summary_json, summary)
        step(2, 4)
        figs = _Figures()
        markup = _html(run_dir, data, rows, summary, config, figs)
        step(3, 4)
        write_text(files.html, figs.fill(markup, executor or SerialExecutor()))
        step(4, 4)
        info.update(html=str(files.html), frames=data.log.n_frames)
    return files


# ----------------------------------------------------------------------------- gathering
def _gather(run_dir: Path) -> _RunData:
    layout = RunLayout(run_dir)
    run = RunFolder(run_dir)
    data = _RunData(run=run.read(), log=load_ingested(layout.ingest_dir))
    n_frames = data.log.n_frames
    if run.is_done("build-template"):
        data.template = read_template(layout).points
        if layout.template_summary.is_file():
            data.template_summary = read_json(layout.template_summary, "build-template")
    if data.template is None:
        return data
    n = len(data.template)
    if run.is_done("register"):
        registered = np.full((n_frames, n, 3), np.nan)
        registered[0] = data.template
        status = np.zeros((n_frames, n), np.uint8)
        seconds = np.full((n_frames, 2), np.nan)
        residual = [np.zeros(0)]
        frames_reg = []
        for k in range(1, n_frames):
            reg = read_registration(layout, k, n)
            frames_reg.append(reg)
            registered[k] = reg.registered
            status[k] = reg.status
            residual.append(reg.residual[reg.has_target].astype(float) * 1e3)
            seconds[k] = [reg.seconds_target, reg.seconds_register]
        data.registered, data.status, data.seconds, data.residual_mm = (
            registered, status, seconds, residual)
        data.displacement_mm = np.linalg.norm(registered - data.template, axis=2) * 1e3
    if run.is_done("classify"):
        data.labels = read_labels(layout, (n_frames, n)).labels
    if run.is_done("register"):
        data.quality = [
            frame_quality(k, reg.status, None if data.labels is None else data.labels[k],
                          reg.sigma.astype(float), reg.residual.astype(float),
                          reg.target_sigma.astype(float), reg.failed, reg.converged, reg.error)
            for k, reg in enumerate(frames_reg, start=1)]
        data.noise = _noise_figures(data.log, data.template_summary, frames_reg)
    if run.is_done("evaluate") and layout.evaluation_json.is_file():
        data.evaluation = read_json(layout.evaluation_json, "evaluate")
        if layout.evaluation_errors.is_file():
            with np.load(layout.evaluation_errors, allow_pickle=False) as z:
                data.errors = {k: z[k] for k in z.files}
    return data


def _noise_figures(log: IngestedLog, template_summary: dict[str, Any] | None,
                   frames: list[FrameRegistration]) -> dict[str, Any]:
    """The run's measured noise: pixel noise (template), tracker jitter per camera (ingest),
    tracking noise (median over frames) and the median template σ."""
    stats = (template_summary or {}).get("stats", {})
    cams = log.report.get("cameras", {})
    tracking = [f.tracking_px for f in frames if np.isfinite(f.tracking_px)]
    return {
        "pixel_px": stats.get("pixel_noise_px"),
        "tracking_px": float(np.median(tracking)) if tracking else None,
        "tracker_jitter_mm": {c: r.get("tracker_jitter_mm") for c, r in cams.items()},
        "tracker_jitter_deg": {c: r.get("tracker_jitter_deg") for c, r in cams.items()},
    }


def _stats(values: np.ndarray) -> tuple[float, float, float]:
    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    if not v.size:
        return float("nan"), float("nan"), float("nan")
    return float(np.median(v)), float(np.percentile(v, 95)), float(v.max())


def frame_rows(data: _RunData) -> list[dict[str, Any]]:
    """One dict per frame with the FRAME_COLUMNS (missing parts are None)."""
    log = data.log
    t0 = log.stamps_ns[0] if log.n_frames else 0
    reg_eval = {}
    label_eval = {}
    if data.evaluation:
        reg_eval = {r["frame"]: r for r in (data.evaluation.get("registration") or {})
                    .get("per_frame", [])}
        label_eval = {r["frame"]: r for r in (data.evaluation.get("labels") or {})
                      .get("per_frame", [])}
    rows = []
    for k in range(log.n_frames):
        row: dict[str, Any] = {"frame": k, "time_s": round(float(log.stamps_ns[k] - t0) / 1e9, 6)}
        if data.template is not None:
            row["points"] = len(data.template)
        if data.labels is not None:
            for name in CLASS_COLUMNS:
                row[name] = int((data.labels[k] == _CODES[name]).sum())
        if data.status is not None and k > 0:
            for code, name in STATUS_NAMES.items():
                row[name] = int((data.status[k] == code).sum())
            row["residual_median_mm"], row["residual_p95_mm"], _ = _stats(data.residual_mm[k])
            row["seconds_target"], row["seconds_register"] = (float(x) for x in data.seconds[k])
        if data.displacement_mm is not None:
            (row["displacement_median_mm"], row["displacement_p95_mm"],
             row["displacement_max_mm"]) = _stats(data.displacement_mm[k])
        if k in reg_eval:
            e = reg_eval[k]
            row["error_median_mm"], row["error_p95_mm"], row["error_max_mm"] = (
                e.get("median_mm"), e.get("p95_mm"), e.get("max_mm"))
        if k in label_eval:
            row["macro_f1"] = label_eval[k].get("macro_f1")
        if data.quality is not None and k > 0:
            row.update({key: value for key, value in data.quality[k - 1].row().items()
                        if key != "frame"})
        rows.append(row)
    return rows


def _stage_seconds(run: dict[str, Any]) -> dict[str, float]:
    stages = run.get("stages", {})
    piped = run.get("pipeline", {}).get("seconds", {})
    out = {}
    for name in (*_STAGE_ORDER, STAGE):
        seconds = stages.get(name, {}).get("seconds", piped.get(name))
        if seconds is not None and name != STAGE:
            out[name] = float(seconds)
    return out


def _summary(data: _RunData, rows: list[dict[str, Any]], config: Config) -> dict[str, Any]:
    run, log = data.run, data.log
    later = rows[1:]
    summary: dict[str, Any] = {
        "surgrecon": __version__,
        "input": run.get("input", {}),
        "frames": log.n_frames,
        "cameras": list(log.cameras),
        "template_points": None if data.template is None else len(data.template),
        "stages": {k: v.get("status") for k, v in run.get("stages", {}).items()},
        "seconds": _stage_seconds(run),
    }
    if data.template_summary:
        summary["camera_pairs"] = data.template_summary.get("pairs", {})
        summary["template"] = data.template_summary.get("stats", {})
    if data.labels is not None:
        counts = {name: int(sum(r[name] for r in later)) for name in CLASS_COLUMNS}
        total = max(sum(counts.values()), 1)
        summary["classes_frames_1_on"] = {
            "counts": counts, "fractions": {k: v / total for k, v in counts.items()}}
    if data.status is not None and log.n_frames > 1:
        summary["status_frames_1_on"] = {name: int(sum(r[name] for r in later))
                                         for name in STATUS_COLUMNS}
        med, p95, mx = _stats(np.concatenate(data.residual_mm[1:]))
        summary["residual_mm"] = {"median": med, "p95": p95, "max": mx}
        med, p95, mx = _stats(data.displacement_mm[1:])
        summary["displacement_mm"] = {"median": med, "p95": p95, "max": mx}
        summary["seconds_per_frame"] = {
            "target_mean": float(np.nanmean(data.seconds[1:, 0])),
            "register_mean": float(np.nanmean(data.seconds[1:, 1]))}
    if data.evaluation:
        ev = data.evaluation
        summary["evaluation"] = {
            "template_error_mm": ev["template"]["error"],
            "template_on_tool": ev["template"].get("on_tool"),
            "registration_error_mm": (ev.get("registration") or {}).get("overall"),
            "macro_f1": ((ev.get("labels") or {}).get("overall") or {}).get("macro_f1"),
        }
    if data.quality is not None:
        summary["noise"] = data.noise
        summary["quality"] = {
            "per_frame": [q.row() for q in data.quality],
            "warnings": [w for q in data.quality for w in q.warnings],
            "untrustworthy_frames": [q.frame for q in data.quality if q.warnings],
        }
    summary["classify"] = {"static_mm": config.classify.static_mm,
                           "significance": config.classify.significance,
                           "max_sigma_mm": config.classify.max_sigma_mm,
                           "deform_mm": config.classify.deform_mm,
                           "measure": config.classify.measure}
    return finite_json(summary)


# ----------------------------------------------------------------------------- HTML
class _Figures:
    """The report's figures, drawn together as tasks on an executor (matplotlib is most of
    the stage's time): `add` keeps a figure's drawing call and returns a placeholder block,
    `fill` draws them all and puts each figure in place of its placeholder."""

    def __init__(self) -> None:
        self._draws: list[Callable[[], bytes]] = []
        self._captions: list[str] = []

    def add(self, draw: Callable[[], bytes], caption: str) -> str:
        """draw: a picklable call returning PNG bytes, e.g. partial(plots.histogram, ...)."""
        self._draws.append(draw)
        self._captions.append(caption)
        return self._placeholder(len(self._draws) - 1)

    @staticmethod
    def _placeholder(index: int) -> str:
        # A comment cannot come from the report's text: every text block is escaped.
        return f"<!--figure {index}-->"

    def fill(self, markup: str, executor: Executor) -> str:
        pngs = executor.run([Task(f"figure-{i}", draw) for i, draw in enumerate(self._draws)])
        placed: list[int] = []

        def figure(match: re.Match[str]) -> str:
            i = int(match.group(1))
            placed.append(i)
            return rh.figure(pngs[f"figure-{i}"], self._captions[i])

        markup = re.sub(r"<!--figure (\d+)-->", figure, markup)
        if sorted(placed) != list(range(len(self._draws))):  # a bug in _html, not the input
            raise AssertionError(f"report figures placed {sorted(placed)}, drawn "
                                 f"{len(self._draws)}")
        return markup


def _col(rows: list[dict[str, Any]], key: str, frames: range | None = None) -> np.ndarray:
    sel = rows if frames is None else [rows[k] for k in frames]
    return np.array([np.nan if r.get(key) is None else r[key] for r in sel], float)


def _pick_frames(data: _RunData) -> list[int]:
    """Frames worth rendering: 0, the most deforming, the most shifting, the last."""
    n_frames = data.log.n_frames
    picks = {0, n_frames - 1}
    if data.labels is not None and n_frames > 1:
        for code in (DEFORMING, SHIFTING):
            counts = (data.labels == code).sum(1)
            if counts.max() > 0:
                picks.add(int(np.argmax(counts)))
    return sorted(picks)[:4]


def _best_camera(data: _RunData, frame: int, xyz: np.ndarray,
                 tool: ToolConfig) -> tuple[int, np.ndarray] | None:
    """The usable camera seeing most points at `frame`, with their pixels (N, 2) (NaN if not
    in the image, or hidden by the tool)."""
    log = data.log
    best: tuple[int, np.ndarray] | None = None
    best_count = 0
    tool_pose = log.tool_poses[frame]
    for c, model in enumerate(log.models):
        if not log.usable[frame, c]:
            continue
        uv, z = project(np.nan_to_num(xyz), log.poses[frame, c], model)
        ok = (z > 0) & in_image(uv, model) & np.isfinite(xyz).all(1)
        ok[ok] &= ~tool_pixel_mask(uv[ok], model, log.poses[frame, c], tool_pose,
                                   dataclasses.replace(tool, mask_margin_px=0.0))
        if ok.sum() > best_count:
            best_count = int(ok.sum())
            best = (c, np.where(ok[:, None], uv, np.nan))
    return best


def _cloud_views(data: _RunData, tool: ToolConfig, figs: _Figures) -> list[str]:
    blocks = []
    frames = _pick_frames(data)
    labels = data.labels
    for k in frames:
        if data.registered is not None:
            xyz = data.registered[k]
        elif k == 0 and data.template is not None:
            xyz = data.template
        else:
            continue
        lab = labels[k] if labels is not None else np.full(len(xyz), UNKNOWN, np.uint8)
        cam = _best_camera(data, k, xyz, tool)
        image, uv, cam_name = None, None, ""
        if cam is not None:
            try:
                image = data.log.load_image(k, cam[0])
                uv, cam_name = cam[1], data.log.cameras[cam[0]]
            except RunFolderError:
                image = None
        counts = ", ".join(f"{n} {int((lab == c).sum())}" for c, n in CLASS_NAMES.items())
        title = f"frame {k}" + (f" ({counts})" if labels is not None else "")
        draw = partial(plots.labelled_views, title, image, uv, xyz, lab, CLASS_NAMES)
        blocks.append(figs.add(draw, f"Frame {k}: registered cloud coloured by class, projected "
                                     f"into camera {cam_name}'s image (left; points behind the "
                                     "tool hidden) and in 3D (right)."
                                if image is not None else f"Frame {k}: registered cloud."))
    return blocks


def _quality_section(data: _RunData, frames_later: np.ndarray, figs: _Figures) -> rh.Section:
    """Per frame: what the data support (shares observed / unknown), the median σ and the
    residual against the noise, with the frames not to trust named in plain words."""
    quality = data.quality or []
    sec = rh.Section("quality", "Quality (no ground truth needed)")
    noise = data.noise or {}
    jitter = [v for v in (noise.get("tracker_jitter_mm") or {}).values() if v is not None]
    jitter_deg = [v for v in (noise.get("tracker_jitter_deg") or {}).values() if v is not None]
    bodies = data.log.report.get("tracker_bodies", [])
    sec.add(rh.table(("measured noise (1σ per axis)", "value"), [
        ("pixel noise at frame 0 (template residuals)", _fmt_num(noise.get("pixel_px"), "px")),
        ("tracker position jitter (median over cameras)",
         _fmt_num(float(np.median(jitter)) if jitter else None, "mm")),
        ("tracker rotation jitter (median over cameras)",
         _fmt_num(float(np.median(jitter_deg)) if jitter_deg else None, "°")),
        ("tracking noise (Cramér-Rao bound of each tracked patch, median over frames)",
         _fmt_num(noise.get("tracking_px"), "px")),
        ("cameras sharing one tracked body (pose error rigid for the group)",
         "; ".join(", ".join(g) for g in bodies) or "none"),
    ]))
    series = {
        "observed": np.array([q.observed for q in quality]),
        "unknown": np.array([q.unknown for q in quality]),
        "outlier": np.array([q.outlier for q in quality]),
    }
    sec.add(figs.add(partial(plots.quality_over_time, frames_later, series,
                             np.array([q.sigma_median_mm for q in quality]),
                             np.array([q.residual_over_sigma for q in quality])),
                     "Left: share of template points observed in the frame, labelled unknown "
                     "(too far from data) and rejected as outliers. Right: median uncertainty σ "
                     "of the labelled points, and the median registration residual in units "
                     "of the target's σ (about 1 when the fit is as good as the noise allows)."))
    warnings = [w for q in quality for w in q.warnings]
    if warnings:
        sec.add(rh.paragraph("Frames not to trust: " + "; ".join(warnings) + "."))
    else:
        sec.add(rh.paragraph("Every frame is supported by data and fits within its noise.",
                             note=True))
    return sec


def _fmt_num(value: Any, unit: str) -> str:
    return "–" if value is None or not np.isfinite(value) else f"{value:.3g} {unit}"


def _fmt_mm(value: Any) -> str:
    return "–" if value is None else f"{value:.2f} mm"


def _html(run_dir: Path, data: _RunData, rows: list[dict[str, Any]], summary: dict[str, Any],
          config: Config, figs: _Figures) -> str:
    """The report's HTML, with a placeholder for each figure added to `figs`."""
    log = data.log
    frames_all = np.arange(log.n_frames)
    later = range(1, log.n_frames)
    frames_later = np.arange(1, log.n_frames)
    sections: list[rh.Section] = []

    # --- overview
    overview = rh.Section("overview", "Overview")
    items = [("frames", str(log.n_frames), ""), ("cameras", str(len(log.cameras)), "")]
    if data.template is not None:
        items.append(("template points", f"{len(data.template):,}", ""))
    fractions = summary.get("classes_frames_1_on", {}).get("fractions")
    if fractions:
        items.append(("moving (frames 1..)",
                      f"{fractions['shifting'] + fractions['deforming']:.1%}", ""))
    ev = summary.get("evaluation")
    if ev and ev.get("registration_error_mm"):
        med = ev["registration_error_mm"]["median_mm"]
        items.append(("median registration error", _fmt_mm(med),
                      "good" if med is not None and med <= 1.0 else "bad"))
    if ev and ev.get("macro_f1") is not None:
        items.append(("label macro-F1", f"{ev['macro_f1']:.3f}", ""))
    overview.add(rh.tiles(items))
    inp = data.run.get("input", {})
    stage_rows = [(name, entry.get("status"), entry.get("seconds"))
                  for name, entry in data.run.get("stages", {}).items() if name != STAGE]
    overview.add(rh.table(("input", ""), [
        ("log", inp.get("path")), ("SHA-256", (inp.get("sha256") or "")[:16] + "…"),
        ("size", f"{(inp.get('bytes') or 0) / 1e6:.1f} MB"),
        ("duration", f"{rows[-1]['time_s']:.2f} s" if rows else "–"),
        ("surgrecon", __version__)]))
    overview.add(rh.table(("stage", "status", "seconds"), stage_rows))
    sections.append(overview)

    # --- cameras and template
    cams = rh.Section("cameras", "Cameras and template")
    pairs = (data.template_summary or {}).get("pairs", {})
    groups, sequences = pairs.get("groups", []), pairs.get("sequence", [])
    if data.template is not None:
        centres = log.poses[0, :, :3, 3]
        axes = log.poses[0, :, :3, 2]
        cams.add(figs.add(partial(plots.camera_layout, data.template, centres, axes,
                                  log.cameras, groups, sequences),
                           "Camera positions at frame 0 over the template (grey). Lines: pairs "
                           "matched when building the template, numbered in matching order; "
                           "one colour per camera group."))
    for g, group in enumerate(groups):
        seq = sequences[g] if g < len(sequences) else []
        cams.add(rh.paragraph(f"Group {g + 1}: cameras {', '.join(group)}; pair sequence "
                              + (" → ".join(f"{a}-{b}" for a, b in seq) or "none")))
    cam_report = log.report.get("cameras", {})
    if cam_report:
        cams.add(rh.table(("camera", "images", "frames", "dropped", "late", "pose gaps", "usable",
                           "image Hz", "tracker Hz"),
                          [(cid, r.get("images"), r.get("frames"), r.get("dropped"), r.get("late"),
                            r.get("pose_gaps"), r.get("usable"), r.get("image_rate_hz"),
                            r.get("tracker_rate_hz")) for cid, r in cam_report.items()]))
    stats = (data.template_summary or {}).get("stats", {})
    if stats:
        cams.add(rh.paragraph(
            f"Template: {stats.get('points')} points from {stats.get('tracks')} feature tracks; "
            f"{stats.get('verified_pairs')} of {stats.get('candidate_pairs')} candidate pairs "
            f"verified; {stats.get('rejected_geometry')} rejected by reprojection/angle, "
            f"{stats.get('removed_off_surface')} off the surface, {stats.get('removed_tool')} "
            f"on the tool.", note=True))
    if not log.report.get("robot", True):
        cams.add(rh.paragraph(
            "No robot kinematics in this log (topics.tool_pose = \"\"): tool removal is off, "
            "so points on the tool are kept and may be labelled as tissue.", note=True))
    sections.append(cams)

    # --- quality without ground truth
    if data.quality is not None and log.n_frames > 1:
        sections.append(_quality_section(data, frames_later, figs))

    # --- labels over time
    if data.labels is not None or data.status is not None:
        lab = rh.Section("labels", "Labels over time")
        if data.labels is not None:
            counts = {n: _col(rows, n) for n in CLASS_COLUMNS}
            lab.add(figs.add(partial(plots.stacked_counts, frames_all, counts,
                                     plots.CLASS_COLOURS, "points per class"),
                              f"Static: registered displacement below {config.classify.static_mm:g}"
                              f" mm; deforming: neighbourhood ({config.classify.neighbourhood_mm:g}"
                              f" mm) {config.classify.measure} at or above "
                              f"{config.classify.deform_mm:g} mm; shifting otherwise."))
        if data.status is not None and log.n_frames > 1:
            counts = {n: _col(rows, n, later) for n in STATUS_COLUMNS}
            lab.add(figs.add(partial(plots.stacked_counts, frames_later, counts,
                                     plots.STATUS_COLOURS, "reprojection-error check"),
                              "Intra-camera inliers (frame-0 position still reprojects: static "
                              "evidence), inter-camera inliers (re-triangulated: dynamic), "
                              "outliers, and points not visible."))
        sections.append(lab)

    # --- labelled clouds
    views = _cloud_views(data, config.tool, figs)
    if views:
        sections.append(rh.Section("clouds", "Labelled clouds").add(*views))

    # --- registration
    if data.status is not None and log.n_frames > 1:
        reg = rh.Section("registration", "Registration")
        reg.add(figs.add(partial(plots.per_frame_boxes,
            frames_later, [data.displacement_mm[k] for k in later], "displacement from frame 0",
            "mm", lines={f"static below {config.classify.static_mm:g} mm":
                         config.classify.static_mm}),
            "Registered displacement ‖T_i p_i − p_i‖ per frame (boxes: quartiles, whiskers: "
            "5–95 %)."))
        reg.add(figs.add(partial(plots.per_frame_boxes,
            frames_later, [data.residual_mm[k] for k in later], "data residual", "mm"),
            "Distance of each point with a target (intra/inter-camera inlier) to its target "
            "after registration."))
        sections.append(reg)

    # --- timing
    stage_seconds = _stage_seconds(data.run)
    if stage_seconds:
        timing = rh.Section("timing", "Timing")
        per_frame = {}
        if data.seconds is not None and log.n_frames > 1:
            per_frame = {"target cloud": data.seconds[1:, 0], "registration": data.seconds[1:, 1]}
        early = data.run.get("stages", {}).get("classify", {}).get("classified_with_register")
        note = (f" {early} frames were classified as they were registered: their time counts "
                "under register." if early else "")
        timing.add(figs.add(partial(plots.timing, stage_seconds, frames_later, per_frame),
                            "Wall time of each stage (left) and of target-cloud building and "
                            "non-rigid registration per frame (right)." + note))
        sections.append(timing)

    # --- evaluation
    if data.evaluation:
        sections.append(_evaluation_section(data, frames_later, figs))

    files = rh.Section("files", "Files")
    layout = RunLayout(run_dir)
    files.add(rh.table(("file", "contents"), [
        (layout.relative(getattr(layout, name)), what) for name, what in DESCRIBED_FILES]))
    sections.append(files)

    created = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    subtitle = (f"{Path(str(inp.get('path', ''))).name} · {log.n_frames} frames · "
                f"{len(log.cameras)} cameras · {run_dir.name}")
    return rh.render("surgrecon run report", subtitle, sections,
                     footer=f"surgrecon {__version__} · generated {created} · Su, Huang & "
                            "Hannaford, IROS 2019")


def _evaluation_section(data: _RunData, frames_later: np.ndarray,
                        figs: _Figures) -> rh.Section:
    ev = data.evaluation or {}
    sec = rh.Section("evaluation", "Evaluation against ground truth")
    tpl = ev["template"]
    items = [("template error (median)", _fmt_mm(tpl["error"].get("median_mm")), ""),
             ("template error (p95)", _fmt_mm(tpl["error"].get("p95_mm")), "")]
    if tpl.get("on_tool") is not None:
        items.append(("template points on the tool", str(tpl["on_tool"]["count"]),
                      "good" if tpl["on_tool"]["count"] == 0 else "bad"))
    reg = ev.get("registration")
    if reg:
        o = reg["overall"]
        items.append(("registration error (p95)", _fmt_mm(o.get("p95_mm")), ""))
        if o.get("within_1mm") is not None:
            items.append(("within 1 mm", f"{o['within_1mm']:.1%}",
                          "good" if o["within_1mm"] >= 0.95 else "bad"))
    sec.add(rh.tiles(items))
    sec.add(rh.paragraph(
        "Each template point is mapped to the nearest point of the true surface at frame 0 and "
        "that material point is followed through the frames; its true label is that of the "
        "nearest true vertex.", note=True))
    errors = data.errors or {}
    if "template_error_mm" in errors:
        tool = errors.get("on_tool", np.zeros(len(errors["template_error_mm"]), bool)).astype(bool)
        by = {"on the surface": ~tool, "on the tool": tool} if tool.any() else None
        sec.add(figs.add(partial(plots.histogram,
            errors["template_error_mm"], "template error", "distance to the true surface (mm)",
            lines={"1 mm": 1.0}, by=by,
            colours={"on the surface": "#4C78A8", "on the tool": "#D1495B"}),
            "Distance of every template point to the true frame-0 surface."))
    if reg and reg["per_frame"]:
        pf = reg["per_frame"]
        frames = np.array([r["frame"] for r in pf])

        def get(key: str, pf: list[dict[str, Any]] = pf) -> np.ndarray:
            return np.array([np.nan if r.get(key) is None else r[key] for r in pf])

        sec.add(figs.add(partial(plots.error_over_time, frames, get("median_mm"),
                                 get("p95_mm"), get("max_mm")),
                          "Registration error: registered position vs. the followed material "
                          "point, all template points."))
        if "registration_error_mm" in errors:
            err = errors["registration_error_mm"]
            sec.add(figs.add(partial(plots.error_histograms, frames_later,
                                     [err[k] for k in frames_later]),
                              "Distribution of the registration error in each frame (dashed: "
                              "1 mm)."))
        sec.add(rh.table(("frame", "median mm", "p95 mm", "max mm", "within 1 mm"),
                         [(r["frame"], r.get("median_mm"), r.get("p95_mm"), r.get("max_mm"),
                           None if r.get("within_1mm") is None else f"{r['within_1mm']:.1%}")
                          for r in pf]))
    labels = ev.get("labels")
    if labels and labels.get("overall"):
        o = labels["overall"]
        axes = o["confusion_axes"]
        score_rows = [(name, s["precision"], s["recall"], s["f1"], s["support"])
                      for name, s in o["per_class"].items()]
        score_rows.append(("macro-F1", None, None, o["macro_f1"], None))
        sec.add(rh.grid(
            figs.add(partial(plots.confusion, np.array(o["confusion"]), axes["rows"],
                             axes["cols"]),
                     "Rows: truth; columns: predicted (unknown = no label)."),
            rh.table(("class", "precision", "recall", "F1", "support"), score_rows)))
        pf = labels["per_frame"]
        if pf:
            frames = np.array([r["frame"] for r in pf])
            per_class = {name: np.array([r["per_class"][name]["f1"]
                                         if r["per_class"][name]["support"] else np.nan
                                         for r in pf]) for name in CLASS_NAMES.values()}
            macro = np.array([np.nan if r["macro_f1"] is None else r["macro_f1"] for r in pf])
            sec.add(figs.add(partial(plots.f1_over_time, frames, per_class, macro),
                              "F1 per class and frame (gaps: the class is absent in that "
                              "frame's truth)."))
    return sec


def pipeline_step(ctx: StageContext, progress: Callable[[float], None]) -> None:
    """The stage within `surgrecon run`."""
    run_report(ctx.run_dir, ctx.config, on_step=lambda d, t: progress(d / t),
               executor=ctx.executor)
