"""`surgrecon report RUN`: metrics CSV/JSON and the HTML report of a run."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from .common import common_options, executor_options, locks_run_folder, progress


@click.command("report")
@click.argument("run_dir", type=click.Path(exists=True, file_okay=False, path_type=Path))
@common_options
@executor_options
@locks_run_folder()
def report_cmd(run_dir: Path, config: Any, quiet: bool) -> None:
    """Write the metrics and the HTML report of a run (uses whatever stages are done).

    RUN/metrics/frames.csv has one row per frame (points per class and per reprojection
    status, residual and displacement statistics, timings, and errors when evaluated);
    RUN/metrics/summary.json the run at a glance; RUN/report.html plots and rendered
    labelled clouds, self-contained (open it in any browser, offline).

    \b
    Example:
      surgrecon report runs/sample && xdg-open runs/sample/report.html
      surgrecon report runs/sample --executor processes --workers 2
    """
    from ..pipeline import open_executor
    from ..stages.report import run_report

    with open_executor(config) as executor, \
            progress(quiet)(desc="report", unit="step", total=4) as bar:
        files = run_report(run_dir, config, on_step=lambda done, _t: bar.update(done - bar.n),
                           executor=executor)
    click.echo(f"metrics -> {files.frames_csv}, {files.summary_json}")
    click.echo(f"report -> {files.html}")
