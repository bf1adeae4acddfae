"""`surgrecon info LOG`: channels, TF tree, role candidates and pose chains of a log; a starter
config (the text and the config come from info)."""

from __future__ import annotations

import shlex
from pathlib import Path
from typing import Any

import click

from .common import common_options


@click.command("info")
@click.argument("log", type=click.Path(exists=True, path_type=Path))
@click.option("--write-config", "write_config", type=click.Path(dir_okay=False, path_type=Path),
              help="Write a starter [topics] TOML block for this log to FILE.")
@click.option("--force", is_flag=True, help="Replace an existing --write-config FILE.")
@common_options
def info_cmd(log: Path, write_config: Path | None, force: bool, config: Any,
             quiet: bool) -> None:
    """Describe LOG: channels, TF tree, which topics fit each [topics] role, and how each
    camera's and the tool's pose reaches the world frame.

    LOG is an .mcap file, a rosbag2 bag folder (metadata.yaml and its .mcap files) or a
    folder of split .mcap files (statistics over all files, listed in order).

    Lists every channel (schema, encoding, messages, rate, time span), the TF tree of /tf
    and /tf_static (frames, parents, static or dynamic, rates), per role (camera images,
    camera infos, camera poses, tool pose, joint states, tf) the candidate topics and
    frames, found from the schemas and the names, and per camera the chain that gives its
    pose in the world frame (optical frame up through the TF tree, static or dynamic per
    edge) as ingest will compose it. Checks the [topics] of the effective config against
    the log. Fast: reads the summary and indexes where the log has them.

    A log without camera images is described, and said to be one that surgrecon cannot
    reconstruct from; --write-config then writes nothing and exits with 2.

    --write-config writes a [topics] block that ingest runs with as written: world_frame,
    and tool_pose = "" / joint_states = "" when the log has no robot / no joints. A tool
    pose in a frame no transform connects to the world needs tool.base_to_world, which
    no log holds: the text and the file say so. With --quiet and --write-config only the
    file is written.

    \b
    Examples:
      surgrecon info sample_data/sample.mcap
      surgrecon info my_raven.mcap --write-config raven.toml
      surgrecon ingest my_raven.mcap -o runs/raven --config raven.toml
      surgrecon info recordings/bag_2024_05_01/ --write-config bag.toml
    """
    from ..errors import InputError
    from ..info import format_info, scan_log, topics_toml
    from ..io.logs.encodings.registry import no_images_message
    from ..io.run.atomic import atomic_open

    if write_config is not None and write_config.exists() and not force:
        raise InputError(f"{write_config} exists; pass --force to replace it")
    info = scan_log(log, config.ingest.time_source)
    if not (quiet and write_config is not None):
        click.echo(format_info(info, config.topics, config.tool.base_to_world))
    if write_config is not None:
        if not info.has_images:
            raise InputError(f"{no_images_message(info.path)}; {write_config} not written")
        with atomic_open(write_config, "w") as f:
            f.write(topics_toml(info))
        click.echo(f"wrote {write_config}: run with --config {shlex.quote(str(write_config))}")
