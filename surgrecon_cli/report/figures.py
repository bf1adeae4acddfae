"""Report layer 3: the figures, drawn before the page is written, as tasks on an executor
(matplotlib is most of the stage's time); report/plots.py draws.

`figure_tasks` decides which figures the run has, each a picklable call keyed by its name;
`draw_figures` runs them and returns {name: PNG bytes} for the page (report/page.py) to place.
"""

from __future__ import annotations

from functools import partial
from typing import Any

import numpy as np

from ..config import Config
from ..core.classify.labels import CLASS_COLOURS, CLASS_NAMES, STATUS_COLOURS, UNKNOWN
from ..core.measure.indentation import tool_known
from ..executors import Executor, Task
from . import plots
from .gather import CloudView, RunData
from .metrics import CLASS_COLUMNS, STATUS_COLUMNS, Metrics, stage_seconds


def cloud_key(frame: int) -> str:
    """The name of frame `frame`'s labelled-cloud figure."""
    return f"cloud-{frame}"


def draw_figures(data: RunData, metrics: Metrics, views: list[CloudView], config: Config,
                 executor: Executor) -> dict[str, bytes]:
    """Every figure of the run drawn on `executor`: {name: PNG bytes}."""
    return executor.run(figure_tasks(data, metrics, views, config))


def figure_tasks(data: RunData, metrics: Metrics, views: list[CloudView],
                 config: Config) -> list[Task]:
    """One task per figure the run's data allow, in page order."""
    log, rows, frames = data.log, metrics.rows, data.frames
    frames_later = np.arange(1, log.n_frames)
    later = range(1, log.n_frames)
    tasks: list[Task] = []
    if data.template is not None:
        pairs = (data.template_summary or {}).get("pairs", {})
        tasks.append(Task("camera-layout", partial(
            plots.camera_layout, data.template, log.poses[0, :, :3, 3], log.poses[0, :, :3, 2],
            log.cameras, pairs.get("groups", []), pairs.get("sequence", []))))
    if frames is not None and log.n_frames > 1:
        q = frames.quality
        series = {"observed": np.array([x.observed for x in q]),
                  "unknown": np.array([x.unknown for x in q]),
                  "outlier": np.array([x.outlier for x in q])}
        tasks.append(Task("quality", partial(
            plots.quality_over_time, frames_later, series,
            np.array([x.sigma_median_mm for x in q]),
            np.array([x.residual_over_sigma for x in q]))))
    if data.class_counts is not None:
        counts = {n: _col(rows, n) for n in CLASS_COLUMNS}
        tasks.append(Task("class-counts", partial(
            plots.stacked_counts, np.arange(log.n_frames), counts, CLASS_COLOURS,
            "points per class")))
    if frames is not None and log.n_frames > 1:
        counts = {n: _col(rows, n, later) for n in STATUS_COLUMNS}
        tasks.append(Task("status-counts", partial(
            plots.stacked_counts, frames_later, counts, STATUS_COLOURS,
            "reprojection-error check")))
    tasks.extend(Task(cloud_key(v.frame), _cloud_view(v)) for v in views)
    if frames is not None and log.n_frames > 1:
        static_mm = config.classify.static_mm
        tasks.append(Task("displacement", partial(
            plots.per_frame_boxes, frames.sampled, frames.displacement_sampled,
            "displacement from frame 0", "mm",
            lines={f"static below {static_mm:g} mm": static_mm})))
        tasks.append(Task("residual", partial(
            plots.per_frame_boxes, frames.sampled, frames.residual_sampled,
            "data residual", "mm")))
        if frames.floor_sampled is not None and any(f.size for f in frames.floor_sampled):
            deform_mm = config.classify.deform_mm
            tasks.append(Task("deform-floor", partial(
                plots.per_frame_boxes, frames.sampled, frames.floor_sampled,
                "deformation floor: the rigid-fit RMS a bend along the lines of sight needs",
                "mm", lines={f"deform_mm {deform_mm:g} mm": deform_mm})))
    if data.deformation is not None and tool_known(log.tool_poses).any():
        tasks.extend(deformation_tasks(data, config))  # none without a tool pose: unmeasured
    seconds = stage_seconds(data.run)
    if seconds:
        per_frame = {}
        if frames is not None and log.n_frames > 1:
            per_frame = {"target cloud": frames.seconds[1:, 0],
                         "registration": frames.seconds[1:, 1]}
        tasks.append(Task("timing", partial(plots.timing, seconds, frames_later, per_frame)))
    if data.evaluation:
        tasks.extend(_evaluation_tasks(data.evaluation, data.errors or {},
                                       np.zeros(0, int) if frames is None else frames.sampled))
    return tasks


def deformation_tasks(data: RunData, config: Config) -> list[Task]:
    """Indentation, area (and force) over time; the displacement map of the deepest frame."""
    assert data.deformation is not None and data.template is not None
    series = data.deformation
    frames = np.arange(series.n_frames)
    known = tool_known(data.log.tool_poses)  # frames with the tool pose: the others unmeasured
    area_mm2 = np.where(known, series.area_mm2, np.nan)
    scores = (data.evaluation or {}).get("deformation") or {}
    truth = {key: np.array([np.nan if r[f"true_{key}"] is None else r[f"true_{key}"]
                            for r in scores["per_frame"]]) for key in ("indentation_mm",
                                                                       "area_mm2")
             } if scores.get("per_frame") else {}
    d = config.deformation
    force = series.force_n if d.youngs_modulus_kpa > 0 else None
    label = (f"Hertz, E = {d.youngs_modulus_kpa:g} kPa, ν = {d.poisson_ratio:g}, "
             f"R = {config.tool.shaft_radius_m * 1e3:g} mm")
    tasks = [Task("deformation-over-time", partial(
        plots.deformation_over_time, frames, series.contact,
        series.depth_under_tip_mm, np.nan_to_num(series.depth_sigma_mm),
        series.penetration_mm, area_mm2, force, label,
        truth.get("indentation_mm"), truth.get("area_mm2")))]
    deepest = (data.deformation_summary or {}).get("deepest_frame")
    if deepest is not None and data.deepest_field is not None:
        pose = data.log.tool_poses[deepest]
        inward_mm, deformed = data.deepest_field
        tasks.append(Task("deformation-map", partial(
            plots.displacement_map, data.template[:, :2] * 1e3,
            inward_mm, deformed, pose[:2, 3] * 1e3, pose[:2, 2],
            f"frame {deepest}: displacement, the rigid motion of each ring removed")))
    return tasks


def _col(rows: list[dict[str, Any]], key: str, frames: range | None = None) -> np.ndarray:
    """Column `key` of the frame rows (of `frames`; default all) as floats, None as NaN."""
    sel = rows if frames is None else [rows[k] for k in frames]
    return np.array([np.nan if r.get(key) is None else r[key] for r in sel], float)


def _cloud_view(view: CloudView) -> partial[bytes]:
    """The labelled cloud in its camera's image (if any) and in 3D, titled with its counts."""
    labels = view.labels if view.labels is not None else np.full(len(view.xyz), UNKNOWN,
                                                                 np.uint8)
    counts = ", ".join(f"{n} {int((labels == c).sum())}" for c, n in CLASS_NAMES.items())
    title = f"frame {view.frame}" + (f" ({counts})" if view.labels is not None else "")
    return partial(plots.labelled_views, title, view.image, view.uv, view.xyz, labels,
                   CLASS_NAMES)


def _evaluation_tasks(ev: dict[str, Any], errors: dict[str, np.ndarray],
                      sampled: np.ndarray) -> list[Task]:
    """Template error, registration error over time and per sampled frame (errors hold
    their rows), confusion and F1."""
    tasks = []
    if "template_error_mm" in errors:
        tool = errors.get("on_tool", np.zeros(len(errors["template_error_mm"]), bool)).astype(bool)
        by = {"on the surface": ~tool, "on the tool": tool} if tool.any() else None
        tasks.append(Task("template-error", partial(
            plots.histogram, errors["template_error_mm"], "template error",
            "distance to the true surface (mm)", lines={"1 mm": 1.0}, by=by,
            colours={"on the surface": "#4C78A8", "on the tool": "#D1495B"})))
    reg = ev.get("registration")
    if reg and reg["per_frame"]:
        pf = reg["per_frame"]

        def get(key: str) -> np.ndarray:
            return np.array([np.nan if r.get(key) is None else r[key] for r in pf])

        tasks.append(Task("error-over-time", partial(
            plots.error_over_time, np.array([r["frame"] for r in pf]), get("median_mm"),
            get("p95_mm"), get("max_mm"))))
        if "registration_error_mm" in errors:
            tasks.append(Task("error-histograms", partial(
                plots.error_histograms, sampled, list(errors["registration_error_mm"]))))
    labels = ev.get("labels")
    if labels and labels.get("overall"):
        o = labels["overall"]
        axes = o["confusion_axes"]
        tasks.append(Task("confusion", partial(
            plots.confusion, np.array(o["confusion"]), axes["rows"], axes["cols"])))
        pf = labels["per_frame"]
        if pf:
            per_class = {name: np.array([r["per_class"][name]["f1"]
                                         if r["per_class"][name]["support"] else np.nan
                                         for r in pf]) for name in CLASS_NAMES.values()}
            macro = np.array([np.nan if r["macro_f1"] is None else r["macro_f1"] for r in pf])
            tasks.append(Task("f1-over-time", partial(
                plots.f1_over_time, np.array([r["frame"] for r in pf]), per_class,
                macro)))
    return tasks
