"""`surgrecon simulate OUT.mcap`: synthetic log of a deforming cavity + ground truth."""

from __future__ import annotations

import time
from pathlib import Path

import click
from click.core import ParameterSource

from ..config import TopicsConfig
from ..sim import LENSES, POSE_CONVENTIONS
from ..sim.variants import VARIANTS
from .common import common_options

ENCODINGS = ("ros2", "ros1", "foxglove-protobuf", "foxglove-json")

# CLI option -> (SimConfig field, divisor from the option's unit to the field's).
_FIELDS = {
    "cameras": ("cameras", 1),
    "frames": ("frames", 1),
    "seed": ("seed", 1),
    "width": ("width", 1),
    "height": ("height", 1),
    "separated": ("separated", 1),
    "stereo_baseline_mm": ("stereo_baseline", 1000),
    "rigid_scene": ("rigid_scene", 1),
    "sweep_deg": ("sweep_deg", 1),
    "tracker_noise_mm": ("tracker_noise_pos", 1000),
    "tracker_noise_deg": ("tracker_noise_deg", 1),
    "lens": ("lens", 1),
    "robot": ("robot", 1),
}

def _no_robot_topics(topics: TopicsConfig) -> bool:
    """True when `--set topics.tool_pose=""` (and topics.joint_states="") asks for a log
    without a robot; UsageError for any other `topics` setting (the simulator writes the
    default topic names)."""
    from dataclasses import asdict

    given, default = asdict(topics), asdict(TopicsConfig())
    robot = ("tool_pose", "joint_states")
    changed = sorted(k for k in default if given[k] != default[k] and k not in robot)
    if changed:
        raise click.UsageError(
            f"simulate writes the default topic names; it does not take topics.{changed[0]} "
            "(only topics.tool_pose=\"\", the same as --no-robot). Set the topics when you "
            "ingest or run the log.")
    for key in robot:
        if given[key] not in ("", default[key]):
            raise click.UsageError(f"simulate writes topics.{key} on {default[key]}; here "
                                   "it takes only \"\" (a log without a robot: --no-robot)")
    if given["joint_states"] == "" and given["tool_pose"]:
        raise click.UsageError("simulate records the tool pose and joint states together: "
                               "for a log without the robot use --no-robot (or "
                               "topics.tool_pose=\"\")")
    return given["tool_pose"] == ""


_VARIANT_HELP = "\n".join(f"  {v.name:<12} {v.description}" for v in VARIANTS.values())


def _explicit(ctx: click.Context, name: str) -> bool:
    """True when the user gave this option (not its default)."""
    return ctx.get_parameter_source(name) not in (None, ParameterSource.DEFAULT)


@click.command(
    "simulate",
    epilog=f"\b\nVariants (--variant; options given explicitly override them):\n{_VARIANT_HELP}",
)
@click.argument("out", type=click.Path(dir_okay=False, path_type=Path))
@click.option(
    "--variant",
    type=click.Choice(list(VARIANTS)),
    default="default",
    show_default=True,
    help="Preset rig/scene (listed below); sets several options at once. The defaults "
    "shown are the default variant's.",
)
@click.option("--cameras", default=6, show_default=True, type=click.IntRange(1, 16))
@click.option("--frames", default=20, show_default=True, type=click.IntRange(2, 100000))
@click.option("--seed", default=7, show_default=True, type=int)
@click.option("--width", default=640, show_default=True, type=click.IntRange(32, 4096))
@click.option("--height", default=480, show_default=True, type=click.IntRange(32, 4096))
@click.option(
    "--stereo-baseline-mm",
    default=0.0,
    show_default=True,
    type=click.FloatRange(0, 100),
    help="Cameras 0 and 1 form one tracked stereo endoscope with this baseline (0 = off).",
)
@click.option(
    "--rigid-scene/--no-rigid-scene",
    default=False,
    show_default=True,
    help="The whole tissue moves as one rigid body: no breathing, no indentation.",
)
@click.option(
    "--sweep-deg",
    default=0.0,
    show_default=True,
    type=click.FloatRange(0, 90),
    help="Every camera pans by up to this angle over the log (0 = off).",
)
@click.option(
    "--tracker-noise-mm",
    default=0.1,
    show_default=True,
    type=click.FloatRange(0),
    help="Tracker position noise (RMS norm of the error).",
)
@click.option(
    "--tracker-noise-deg",
    default=0.05,
    show_default=True,
    type=click.FloatRange(0),
    help="Tracker rotation noise (RMS angle of the error).",
)
@click.option("--lens", type=click.Choice(LENSES), default="plumb_bob", show_default=True,
              help="Lens distortion model of every camera (as in CameraInfo).")
@click.option("--encoding", type=click.Choice(ENCODINGS), default="ros2", show_default=True)
@click.option(
    "--poses",
    type=click.Choice(POSE_CONVENTIONS),
    default="topics",
    show_default=True,
    help="How the log gives the camera and tool poses: PoseStamped per topic in world; "
    "transforms on /tf; a navigation TF tree (tracker, markers, hand-eye on /tf_static); "
    "cameras in the tracker's frame; the tool in the robot's base frame. The `--set` "
    "keys to ingest it with are printed.",
)
@click.option(
    "--video",
    type=click.Choice(["h264", "h265"]),
    default=None,
    help="Write the camera images as foxglove.CompressedVideo of this codec instead of JPEG "
    "(with --encoding foxglove-protobuf or foxglove-json; needs PyAV: "
    'pip install "surgrecon[video]").',
)
@click.option("--separated", is_flag=True, help="Place the last camera where it shares no view.")
@click.option("--robot/--no-robot", default=True, show_default=True,
              help="Record the robot's tool pose and joint states; --no-robot writes a log "
                   "without them (the tool is still in the images; the same as --set "
                   "topics.tool_pose=\"\" here), to be run with --set topics.tool_pose=\"\" "
                   "--set topics.joint_states=\"\".")
@common_options
@click.pass_context
def simulate_cmd(
    ctx: click.Context,
    out: Path,
    variant: str,
    encoding: str,
    poses: str,
    video: str | None,
    config,
    quiet: bool,
    **options,
) -> None:
    """Render a synthetic multi-camera log of a deforming cavity with ground truth.

    Writes OUT.mcap and, beside it, OUT.gt.npz (true surface per frame and labels).
    Deterministic for a given seed. --variant picks a preset rig or scene (below).

    \b
    Examples:
      surgrecon simulate sim.mcap --cameras 6 --frames 20 --seed 7
      surgrecon simulate stereo.mcap --variant stereo --frames 12 --seed 101
      surgrecon simulate noisy.mcap --variant noisy --tracker-noise-mm 0.5
      surgrecon simulate no_robot.mcap --no-robot
    """
    from ..sim.simulate import simulate
    from ..sim.variants import variant_config
    from .common import progress

    overrides = {}
    for name, value in options.items():
        if _explicit(ctx, name):
            key, divisor = _FIELDS[name]
            overrides[key] = value / divisor if divisor != 1 else value
    if _no_robot_topics(config.topics):
        overrides["robot"] = False
    if not overrides.get("robot", True) and poses == "robot-base":
        raise click.UsageError("--poses robot-base gives the tool in the robot's base frame: "
                               "it needs the robot (drop --no-robot)")
    try:
        cfg = variant_config(variant, **overrides)
    except ValueError as exc:
        raise click.UsageError(str(exc)) from exc
    if video and not encoding.startswith("foxglove"):
        raise click.UsageError(f"--video writes foxglove.CompressedVideo: use --encoding "
                               f"foxglove-protobuf or foxglove-json, not {encoding}")
    start = time.perf_counter()
    with progress(quiet)(total=cfg.frames, desc="rendering frames", unit="frame") as bar:
        result = simulate(
            out,
            cfg,
            encoding=encoding,
            convention=poses,
            labels=config.labels,
            on_frame=lambda _: bar.update(1),
            video=video,
        )
    fractions = ", ".join(f"{k} {v:.1%}" for k, v in result.class_fractions.items())
    click.echo(
        f"wrote {result.log_path} ({result.n_messages} messages, {result.n_frames} frames, "
        f"{cfg.cameras} cameras, variant {variant}, {encoding}"
        f"{f', {video} video' if video else ''}) in "
        f"{time.perf_counter() - start:.1f} s"
    )
    click.echo(
        f"ground truth {result.gt_path}; classes over frames 1..{cfg.frames - 1}: {fractions}"
    )
    from ..sim.conventions import CONVENTIONS

    settings = CONVENTIONS[poses].settings
    if not cfg.robot:
        settings = (*settings, 'topics.tool_pose=""', 'topics.joint_states=""')
    if settings:
        click.echo("ingest it with: " + " ".join(f"--set '{s}'" for s in settings))
