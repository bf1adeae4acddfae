"""`surgrecon ingest LOG.mcap -o RUN`: decode, synchronise and validate a log into a run folder."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from ..errors import counted
from .common import common_options, locks_run_folder, progress


@click.command("ingest")
@click.argument("log", type=click.Path(exists=True, path_type=Path))
@click.option(
    "-o",
    "--output",
    "run_dir",
    required=True,
    type=click.Path(file_okay=False, path_type=Path),
    help="Run folder to create.",
)
@click.option(
    "--allow-truncated",
    is_flag=True,
    help="Use the data before a truncation or corrupt chunk instead of failing "
    "(keeps complete frames only).",
)
@click.option("--force", is_flag=True, help="Replace an existing ingest in RUN.")
@common_options
@locks_run_folder(create=True)
def ingest_cmd(
    log: Path, run_dir: Path, allow_truncated: bool, force: bool, config: Any, quiet: bool
) -> None:
    """Decode, time-synchronise and validate LOG into the run folder RUN.

    Images of all cameras within ingest.sync_tolerance_ms form a frame; tracker poses are
    interpolated to each image stamp, the robot to each frame stamp. Which topic is which
    comes from the [topics] config section.

    \b
    Example:
      surgrecon ingest sample_data/sample.mcap -o runs/sample
      surgrecon ingest my_raven.mcap -o runs/raven --config raven.toml --allow-truncated
      surgrecon ingest long.mcap -o runs/part --set ingest.duration_s=30 \\
          --set ingest.every=3
    """
    from ..io.logs.log_input import resolve_log
    from ..io.run.layout import RunLayout
    from ..stages.ingest import ingest

    size = resolve_log(log).size
    with progress(quiet)(total=size, unit="B", unit_scale=True, desc="ingest") as bar:
        result = ingest(
            log, run_dir, config, allow_truncated=allow_truncated, force=force, on_bytes=bar.update
        )
    if not quiet:
        click.echo(format_report(result.report))
        click.echo(
            f"{counted(result.n_frames, 'frame')} from {counted(len(result.cameras), 'camera')}"
            " -> "
            f"{RunLayout(run_dir).ingest_dir}"
        )


def format_report(report: dict[str, Any]) -> str:
    """The per-camera ingest table (one line per camera) as text."""
    head = (
        "camera",
        "images",
        "frames",
        "dropped",
        "late",
        "dup",
        "pose gaps",
        "usable",
        "image Hz",
        "tracker Hz",
    )
    rows = [head]
    for cid, r in report["cameras"].items():
        rows.append(
            (
                cid,
                str(r["images"]),
                str(r["frames"]),
                str(r["dropped"]),
                str(r["late"]),
                str(r["duplicates"]),
                str(r["pose_gaps"]),
                str(r["usable"]),
                f"{r['image_rate_hz']:.1f}",
                f"{r['tracker_rate_hz']:.1f}" if r["tracker_rate_hz"] else "fixed",
            )
        )
    widths = [max(len(row[i]) for row in rows) for i in range(len(head))]
    lines = [
        "  ".join(
            v.ljust(w) if i == 0 else v.rjust(w)
            for i, (v, w) in enumerate(zip(row, widths, strict=True))
        )
        for row in rows
    ]
    extra = (
        f"tool {report['tool_rate_hz']:.1f} Hz (pose unknown at "
        f"{report['tool_pose_missing']} frames), joints {report['joint_rate_hz']:.1f} Hz; "
        f"{report['frames_all_usable']} of {report['frames']} frames with every camera usable"
    )
    if report.get("truncated"):
        extra += f"\ntruncated log: {report['truncated']}; "
        extra += f"{report['frames_dropped_after_damage']} incomplete frames dropped at the end"
    return "\n".join(lines) + "\n" + extra
