"""`surgrecon measure RUN`: tool-tissue contact and indentation from the reconstruction."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from .common import common_options, locks_run_folder, progress


@click.command("measure")
@click.argument("run_dir", type=click.Path(exists=True, file_okay=False, path_type=Path))
@common_options
@locks_run_folder()
def measure_cmd(run_dir: Path, config: Any, quiet: bool) -> None:
    """Measure tool-tissue contact and indentation in every registered frame.

    Every template point's displacement from frame 0 is taken after removing the rigid
    motion of the ring of points around it (deformation.ring_inner_mm to ring_outer_mm), so
    that breathing does not count. Contact: the tool (robot kinematics, a capsule of
    tool.shaft_radius_m) comes within the noise-based tolerance of the registered surface.
    Per frame: indentation depth at the tool tip (along its axis and the surface normal),
    deformed area (mm²), indented volume (mm³) and, with deformation.youngs_modulus_kpa > 0,
    a Hertzian force proxy (a model output, not a measurement). Every tool is measured
    at its working end (the jaw's end when it has one). Writes RUN/metrics/deformation.csv
    (the [tool]), with [[tools]] RUN/metrics/deformation_tools.csv (a row per frame and
    tool), and RUN/measure/.

    \b
    Example:
      surgrecon measure runs/sample
      surgrecon measure runs/sample --set deformation.youngs_modulus_kpa=5
    """
    from ..io.run.layout import RunLayout
    from ..stages.measure import run_measure

    with progress(quiet)(desc="measure", unit="frame") as bar:
        def on_step(done: int, total: int) -> None:
            bar.total = total
            bar.update(done - bar.n)

        summary = run_measure(run_dir, config, on_step=on_step)
    click.echo(format_summary(summary))
    layout = RunLayout(run_dir)
    tools = f", {layout.deformation_tools_csv}" if summary.get("extra_tools") else ""
    click.echo(f"-> {layout.deformation_csv}{tools}, {layout.deformation}")


def _num(value: Any, unit: str) -> str:
    return "-" if value is None else f"{value:.3g} {unit}"


def format_summary(s: dict[str, Any]) -> str:
    """The measures at a glance, one line (two with the force proxy), and a line per
    `[[tools]]` tool."""
    text = _contact_line(s)
    if s.get("force_model"):
        force = _num(s["max_force_n"], "N")
        text += f"\nforce proxy (model output, not a measurement): up to {force}"
    for tool in s.get("extra_tools") or []:
        text += f"\n{tool.get('name', 'tool')} ({tool['pose']}): {_contact_line(tool)}"
    return text


def _contact_line(s: dict[str, Any]) -> str:
    if s.get("onset_frame") is None:
        return "no tool-tissue contact"
    release = s["release_frame"]
    return (f"contact from frame {s['onset_frame']} "
            + ("to the end" if release is None else f"until frame {release}")
            + f" ({len(s['contact_frames'])} frames); deepest indentation "
            f"{_num(s['max_indentation_mm'], 'mm')} (frame {s['deepest_frame']}), area up to "
            f"{_num(s['max_area_mm2'], 'mm²')}, volume up to {_num(s['max_volume_mm3'], 'mm³')}")
