"""The text `surgrecon info` prints for a `LogInfo`: header (and the files of a split log),
channel table, TF tree, role candidates, the pose chain of every camera and of the tool as
ingest will compose it, and the check of the effective config's `[topics]`."""

from __future__ import annotations

import textwrap
from collections.abc import Sequence

from ..config import TopicsConfig
from ..core.sync.streams import fmt_stamp
from ..io.logs.encodings.registry import no_images_message
from .config_text import check_topics
from .patterns import captures
from .roles import other_candidates
from .scan import LogInfo

_MAX_FILES = 20
_WIDTH = 100
_ROLE_LABELS = {
    "image": "camera images", "camera_info": "camera infos", "camera_pose": "camera poses",
    "tool_pose": "tool pose", "joint_states": "joint states", "tf": "tf",
}


def format_info(info: LogInfo, topics: TopicsConfig | None = None,
                base_to_world: tuple[float, ...] = ()) -> str:
    """The whole `info` text; the config check only when `topics` is given. A log without
    camera images ends after its TF tree with the line saying so (no roles, no config)."""
    parts = [_header(info), _files(info), _channel_table(info), _tf_section(info)]
    if not info.has_images:
        parts.append(no_images_message(info.path))
    else:
        parts += [_roles_section(info), _poses_section(info)]
        if topics is not None:
            parts.append(_config_section(info, topics, base_to_world))
    return "\n\n".join(p for p in parts if p)


def _header(info: LogInfo) -> str:
    span = (info.end_ns - info.start_ns) * 1e-9 if info.message_count else 0.0
    start = fmt_stamp(info.start_ns) if info.message_count else "-"
    n = len(info.files)
    what = ""
    if info.path.is_dir():
        what = (f"rosbag2 bag folder, {n} file{'s' if n > 1 else ''}, " if info.bag
                else f"folder of {n} split file{'s' if n > 1 else ''}, ")
    lines = [
        f"{info.path}: {what}{_size(info.size)}, profile {info.profile or '-'}, "
        f"{info.message_count} messages on {len(info.channels)} channels, "
        f"{span:.3f} s from log time {start}",
        f"written by {info.library or '-'}; "
        + ("read from the summary and message indexes" if info.indexed
           else "no usable index: streamed" if n == 1 else
           f"streamed {sum(not f.indexed for f in info.files)} of {n} files (no usable index)"),
    ]
    if info.damage:
        lines.append(f"damaged log: {info.damage}")
        if info.files[-1].damage is None:
            lines.append("  (ingest reads nothing after the first damage: the later files are "
                         "described here, but not used)")
    return "\n".join(lines)


def _files(info: LogInfo) -> str:
    if len(info.files) < 2 and not info.path.is_dir():
        return ""
    rows = [("file", "size", "messages", "log time from", "span s")]
    for f in info.files[:_MAX_FILES]:
        rows.append((f.path.name, _size(f.size), str(f.messages),
                     fmt_stamp(f.first_ns) if f.messages else "-",
                     f"{(f.last_ns - f.first_ns) * 1e-9:.2f}" if f.messages else "-"))
    more = len(info.files) - _MAX_FILES
    tail = [f"  ... and {more} more"] if more > 0 else []
    return ("files (read in this order; statistics below are over all of them):\n"
            + "\n".join(["  " + line for line in _table(rows, {1, 2, 4})] + tail))


def _size(n: int) -> str:
    return f"{n / 1e6:.1f} MB" if n >= 1e6 else f"{n / 1e3:.1f} kB"


def _rate(rate_hz: float) -> str:
    """The rate column: Hz, or "-" where there is no rate (one message, or a burst)."""
    return f"{rate_hz:.1f}" if rate_hz > 0 else "-"


def _table(rows: Sequence[tuple[str, ...]], right: set[int]) -> list[str]:
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    return ["  ".join(v.rjust(w) if i in right else v.ljust(w)
                      for i, (v, w) in enumerate(zip(row, widths, strict=True))).rstrip()
            for row in rows]


def _channel_table(info: LogInfo) -> str:
    rows = [("topic", "schema", "encoding", "messages", "rate Hz", "span s", "detail")]
    for c in sorted(info.channels, key=lambda c: c.topic):
        detail = c.detail
        if c.frame_id and c.kind != "pose":
            detail = f"{detail} [{c.frame_id}]".strip()
        if not c.kind:
            detail = "(not read by surgrecon)"
        rows.append((c.topic, c.schema_name or "-", c.message_encoding, str(c.count),
                     _rate(c.rate_hz), f"{c.span_s:.2f}", detail))
    return "channels:\n" + "\n".join("  " + line for line in _table(rows, {3, 4, 5}))


def _tf_section(info: LogInfo) -> str:
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
                     "" if s.static else _rate(s.rate_hz),
                     "" if s.static else f"{(s.last_ns - s.first_ns) * 1e-9:.2f}"))
    left_out = f"\n  left out: {info.tf_error}" if info.tf_error else ""
    return head + ":\n" + "\n".join("  " + line for line in _table(rows, {3, 4, 5})) + left_out


def _roles_section(info: LogInfo) -> str:
    camera_frames = info.role("image").frame_pattern
    lines = ["roles (candidates from schemas and names; `--write-config FILE` writes them):"]
    for r in info.roles:
        if r.role == "tf":
            continue
        label = f"  {_ROLE_LABELS[r.role]:<13}"
        if not r.topics and not r.pattern:
            lines.append(f"{label} none" + (f" ({r.role} = \"\")"
                                            if r.role in ("tool_pose", "joint_states") else ""))
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
        others = other_candidates(info.roles, r)
        if others:
            extra.append(f"other candidates {', '.join(others[:6])}"
                         + (", ..." if len(others) > 6 else ""))
        if extra:
            lines.append(" " * 16 + "; ".join(extra))
    lines.append(f"  world frame   {info.world_frame}")
    return "\n".join(lines)


def _poses_section(info: LogInfo) -> str:
    plan = info.poses
    if plan is None or not plan.chains:
        return ""
    lines = [f"poses in world frame {plan.world!r} as ingest will compose them with the "
             "suggested [topics] (frame -(edge)-> parent):"]
    width = max(len(c.who) for c in plan.chains)
    for chain in plan.chains:
        lines.append(f"  {chain.who:<{width}}  {chain.text()}")
        if chain.note:
            lines += _wrapped(chain.note, width + 4)
        if chain.problem:
            lines += _wrapped(f"cannot: {chain.problem}", width + 4)
    if plan.tool is None:
        lines.append(f"  {'tool':<{width}}  none (tool_pose = \"\": no robot, tool removal off)")
    return "\n".join(lines)


def _config_section(info: LogInfo, topics: TopicsConfig, base_to_world: tuple[float, ...]
                    ) -> str:
    problems = check_topics(info, topics, base_to_world)
    if not problems:
        return (f"the config's [topics] find every role in this log, and every pose reaches "
                f"world_frame {topics.world_frame!r}")
    return ("the config's [topics] do not fit this log (`--write-config FILE` writes a block "
            "that does):\n" + "\n".join(line for p in problems for line in _wrapped(p, 2, 4)))


def _wrapped(text: str, indent: int, more: int = 0) -> list[str]:
    """`text` in lines of at most _WIDTH characters, indented (continuations by `more`)."""
    return textwrap.wrap(text, _WIDTH, initial_indent=" " * indent,
                         subsequent_indent=" " * (indent + more), break_on_hyphens=False,
                         break_long_words=False)
