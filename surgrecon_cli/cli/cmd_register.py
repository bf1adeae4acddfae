"""`surgrecon register RUN`: target cloud + sparse non-rigid registration of every frame."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from ..errors import counted
from .common import common_options, executor_options, locks_run_folder, progress


@click.command("register")
@click.argument("run_dir", type=click.Path(exists=True, file_okay=False, path_type=Path))
@common_options
@executor_options
@locks_run_folder()
def register_cmd(run_dir: Path, config: Any, quiet: bool) -> None:
    """Register the template to every later frame of a run (resumable).

    Template points are tracked into each frame's images, sorted by the reprojection-error
    check into static / dynamic / outlier, and the template is registered to that target
    cloud with one affine transform per point (l1 data and smoothness terms, ADMM).
    Writes RUN/clouds/NNNNNN.ply and RUN/registration/NNNNNN.npz per frame.

    \b
    Example:
      surgrecon register runs/sample --set registration.alpha=0.1
      surgrecon register runs/sample --executor processes --workers 2
    """
    from ..io.run.ingest_store import load_ingested
    from ..io.run.layout import RunLayout
    from ..pipeline import open_executor
    from ..stages.register import run_register

    layout = RunLayout(run_dir)
    n_frames = load_ingested(layout.ingest_dir).n_frames
    with open_executor(config) as executor, \
            progress(quiet)(total=max(n_frames - 1, 0), desc="register", unit="frame") as bar:
        processed = run_register(run_dir, config, on_frame=lambda _f, _n: bar.update(1),
                                 executor=executor)
    click.echo(
        f"registered {counted(len(processed), 'frame')} ({n_frames - 1 - len(processed)} already "
        f"done) -> {layout.registration_dir} (labelled clouds: `surgrecon classify`)"
    )
