"""`surgrecon info LOG.mcap`: channels, TF tree and role candidates of a log; a starter config."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from .common import common_options


@click.command("info")
@click.argument("log", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option("--write-config", "write_config", type=click.Path(dir_okay=False, path_type=Path),
              help="Write a starter [topics] TOML block for this log to FILE.")
@click.option("--force", is_flag=True, help="Replace an existing --write-config FILE.")
@common_options
def info_cmd(log: Path, write_config: Path | None, force: bool, config: Any,
             quiet: bool) -> None:
    """Describe LOG: channels, TF tree, and which topics fit each [topics] role.

    Lists every channel (schema, encoding, messages, rate, time span), the TF tree of /tf
    and /tf_static (frames, parents, static or dynamic, rates), and per role (camera
    images, camera infos, camera poses, tool pose, joint states, tf) the candidate topics
    and frames, found from the schemas and the names. Checks the [topics] of the effective
    config against the log. Fast: reads the summary and indexes where the log has them.
    With --quiet and --write-config only the file is written.

    \b
    Examples:
      surgrecon info sample_data/sample.mcap
      surgrecon info my_raven.mcap --write-config raven.toml
      surgrecon ingest my_raven.mcap -o runs/raven --config raven.toml
    """
    from ..errors import InputError
    from ..io.atomic import atomic_open
    from ..io.log_info import scan_log, topics_toml

    if write_config is not None and write_config.exists() and not force:
        raise InputError(f"{write_config} exists; pass --force to replace it")
    info = scan_log(log, config.ingest.time_source)
    if not (quiet and write_config is not None):
        click.echo(format_info(info, config.topics))
    if write_config is not None:
        with atomic_open(write_config, "w") as f:
            f.write(topics_toml(info))
        click.echo(f"wrote {write_config}: run with --config {write_config}")


def format_info(info: Any, topics: Any = None) -> str:
    """The whole `info` text: header, channel table, TF tree, roles, config check."""
    parts = [_header(info), _channel_table(info), _tf_section(info), _roles_section(info)]
    if topics is not None:
        parts.append(_config_section(info, topics))
    return "\n\n".join(p for p in parts if p)


def _header(info: Any) -> str:
    span = (info.end_ns - info.start_ns) * 1e-9 if info.message_count else 0.0
    start = _stamp(info.start_ns) if info.message_count else "-"
    lines = [
        f"{info.path}: {info.size / 1e6:.1f} MB, profile {info.profile or '-'}, "
        f"{info.message_count} messages on {len(info.channels)} channels, "
        f"{span:.3f} s from log time {start}",
        f"written by {info.library or '-'}; "
        + ("read from the summary and message indexes" if info.indexed
           else "no usable index: streamed"),
    ]
    if info.damage:
        lines.append(f"damaged log: {info.damage}")
    return "\n".join(lines)


def _stamp(ns: int) -> str:
    return f"{ns // 1_000_000_000}.{ns % 1_000_000_000:09d} s"


def _table(rows: list[tuple[str, ...]], right: set[int]) -> list[str]:
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    return ["  ".join(v.rjust(w) if i in right else v.ljust(w)
                      for i, (v, w) in enumerate(zip(row, widths, strict=True))).rstrip()
            for row in rows]


def _channel_table(info: Any) -> str:
    rows = [("topic", "schema", "encoding", "messages", "rate Hz", "span s", "detail")]
    for c in sorted(info.channels, key=lambda c: c.topic):
        detail = c.detail
        if c.frame_id and c.kind != "pose":
            detail = f"{detail} [{c.frame_id}]".strip()
        if not c.kind:
            detail = "(not read by surgrecon)"
        rows.append((c.topic, c.schema_name or "-", c.message_encoding, str(c.count),
                     f"{c.rate_hz:.1f}", f"{c.span_s:.2f}", detail))
    return "channels:\n" + "\n".join("  " + line for line in _table(rows, {3, 4, 5}))


def _tf_section(info: Any) -> str:
    tf = info.role("tf")
    if not tf.topics:
        return "TF tree: none (no tf2_msgs/TFMessage or foxglove.FrameTransform(s) channel)"
    head = f"TF tree from {tf.note}"
    if info.tf_tree is None:
        return f"{head}:\n  cannot be built: {info.tf_error}"
    summaries = info.tf_tree.describe()
    head += f": {len(summaries)} frames, root{'s' if len(info.tf_tree.roots) > 1 else ''} " + (
        ", ".join(info.tf_tree.roots))
    rows = [("frame", "parent", "edge", "transforms", "rate Hz", "span s")]
    for s in summaries:
        name = "  " * s.depth + s.frame
        if not s.parent:
            rows.append((name, "-", "root", "", "", ""))
            continue
        rows.append((name, s.parent, "static" if s.static else "dynamic", str(s.samples),
                     "" if s.static else f"{s.rate_hz:.1f}",
                     "" if s.static else f"{(s.last_ns - s.first_ns) * 1e-9:.2f}"))
    return head + ":\n" + "\n".join("  " + line for line in _table(rows, {3, 4, 5}))


_ROLE_LABELS = {
    "image": "camera images", "camera_info": "camera infos", "camera_pose": "camera poses",
    "tool_pose": "tool pose", "joint_states": "joint states", "tf": "tf",
}


def _roles_section(info: Any) -> str:
    from ..io.log_info import captures, other_candidates

    camera_frames = info.role("image").frame_pattern
    lines = ["roles (candidates from schemas and names; `--write-config FILE` writes them):"]
    for r in info.roles:
        if r.role == "tf":
            continue
        label = f"  {_ROLE_LABELS[r.role]:<13}"
        if not r.topics:
            lines.append(f"{label} none")
            continue
        lines.append(f"{label} {r.pattern or '(none chosen)'}")
        extra = []
        if r.cameras:
            extra.append(f"cameras {' '.join(r.cameras)}")
        if r.frame_pattern:
            extra.append(f"frame {r.frame_pattern}")
        elif r.frames and camera_frames and len(captures(camera_frames, r.frames)) == len(
                r.frames):
            extra.append(f"frame {camera_frames}")
        elif r.frames:
            shown = ", ".join(r.frames[:6]) + (", ..." if len(r.frames) > 6 else "")
            extra.append(f"frame{'s' if len(r.frames) > 1 else ''} {shown}")
        if r.parent_frames:
            extra.append(f"in {', '.join(r.parent_frames)}")
        if r.note:
            extra.append(r.note)
        others = other_candidates(info, r)
        if others:
            extra.append(f"other candidates {', '.join(others[:6])}"
                         + (", ..." if len(others) > 6 else ""))
        if extra:
            lines.append(" " * 16 + "; ".join(extra))
    if info.world_frame:
        lines.append(f"  world frame   {info.world_frame}")
    return "\n".join(lines)


def _config_section(info: Any, topics: Any) -> str:
    from ..io.log_info import check_topics

    problems = check_topics(info, topics)
    if not problems:
        return "the config's [topics] find every role in this log"
    return ("the config's [topics] do not fit this log (`--write-config FILE` writes a block "
            "that does):\n" + "\n".join(f"  {p}" for p in problems))
