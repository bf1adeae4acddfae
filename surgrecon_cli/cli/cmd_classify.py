"""`surgrecon classify RUN`: label every template point of every frame."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from ..errors import counted
from .common import common_options, executor_options, locks_run_folder, progress


@click.command("classify")
@click.argument("run_dir", type=click.Path(exists=True, file_okay=False, path_type=Path))
@common_options
@executor_options
@locks_run_folder()
def classify_cmd(run_dir: Path, config: Any, quiet: bool) -> None:
    """Label every point of every frame static / shifting / deforming.

    A point is static when its registered displacement from frame 0 stays below
    classify.static_mm; a moving point is deforming when its neighbourhood (template points
    within classify.neighbourhood_mm) no longer moves as one rigid piece (classify.measure,
    threshold classify.deform_mm), else shifting. Rewrites RUN/clouds/NNNNNN.ply with the
    labels and writes RUN/classify/labels.npz.

    \b
    Example:
      surgrecon classify runs/sample
      surgrecon classify runs/sample --set classify.significance=0.001
    """
    from ..io.run.layout import RunLayout
    from ..pipeline import open_executor
    from ..stages.classify import run_classify

    with open_executor(config) as executor, \
            progress(quiet)(desc="classify", unit="step") as bar:
        def on_step(done: int, total: int) -> None:
            bar.total = total
            bar.update(done - bar.n)

        info = run_classify(run_dir, config, on_step=on_step, executor=executor)
    counts = info["counts_frames_1_on"]
    total = max(sum(counts.values()), 1)
    shares = ", ".join(f"{name} {n / total:.1%}" for name, n in counts.items())
    click.echo(f"{counted(info['points'], 'point')} x {counted(info['frames'], 'frame')}; "
               f"frames 1..: {shares}")
    layout = RunLayout(run_dir)
    click.echo(f"labels -> {layout.labels}; labelled clouds -> {layout.clouds_dir}")
