"""`surgrecon fit-tools RUN`: per-camera tool offsets fitted to an ingested run's images."""

from __future__ import annotations

import shlex
from pathlib import Path
from typing import Any

import click

from .common import common_options


@click.command("fit-tools")
@click.argument("run_dir", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("--group", "groups", multiple=True, metavar="CAM,CAM",
              help="Cameras that share one hand-eye calibration (repeatable; e.g. a stereo "
                   "pair). Default: all cameras, one group.")
@click.option("--frame", type=click.IntRange(min=0), default=0, show_default=True,
              help="Frame whose images are fitted.")
@click.option("--radius-mm", type=click.FloatRange(min=0.5, max=20), default=4.0,
              show_default=True, help="The instruments' real shaft radius (dVRK: 4).")
@click.option("--search-mm", type=click.FloatRange(min=3, max=60), default=24.0,
              show_default=True, help="Largest move searched per axis.")
@click.option("--min-contrast", type=float, default=40.0, show_default=True,
              help="Shaft contrast (grey levels, summed over the group) a fit needs to be used.")
@click.option("--write-config", "write_config", type=click.Path(dir_okay=False, path_type=Path),
              help="Write the config with the fitted tool.camera_offsets to this TOML file.")
@common_options
def fit_tools_cmd(run_dir: Path, groups: tuple[str, ...], frame: int, radius_mm: float,
                  search_mm: float, min_contrast: float, write_config: Path | None, config: Any,
                  quiet: bool) -> None:
    """Fit each tool's per-camera offset (tool.camera_offsets) to an ingested run's images.

    When camera groups (e.g. stereo pairs) have their own hand-eye calibrations and these
    disagree, the kinematic tool misses the instrument in some cameras. For each group and
    tool this moves the tool's shaft (1-12 cm up from its kinematic point, --radius-mm) by
    translations within --search-mm and keeps the one where the shaft is darkest against
    the tissue beside it in the group's images at --frame. A fit whose contrast reaches
    --min-contrast becomes the tool's camera_offsets entry for each camera of the group
    (docs/recordings.md). Run it after `surgrecon ingest`, then run with the written config.

    \b
    Example:
      surgrecon fit-tools runs/sample --write-config fitted.toml
      surgrecon fit-tools runs/sample --group 0,1 --group 2,3 --group 4,5
    """
    from ..config import to_toml
    from ..errors import InputError
    from ..stages.tool_offsets import fit_run_tool_offsets

    split = [tuple(c.strip() for c in g.split(",") if c.strip()) for g in groups]
    if any(not g for g in split):
        raise InputError("--group takes camera names separated by commas, e.g. --group p1l,p1r")
    new, rows = fit_run_tool_offsets(run_dir, config, frame, split, radius_mm / 1000,
                                     min_contrast, search_mm / 1000)
    if not rows:
        click.echo("no tool pose at this frame: nothing to fit")
    for row in rows:
        move = " ".join(f"{1000 * v:+.1f}" for v in row.offset_m)
        spread = " ".join(f"{1000 * v:.0f}" for v in row.spread_m)
        verdict = "used" if row.used else f"not used (below {min_contrast:g} or no better)"
        click.echo(f"{','.join(row.group)} {row.tool}: move ({move}) mm (+- {spread}), "
                   f"contrast {row.contrast_at_zero:.0f} -> {row.contrast:.0f}: {verdict}")
    for name, cfg in zip(("tool", *(f"tools[{k}]" for k in range(len(new.tools)))),
                         new.tool_configs(), strict=True):
        if cfg.camera_offsets:
            click.echo(f"{name}.camera_offsets = {list(cfg.camera_offsets)}")
    if write_config is not None:
        write_config.write_text(to_toml(new), encoding="utf-8")
        click.echo(f"config -> {write_config}; run with --config "
                   f"{shlex.quote(str(write_config))}")
