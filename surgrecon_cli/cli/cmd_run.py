"""`surgrecon run LOG.mcap -o RUN`: the whole pipeline, resumable."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from .common import common_options, progress


@click.command("run")
@click.argument("log", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option("-o", "--output", "run_dir", required=True,
              type=click.Path(file_okay=False, path_type=Path),
              help="Run folder (created, or resumed if it exists).")
@click.option("--ground-truth", "gt_path", type=click.Path(dir_okay=False, path_type=Path),
              help="Evaluate against this ground truth (default: NAME.gt.npz beside the log, "
                   "if there is one).")
@click.option("--allow-truncated", is_flag=True,
              help="Use the data before a truncation or corrupt chunk instead of failing.")
@common_options
def run_cmd(log: Path, run_dir: Path, gt_path: Path | None, allow_truncated: bool, config: Any,
            quiet: bool) -> None:
    """Run every stage on LOG: ingest, build-template, register, classify, report
    (and evaluate when ground truth is available).

    Resumable: rerunning on the same RUN skips finished stages (and registered frames). A
    changed input log restarts everything; a changed config section reruns the first
    stage that depends on it and all later ones (e.g. registration.* reruns register,
    classify and report, not ingest or the template). Prints the report's path at the end.

    \b
    Example:
      surgrecon run sample_data/sample.mcap -o runs/sample
      surgrecon run sample_data/sample.mcap -o runs/sample --set classify.deform_mm=0.2
    """
    from ..pipeline import run_pipeline
    from .cmd_evaluate import format_evaluation

    with progress(quiet)(total=100, desc="run", unit="%",
                         bar_format="{desc:<22}{percentage:3.0f}%|{bar}| {elapsed}") as bar:
        def on_progress(stage: str, fraction: float) -> None:
            bar.set_description_str(f"run: {stage}", refresh=False)
            bar.update(max(round(fraction * 100, 1) - bar.n, 0))

        result = run_pipeline(log, run_dir, config, ground_truth=gt_path,
                              allow_truncated=allow_truncated, on_progress=on_progress)
    for stage, action in result.actions.items():
        seconds = result.seconds.get(stage)
        timing = f" in {seconds:.1f} s" if seconds is not None else ""
        click.echo(f"{stage:<15} {action}{timing}")
    if result.evaluation is not None and not quiet:
        click.echo(format_evaluation(result.evaluation))
    click.echo(f"report: {result.report}")
