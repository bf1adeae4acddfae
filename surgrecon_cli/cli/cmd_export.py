"""`surgrecon export RUN --mcap OUT.mcap --tum DIR`: a run's results for Foxglove and evo."""

from __future__ import annotations

from pathlib import Path

import click

from .common import locks_run_folder, progress, quiet_options


@click.command("export")
@click.argument("run_dir", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("--mcap", "mcap_path", type=click.Path(dir_okay=False, path_type=Path),
              help="Write the run as an MCAP file for Foxglove (and OUT.layout.json beside "
                   "it). Needs a classified run.")
@click.option("--tum", "tum_dir", type=click.Path(file_okay=False, path_type=Path),
              help="Write every camera's and the tool's poses as TUM trajectories into DIR "
                   "(camera_CC.tum, camera_CC_tracker.tum, tool.tum, tool_robot.tum). "
                   "Needs an ingested run.")
@click.option("--force", is_flag=True, help="Replace an existing --mcap file.")
@quiet_options
@locks_run_folder(writes=False)
def export_cmd(run_dir: Path, mcap_path: Path | None, tum_dir: Path | None, force: bool,
               quiet: bool) -> None:
    """Export RUN's results where robotics tools read them.

    --mcap: one MCAP file (Foxglove protobuf schemas) stamped with the source log's frame
    times: per frame the labelled cloud coloured by class (/surgrecon/cloud: fields
    point_id, label, residual m, sigma m, displacement_mm), the targets
    (/surgrecon/target), camera and tool transforms (/surgrecon/tf), the tool's capsule and
    the camera frusta (/surgrecon/scene), the metrics of metrics/frames.csv
    (/surgrecon/frame_metrics, JSON), and per camera the recorded image, its calibration
    and the cloud's points projected onto it (/cameras/CC/image, calibration,
    annotations); the template once (/surgrecon/template_cloud). OUT.layout.json beside it
    is a Foxglove layout (3D view, image, plots): in Foxglove open the file, then Layouts >
    Import from file.

    --tum: `t tx ty tz qx qy qz qw` files (t in seconds since the epoch, metres, world
    frame), as evo reads them (`evo_traj tum DIR/*.tum`): camera_CC.tum and tool.tum the
    poses interpolated to the images / frames (ingest/frames.npz), camera_CC_tracker.tum and
    tool_robot.tum the tracker's and the robot's streams as recorded (ingest/streams.npz).
    A trajectory without any pose (the tool's, in a run without a robot) is not written.

    \b
    Examples:
      surgrecon export runs/sample --mcap runs/sample.mcap
      surgrecon export runs/sample --tum runs/sample-tum
      evo_traj tum runs/sample-tum/camera_00.tum runs/sample-tum/tool.tum --plot
    """
    from ..errors import InputError, counted

    if mcap_path is None and tum_dir is None:
        raise InputError("nothing to export: give --mcap OUT.mcap and/or --tum DIR")
    if mcap_path is not None and mcap_path.exists() and not force:
        raise InputError(f"{mcap_path} exists; pass --force to replace it")
    if tum_dir is not None:
        from ..io.export.to_tum import export_tum

        for trajectory in export_tum(run_dir, tum_dir):
            if trajectory.poses:
                click.echo(f"{trajectory.name:<24} {counted(trajectory.poses, 'pose'):>10} -> "
                           f"{trajectory.path}")
            else:
                click.echo(f"{trajectory.name:<24} {'no poses':>10}: {trajectory.path.name} "
                           "not written (evo reads no trajectory without a pose)")
    if mcap_path is not None:
        from ..io.export.to_mcap import export_mcap

        with progress(quiet)(desc="export", unit="frame") as bar:
            def on_frame(done: int, total: int) -> None:
                bar.total = total
                bar.update(done - bar.n)

            result = export_mcap(run_dir, mcap_path, on_frame=on_frame)
        messages = sum(result.counts.values())
        click.echo(f"mcap -> {result.path} ({result.bytes / 1e6:.1f} MB, {result.frames} frames, "
                   f"{messages} messages on {len(result.counts)} topics, "
                   f"{result.seconds:.1f} s)")
        click.echo(f"layout -> {result.layout} (Foxglove: Layouts > Import from file)")
