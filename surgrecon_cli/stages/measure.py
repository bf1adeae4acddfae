"""Stage `measure`: tool-tissue contact and indentation measured from the reconstruction
(issue 17; the definitions are in core/measure/deformation.py and core/measure/indentation.py).

Reads the template, its observations (the frame-0 points' uncertainty), every registered
frame (positions, σ and each point's distance to the nearest point with data, for the
contact's hysteresis) and the ingested tool and camera poses; the neighbourhoods are the
classify stage's (same settings, rebuilt here). Writes atomically
  RUN/metrics/deformation.csv   one row per frame (DEFORMATION_COLUMNS; force_n empty when
                                the force model is off; a frame without a tool pose: contact
                                "not measured", the rest empty)
  RUN/measure/deformation.npz   the per-frame series and the compensated field (T, N)
  RUN/metrics/deformation_tools.csv  with `[[tools]]` only: one row per frame and tool
                                (TOOL_COLUMNS; tool `tool`, `tool_1`, ... as core/tool.tool_name)
  RUN/measure/summary.json      onset, release, deepest indentation, largest area, ...; per
                                `[[tools]]` tool the same under `extra_tools`
A point's σ here is that of its registered position and of its template position combined
(the displacement from frame 0 carries both). Frames are measured one at a time and the
field written by rows (io/run/rows.py): memory is flat in the number of frames.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from ..config import Config
from ..config.schema import ExtraToolConfig
from ..core.classify.rules import Neighbourhoods, template_neighbourhoods
from ..core.geometry.tool import tool_name
from ..core.measure.deformation import (
    ReferenceSurface,
    Rings,
    surface_normals,
    surrounding_rings,
)
from ..core.measure.indentation import (
    FIELD_DTYPES,
    NOT_MEASURED,
    SERIES_KEYS,
    DeformationSeries,
    SurfaceEstimate,
    camera_viewpoint,
    held_contact,
    measure_tools,
    series_of,
    summarise,
    tool_known,
)
from ..core.noise.model import covariance_sigma
from ..io.run.artefacts import read_observations, read_registration, read_template
from ..io.run.atomic import write_json
from ..io.run.ingest_store import IngestedLog, load_ingested
from ..io.run.layout import RunLayout
from ..io.run.metrics import finite_json, write_csv
from ..io.run.rows import RowFile, write_npz_rows
from .common import stage_run, tool_poses
from .registry import StageContext

logger = logging.getLogger(__name__)

STAGE = "measure"
DEFORMATION_COLUMNS = ("frame", *SERIES_KEYS)
TOOL_COLUMNS = ("frame", "tool", "pose", "contact", "clearance_mm", "tolerance_mm",
                "indentation_mm", "indentation_normal_mm", "depth_under_tip_mm", "area_mm2",
                "volume_mm3", "force_n")


def geometry(points: np.ndarray, log: IngestedLog,
             config: Config) -> tuple[Neighbourhoods, Rings, np.ndarray]:
    """The frame-0 geometry the measures need: neighbourhoods (classify's settings), rings
    and normals (N, 3) of points (N, 3) m."""
    c, d = config.classify, config.deformation
    nb = template_neighbourhoods(points, c.neighbourhood_mm, c.min_neighbours, c.max_neighbours)
    rings = surrounding_rings(points, d.ring_inner_mm, d.ring_outer_mm, d.ring_points)
    view = camera_viewpoint(log.poses[0], log.usable[0], points)
    return nb, rings, surface_normals(points, nb, view)


def run_measure(run_dir: Path, config: Config,
                on_step: Callable[[int, int], None] | None = None) -> dict[str, Any]:
    """Measure contact and indentation in every frame of a registered run; returns the
    summary. `on_step(done, total)` reports progress over the frames read."""
    layout = RunLayout(run_dir)
    step = on_step or (lambda _d, _t: None)
    with stage_run(layout.root, STAGE, config) as info:
        log = load_ingested(layout.ingest_dir)
        template = read_template(layout).points
        n, n_frames = len(template), log.n_frames
        obs = read_observations(layout, n)
        template_sigma = covariance_sigma(obs.covariance + obs.pose_covariance)
        nb, rings, normals = geometry(template, log, config)
        surface = ReferenceSurface(template, normals, nb, rings)
        figs: list[list[dict[str, float]]] = [[] for _ in config.tool_configs()]  # per tool
        scratch = {key: layout.measure_dir / f".deformation.{key}.tmp" for key in FIELD_DTYPES}
        layout.measure_dir.mkdir(parents=True, exist_ok=True)
        field = {key: RowFile(path, (n_frames, n), FIELD_DTYPES[key], create=True)
                 for key, path in scratch.items()}
        held = [False] * len(figs)  # each tool in contact in its last frame with a pose
        try:
            for k in range(n_frames):  # one frame in memory at a time
                positions, sigma, extrapolation = template, template_sigma, None
                if k:
                    reg = read_registration(layout, k, n)
                    positions = reg.registered.astype(float)
                    sigma = np.hypot(reg.sigma.astype(float), template_sigma)
                    extrapolation = (config.registration.extrapolation_growth
                                     * reg.support_mm.astype(float) * 1e-3)
                frame_figs, rows = measure_tools(
                    surface, SurfaceEstimate(positions, sigma, extrapolation),
                    tool_poses(log, config, k), config.deformation, config.tool_configs(),
                    held)
                held = held_contact(held, frame_figs)
                for t, fig in enumerate(frame_figs):
                    figs[t].append(fig)
                for key, value in rows.items():
                    field[key].write(k, value)
                step(k + 1, n_frames + 1)
            all_series = [series_of(f) for f in figs]
            series = all_series[0]
            summary = finite_json({
                **summarise(series, config.deformation, config.tool),
                "extra_tools": [_extra_summary(t, tool, all_series[t], config)
                                for t, tool in enumerate(config.tools, start=1)]})
            write_npz_rows(layout.deformation, {**{k: getattr(series, k) for k in SERIES_KEYS},
                                                **field})
        finally:
            for key, path in scratch.items():
                field[key].close()
                path.unlink(missing_ok=True)
        measured = tool_known(log.tool_poses)
        summary.update(contact_measured_frames=int(measured.sum()),
                       contact=None if measured.any() else NOT_MEASURED)
        write_json(layout.deformation_summary, summary)
        write_csv(layout.deformation_csv, DEFORMATION_COLUMNS, _rows(series, measured))
        if config.tools:
            write_csv(layout.deformation_tools_csv, TOOL_COLUMNS, _tool_rows(log, config,
                                                                             all_series))
        else:
            layout.deformation_tools_csv.unlink(missing_ok=True)  # from an earlier config
        step(n_frames + 1, n_frames + 1)
        info.update(onset_frame=summary["onset_frame"], release_frame=summary["release_frame"],
                    max_indentation_mm=summary["max_indentation_mm"],
                    max_area_mm2=summary["max_area_mm2"])
        logger.debug("contact frames %s, deepest %s mm", summary["contact_frames"],
                     summary["max_indentation_mm"])
    return summary


def _rows(series: DeformationSeries, measured: np.ndarray) -> list[dict[str, Any]]:
    """A tool's rows (`DeformationSeries.rows`); frames without its pose: "not measured"."""
    return [row if known else {"frame": row["frame"], "contact": NOT_MEASURED}
            for row, known in zip(series.rows(), measured, strict=True)]


def _tool_rows(log: IngestedLog, config: Config,
               all_series: list[DeformationSeries]) -> list[dict[str, Any]]:
    """deformation_tools.csv: per frame, every tool's row, in `Config.tool_configs()` order."""
    poses = [config.topics.tool_pose, *(t.pose for t in config.tools)]
    known = [tool_known(log.tool_poses),
             *(tool_known(log.extra_tool_poses[:, t]) for t in range(len(config.tools)))]
    per_tool = [[{**row, "tool": tool_name(t), "pose": poses[t]}
                 for row in _rows(s, known[t])] for t, s in enumerate(all_series)]
    return [rows[k] for k in range(log.n_frames) for rows in per_tool]


def _extra_summary(index: int, tool: ExtraToolConfig, series: DeformationSeries,
                   config: Config) -> dict[str, Any]:
    """A `[[tools]]` tool over the sequence: `summarise`'s figures (without the settings),
    its smallest clearance, name and pose topic."""
    clearance = series.clearance_mm
    figures = summarise(series, config.deformation, tool)
    del figures["settings"]
    return {"name": tool_name(index), "pose": tool.pose, **figures,
            "min_clearance_mm": (float(np.nanmin(clearance)) if np.isfinite(clearance).any()
                                 else None)}


def pipeline_step(ctx: StageContext, progress: Callable[[float], None]) -> None:
    """The stage within `surgrecon run`."""
    run_measure(ctx.run_dir, ctx.config, on_step=lambda d, t: progress(d / t))
