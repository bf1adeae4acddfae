"""`surgrecon build-template RUN`: the template cloud from the first frame."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from .common import common_options, executor_options, locks_run_folder, progress


@click.command("build-template")
@click.argument("run_dir", type=click.Path(exists=True, file_okay=False, path_type=Path))
@common_options
@executor_options
@locks_run_folder()
def build_template_cmd(run_dir: Path, config: Any, quiet: bool) -> None:
    """Build the template cloud P from frame 0 of an ingested run.

    SIFT features (tool masked) are matched between camera pairs chosen by camera grouping
    and pair sequencing, checked against the tracked epipolar geometry, chained into tracks,
    triangulated and filtered. Writes RUN/template.ply and RUN/clouds/000000.ply.

    \b
    Example:
      surgrecon build-template runs/sample
      surgrecon build-template runs/sample --executor processes --workers 2
    """
    from ..core.template.build import STEPS
    from ..io.run.layout import RunLayout
    from ..pipeline import open_executor
    from ..stages.template import run_build_template

    with open_executor(config) as executor, \
            progress(quiet)(desc="template", unit="step", total=len(STEPS)) as bar:
        result = run_build_template(run_dir, config, on_step=lambda _s: bar.update(1),
                                    executor=executor)
    stats = result.stats
    groups = "; ".join(",".join(str(c) for c in g) for g in _named(run_dir, result.plan.groups))
    click.echo(f"camera groups: {groups}")
    for seq in result.plan.sequences:
        click.echo("pair sequence: " + " ".join(f"{i}-{j}" for i, j in seq))
    click.echo(
        f"features per camera {stats['features']}; {stats['verified_pairs']} of "
        f"{stats['candidate_pairs']} candidate pairs verified; {stats['tracks']} tracks"
    )
    click.echo(
        f"template: {stats['points']} points ({stats['rejected_geometry']} rejected by "
        f"reprojection/angle, {stats['removed_off_surface']} off-surface, "
        f"{stats['removed_tool']} on the tool) -> {RunLayout(run_dir).template_ply}"
    )


def _named(run_dir: Path, groups: list[list[int]]) -> list[list[str]]:
    from ..io.run.folder import RunFolder

    cameras = RunFolder(run_dir).read().get("ingest", {}).get("cameras", [])
    return [[cameras[c] if c < len(cameras) else str(c) for c in g] for g in groups]
