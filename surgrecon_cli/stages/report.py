"""Stage `report`: per-frame metrics table, run summary and the HTML report.

Uses whatever stages are done and writes atomically
  RUN/metrics/frames.csv     one row per frame (FRAME_COLUMNS)
  RUN/metrics/summary.json   the run at a glance (counts, timings, template, evaluation)
  RUN/report.html            self-contained (figures embedded as PNG), readable offline
The work is in surgrecon_cli/report/: gather -> metrics -> figures -> page.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

from ..config import Config
from ..executors import Executor
from ..executors.serial import SerialExecutor
from ..io.run.atomic import write_text
from ..io.run.layout import RunLayout
from ..io.run.metrics import write_csv, write_metrics_json
from ..report.figures import draw_figures
from ..report.gather import gather, gather_views
from ..report.metrics import CLASS_COLUMNS, FRAME_COLUMNS, STATUS_COLUMNS, measure
from ..report.page import compose
from .common import stage_run
from .registry import StageContext

__all__ = ["CLASS_COLUMNS", "FRAME_COLUMNS", "STATUS_COLUMNS", "ReportFiles", "pipeline_step",
           "run_report"]

STAGE = "report"


@dataclass(frozen=True)
class ReportFiles:
    """Where the report stage wrote its outputs."""

    html: Path
    frames_csv: Path
    summary_json: Path


def run_report(run_dir: Path, config: Config,
               on_step: Callable[[int, int], None] | None = None,
               executor: Executor | None = None) -> ReportFiles:
    """Write frames.csv, summary.json and report.html for a run (any stages done); the
    figures are drawn as tasks on `executor` (default: serial) before the page is composed."""
    layout = RunLayout(run_dir)
    step = on_step or (lambda _d, _t: None)
    files = ReportFiles(layout.report_html, layout.frames_csv, layout.summary_json)
    with stage_run(layout.root, STAGE, config) as info:
        data = gather(layout.root)
        step(1, 4)
        metrics = measure(data, config)
        write_csv(files.frames_csv, FRAME_COLUMNS, metrics.rows)
        write_metrics_json(files.summary_json, metrics.summary)
        step(2, 4)
        views = gather_views(layout, data, config.tool)
        pngs = draw_figures(data, metrics, views, config, executor or SerialExecutor())
        step(3, 4)
        write_text(files.html, compose(layout, data, metrics, views, config, pngs,
                                       datetime.now(UTC)))
        step(4, 4)
        info.update(html=str(files.html), frames=data.log.n_frames,
                    caveats=list(metrics.caveats))
    return files


def pipeline_step(ctx: StageContext, progress: Callable[[float], None]) -> None:
    """The stage within `surgrecon run`."""
    run_report(ctx.run_dir, ctx.config, on_step=lambda d, t: progress(d / t),
               executor=ctx.executor)
