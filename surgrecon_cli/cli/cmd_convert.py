"""`surgrecon convert SRC -o OUT.mcap`: stereo / per-camera images or videos + calibration ->
a ROS 2 MCAP log and the config that runs it."""

from __future__ import annotations

import shlex
from pathlib import Path

import click

from ..errors import counted
from .common import progress, quiet_options

_FILE = click.Path(dir_okay=False, path_type=Path)  # missing: one line from convert


def _frame_range(ctx: click.Context, param: click.Parameter, value: str | None) -> slice:
    if not value:
        return slice(None)
    try:
        parts = [int(p) if p.strip() else None for p in value.split(":")]
    except ValueError:
        raise click.BadParameter("use START:STOP[:STEP], e.g. 0:100 or ::5") from None
    if len(parts) not in (2, 3):
        one = f" (frame {parts[0]} alone: {parts[0]}:{parts[0] + 1})" if (
            len(parts) == 1 and parts[0] is not None and parts[0] >= 0) else ""
        raise click.BadParameter(f"use START:STOP[:STEP], e.g. 0:100 or ::5{one}")
    if len(parts) == 3 and parts[2] is not None and parts[2] <= 0:
        raise click.BadParameter("use START:STOP[:STEP] with a positive STEP, e.g. 0:100")
    return slice(*parts)


def _cameras(ctx: click.Context, param: click.Parameter,
             value: tuple[str, ...]) -> tuple[tuple[str, Path], ...]:
    out = []
    for item in value:
        name, sep, path = item.partition("=")
        if not sep or not name or not path:
            raise click.BadParameter(f"{item!r}: use NAME=PATH, e.g. cam0=recordings/cam0")
        out.append((name, Path(path)))
    return tuple(out)


@click.command("convert")
@click.argument("src", required=False, type=click.Path(path_type=Path))
@click.option("-o", "--output", "out", required=True,
              type=click.Path(dir_okay=False, path_type=Path),
              help="MCAP log to write; the config goes beside it as OUT.toml.")
@click.option("--calibration", "calibration", multiple=True, required=True, type=_FILE,
              help="Calibration file: OpenCV YAML/XML (M1 D1 M2 D2 R T, K1/K2, left/right), "
              "JSON with the same fields, 'fx fy cx cy baseline' of a rectified pair, a "
              "'cameras' map for more cameras, a Kalibr camchain.yaml, or one ROS "
              "camera_info YAML per camera (repeat the option).")
@click.option("--left", help="Left image folder's name inside SRC (default: found).")
@click.option("--right", help="Right image folder's name inside SRC.")
@click.option("--camera", "cameras", multiple=True, metavar="NAME=PATH", callback=_cameras,
              help="One image folder or video per camera (repeat; instead of SRC).")
@click.option("--stereo-layout", "layout", default="auto", show_default=True,
              type=click.Choice(["auto", "side-by-side", "top-bottom"]),
              help="How a stereo video holds the two views (auto: from the calibrated size; "
              "with --scale-calibration, its shape).")
@click.option("--units", type=click.Choice(["mm", "m"]),
              help="Unit of the calibration's lengths (T, baseline). Default: millimetres when "
              "the largest camera offset is above 1, else metres.")
@click.option("--scale-calibration", is_flag=True,
              help="The images are the calibrated ones resized: scale each camera's intrinsics "
              "from the calibration's width/height to its images' (instead of an error).")
@click.option("--fps", type=click.FloatRange(min=0, min_open=True),
              help="Frame rate of the images (default: a video's own times, else 30).")
@click.option("--start-time", default=1.0, show_default=True, type=click.FloatRange(min=0),
              metavar="SECONDS",
              help="Stamp of the first frame with --fps or a video's own times (not 0: ROS "
              "reads a zero stamp as unset).")
@click.option("--stamps", type=_FILE,
              help="Stamps file: one per source frame (seconds, or integer nanoseconds).")
@click.option("--camera-poses", type=_FILE,
              help="TUM file (t x y z qx qy qz qw; s, m) of the rig in the world: the first "
              "camera's optical frame (or the frame of a 'cameras' file's poses); default: the "
              "rig is fixed in the world.")
@click.option("--tool-poses", type=_FILE, multiple=True,
              help="TUM file of the tool tip in the world (the robot roles are off without); "
              "repeat for more tools (e.g. a dVRK's second arm): each becomes a [[tools]] table.")
@click.option("--image-format", default="jpeg", show_default=True,
              type=click.Choice(["jpeg", "png"]),
              help="Encoding of decoded video frames (JPEG quality 95, or lossless PNG). Image "
              "files keep their bytes (JPEG, PNG) or become PNG (BMP, TIFF).")
@click.option("--frames", "frames", callback=_frame_range, metavar="START:STOP[:STEP]",
              help="Convert only these source frames (Python slice), e.g. 0:100 or ::5.")
@quiet_options
def convert_cmd(src: Path | None, out: Path, calibration: tuple[Path, ...], left: str | None,
                right: str | None, cameras: tuple[tuple[str, Path], ...], layout: str,
                units: str | None, scale_calibration: bool, fps: float | None,
                start_time: float, stamps: Path | None,
                camera_poses: Path | None, tool_poses: tuple[Path, ...], image_format: str,
                frames: slice, quiet: bool) -> None:
    """Turn stereo (or per-camera) images or a stereo video plus a calibration file into a
    ROS 2 MCAP log (CompressedImage, CameraInfo, /tf) and OUT.toml, a config that runs it.

    SRC is a folder with two image folders (left/right, Left/Right, left_image/right_image,
    image_0/image_1, image01/image02 as Hamlyn's rectified sequences, cam0/cam1, or
    --left/--right), images in name order (PNG, JPEG, BMP, TIFF; 8 or 16 bit), or a stereo
    video (side by side or top-bottom). Without --camera-poses the rig is fixed in the world:
    a moving camera then shows as moving tissue.
    Then: surgrecon run OUT.mcap -o RUN --config OUT.toml

    \b
    Examples:
      surgrecon convert recordings/surgt -o surgt.mcap --calibration calibration.yaml
      surgrecon convert video.mp4 -o surgt_video.mcap --calibration calibration.yaml
    """
    from ..convert.run import ConvertRequest, convert

    request = ConvertRequest(out=out, calibration=calibration, src=src, cameras=cameras,
                             left=left, right=right, layout=layout, units=units, fps=fps,
                             start_time=start_time, stamps=stamps,
                             camera_poses=camera_poses, tool_poses=tool_poses,
                             image_format=image_format, frames=frames,
                             scale_calibration=scale_calibration)
    result = convert(request, progress(quiet))
    click.echo(f"{result.log}: {counted(result.frames, 'frame')} of cameras "
               f"{', '.join(result.cameras)} ({result.source}; calibration lengths in "
               f"{result.units})")
    click.echo(f"{result.config}: run it with  surgrecon run {shlex.quote(str(result.log))} "
               f"-o RUN --config {shlex.quote(str(result.config))}")
