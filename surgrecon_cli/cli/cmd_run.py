"""`surgrecon run LOG.mcap -o RUN`: the whole pipeline, resumable; `surgrecon run LOG... -o
RUNS/`: many logs, one run folder each, over one executor."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from ..errors import InputError
from .common import common_options, executor_options, progress


@click.command("run")
@click.argument("logs", nargs=-1, required=True,
                type=click.Path(exists=True, path_type=Path))
@click.option("-o", "--output", "run_dir", required=True,
              type=click.Path(file_okay=False, path_type=Path),
              help="Run folder (created, or resumed if it exists); with several logs, the "
                   "folder that holds one run folder per log (RUNS/NAME for NAME.mcap).")
@click.option("--ground-truth", "gt_path", type=click.Path(dir_okay=False, path_type=Path),
              help="Evaluate against this ground truth (default: NAME.gt.npz beside the log, "
                   "if there is one). One log only.")
@click.option("--allow-truncated", is_flag=True,
              help="Use the data before a truncation or corrupt chunk instead of failing.")
@click.option("--force", is_flag=True,
              help="Replace a run folder that holds the run of another log (refused "
                   "without it).")
@click.option("--tag", default="", metavar="LABEL",
              help="Write to RUN-LABEL beside RUN (with several logs RUNS/NAME-LABEL), so "
                   "that runs of one log with other settings sit side by side (`surgrecon "
                   "compare RUN RUN-LABEL`). A new RUN-LABEL starts from RUN: every stage "
                   "output of RUN whose config keys did not change is reused (hard links, "
                   "copies across devices), only the rest is computed.")
@click.option("--export", "exports", type=click.Choice(["mcap"]), multiple=True,
              help="At the end, also write RUN/export.mcap for Foxglove (as `surgrecon "
                   "export RUN --mcap`), with RUN/export.layout.json beside it.")
@common_options
@executor_options
def run_cmd(logs: tuple[Path, ...], run_dir: Path, gt_path: Path | None, allow_truncated: bool,
            force: bool, tag: str, exports: tuple[str, ...], config: Any, quiet: bool) -> None:
    """Run every stage on LOG: ingest, build-template, register, classify, measure, report
    (and evaluate when ground truth is available).

    Resumable: rerunning on the same RUN skips finished stages (and registered frames); a
    RUN made from another log is refused (--force replaces it). A changed config section
    reruns the first stage that depends on it and all later ones (e.g. registration.*
    reruns register, classify and report, not ingest or the template). With --tag the run
    goes to RUN-LABEL beside RUN and reuses RUN's outputs that the change leaves valid
    (e.g. a classify.* change recomputes classify and what follows it, not ingest, the
    template or the registration). Prints the report's path at the end.

    The stages' tasks run on --executor (serial, processes, or dask on a LocalCluster or the
    cluster at --scheduler); the outputs are the same whichever runs them. Several logs
    run at once over the same workers; a log that fails does not stop the others, and the
    exit code is non-zero if any failed.

    \b
    Example:
      surgrecon run sample_data/sample.mcap -o runs/sample
      surgrecon run sample_data/sample.mcap -o runs/sample --set classify.significance=0.001
      surgrecon run sample_data/sample.mcap -o runs/sample --export mcap
      surgrecon run sample_data/sample.mcap -o runs/sample --tag strict \\
          --set classify.significance=0.001
      surgrecon run logs/*.mcap -o runs/ --executor processes --workers 2
      surgrecon run logs/*.mcap -o runs/ --scheduler tcp://10.0.0.5:8786
      surgrecon run long.mcap -o runs/part --set ingest.duration_s=30 \\
          --set ingest.every=3
    """
    from ..io.run.lock import run_folder_lock
    from ..pipeline import open_executor, tagged

    if len(logs) > 1 and gt_path is not None:
        raise InputError("--ground-truth goes with one log; with several, each log's "
                         "NAME.gt.npz beside it is used")
    if len(logs) == 1:  # the folder's lock first: a second run refuses before starting workers
        base, run_dir = run_dir, tagged(run_dir, tag)
        with run_folder_lock(run_dir, "run", create=True), open_executor(config) as executor:
            _run_one(logs[0], run_dir, gt_path, allow_truncated, force, config, quiet, executor,
                     base if tag else None)
            if "mcap" in exports:
                _export_mcap([run_dir])
        return
    with open_executor(config) as executor:  # each run folder is locked by run_pipeline
        _run_many(list(logs), run_dir, allow_truncated, force, config, quiet, executor,
                  exports, tag)


def _run_one(log: Path, run_dir: Path, gt_path: Path | None, allow_truncated: bool,
             force: bool, config: Any, quiet: bool, executor: Any,
             seed_from: Path | None = None) -> None:
    from ..pipeline import run_pipeline
    from .cmd_evaluate import format_evaluation

    with progress(quiet)(total=100, desc="run", unit="%",
                         bar_format="{desc:<22}{percentage:3.0f}%|{bar}| {elapsed}") as bar:
        def on_progress(stage: str, fraction: float) -> None:
            bar.set_description_str(f"run: {stage}", refresh=False)
            bar.update(max(round(fraction * 100, 1) - bar.n, 0))

        result = run_pipeline(log, run_dir, config, ground_truth=gt_path,
                              allow_truncated=allow_truncated, on_progress=on_progress,
                              executor=executor, force=force, seed_from=seed_from)
    if not quiet:
        for stage, action in result.actions.items():
            seconds = result.seconds.get(stage)
            timing = f" in {seconds:.1f} s" if seconds is not None else ""
            click.echo(f"{stage:<15} {action}{timing}")
        if result.evaluation is not None:
            click.echo(format_evaluation(result.evaluation))
    click.echo(f"report: {result.report}")


def _export_mcap(run_dirs: list[Path]) -> None:
    """`--export mcap`: RUN/export.mcap of every finished run."""
    from ..io.export.to_mcap import export_mcap
    from ..io.run.layout import RunLayout

    for run_dir in run_dirs:
        result = export_mcap(run_dir, RunLayout(run_dir).export_mcap)
        click.echo(f"mcap: {result.path} ({result.bytes / 1e6:.1f} MB; Foxglove layout "
                   f"{result.layout})")


def _run_many(logs: list[Path], runs_root: Path, allow_truncated: bool, force: bool,
              config: Any, quiet: bool, executor: Any, exports: tuple[str, ...],
              tag: str) -> None:
    import threading

    from ..pipeline import run_many

    fractions = dict.fromkeys(logs, 0.0)
    lock = threading.Lock()
    with progress(quiet)(total=100 * len(logs), desc=f"run: {len(logs)} logs", unit="%",
                         bar_format="{desc:<22}{percentage:3.0f}%|{bar}| {elapsed}") as bar:
        def on_progress(log: Path, _stage: str, fraction: float) -> None:
            with lock:
                fractions[log] = fraction
                bar.update(max(round(sum(fractions.values()) * 100, 1) - bar.n, 0))

        results = run_many(logs, runs_root, config, allow_truncated=allow_truncated,
                           executor=executor, on_progress=on_progress, force=force, tag=tag)
    failed = 0
    for log, result in zip(logs, results, strict=True):
        if isinstance(result, Exception):
            failed += 1
            click.echo(f"{log}: failed: {result}")
            continue
        summary = ""
        overall = ((result.evaluation or {}).get("labels") or {}).get("overall")
        if overall:
            summary = f"  macro-F1 {overall['macro_f1']:.3f}"
        click.echo(f"{log}: report {result.report}{summary}")
    if "mcap" in exports:
        _export_mcap([r.run_dir for r in results if not isinstance(r, Exception)])
    if failed:
        raise InputError(f"{failed} of {len(logs)} logs failed (see above); the others are "
                         f"complete under {runs_root}")
