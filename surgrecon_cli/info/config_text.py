"""The `[topics]` block `info --write-config` writes, and the check of a config's `[topics]`
against the log.

The block is meant to run as written: every key ingest needs for this log is a real key
(`world_frame` included; `tool_pose = ""` / `joint_states = ""` when the log has no robot /
no joints). What a log cannot tell (the robot base's pose in the world when the tool pose is
in a frame no transform connects to the world) is written as a comment saying what to set.
"""

from __future__ import annotations

import textwrap
from collections.abc import Sequence

from ..config import TopicsConfig
from ..io.logs.topics import ROLE_KINDS, ROLES, TopicRoles
from .channels import ChannelInfo
from .patterns import sort_ids
from .poses import PoseChain, plan_poses, suggest_world
from .roles import RoleGuess, other_candidates
from .scan import LogInfo

_KEY_ORDER = ("image", "camera_info", "camera_pose", "camera_frame", "tool_pose", "tool_frame",
              "joint_states", "world_frame")
_WIDTH = 95


def _quote(value: str) -> str:
    """A TOML basic string (control characters escaped)."""
    escaped = "".join(
        {"\\": "\\\\", '"': '\\"'}.get(c) or (c if c.isprintable() else f"\\U{ord(c):08x}")
        for c in value)
    return f'"{escaped}"'


def _comment(text: str) -> list[str]:
    return textwrap.wrap(text, _WIDTH - 2, initial_indent="# ", subsequent_indent="# ",
                         break_on_hyphens=False, break_long_words=False)


def _world_comment(info: LogInfo) -> str:
    plan = info.poses
    world = info.world_frame
    if plan is None or not plan.cameras:
        return "frame the reconstruction is in"
    first = plan.cameras[0]
    if first.via_tf:
        return f"frame the reconstruction is in: the cameras' TF chains lead to {world}"
    if not first.frame:
        return "frame the reconstruction is in: the camera poses name no frame (taken as it)"
    if first.frame == world:
        return "frame the reconstruction is in: the frame the camera poses are given in"
    return (f"frame the reconstruction is in: the camera poses are in {first.frame}, moved "
            f"into {world} through the TF tree")


def topics_toml(info: LogInfo) -> str:
    """A `[topics]` TOML block for the log (keys in the order of configs/default.toml), with
    a comment per key saying what was found; keys that were not found are commented out;
    what the log cannot tell is said in comments at the end."""
    comments = {
        "image": _role_comment(info, info.role("image")),
        "camera_info": _role_comment(info, info.role("camera_info")),
        "camera_pose": _role_comment(info, info.role("camera_pose")),
        "camera_frame": "camera optical frame pattern (its TF chain to world_frame, or the "
                        "images' frame id)",
        "tool_pose": _role_comment(info, info.role("tool_pose")),
        "tool_frame": "tool child frame (poses as transforms)",
        "joint_states": _role_comment(info, info.role("joint_states")),
        "world_frame": _world_comment(info),
    }
    lines = [f"# [topics] for {info.path.name}, written by `surgrecon info --write-config`.",
             "# Check the patterns; {camera} captures the camera id.", "[topics]"]
    for key in _KEY_ORDER:
        if key in info.topics:
            lines += _comment(comments[key])
            lines.append(f"{key} = {_quote(info.topics[key])}")
        elif key in ("image", "camera_info", "camera_pose"):
            lines.append(f"# {key}: no candidate found; set it by hand")
            lines.append(f"# {key} = \"\"")
    if info.topics.get("camera_pose", "").endswith(("ECM/measured_cp",
                                                     "ECM/position_cartesian_current")):
        lines += _comment("each camera's pose in the ECM's frame (hand-eye), x y z qx qy qz "
                          "qw per camera in sorted-id order: the log does not hold it")
        lines.append("# camera_from_ecm = [x, y, z, qx, qy, qz, qw, ...]")
    for topic in info.role("tool_pose").extra_tools:
        lines += ["", *_comment(f"another tool: {topic}; its geometry as in [tool] (keys "
                                "shaft_radius_m, shaft_length_m, jaw_offset_m, jaw_length_m, "
                                "jaw_width_m, shaft_axis): check them for your instrument"),
                  "[[tools]]", f"pose = {_quote(topic)}"]
    plan = info.poses
    world = info.world_frame
    for chain in plan.chains if plan is not None else ():
        if not chain.problem:
            continue
        lines.append("")
        if chain.who == "tool" and not chain.via_tf and chain.frame:
            lines += _comment(
                f"The tool pose on {chain.topic} is in frame {chain.frame!r}, which no TF "
                f"transform connects to {world!r}: ingest needs the pose of "
                f"{chain.frame!r} in {world!r} (x y z in m, quaternion qx qy qz qw). "
                "The log does not hold it, so `info` cannot write it: set it below, or set "
                "tool_pose = \"\" above to ingest without the robot.")
            lines += ["# [tool]", "# base_to_world = [x, y, z, qx, qy, qz, qw]"]
        else:
            lines += _comment(f"{chain.who}: {chain.problem}")
    return "\n".join(lines) + "\n"


def _role_comment(info: LogInfo, guess: RoleGuess) -> str:
    parts = [guess.role]
    if guess.cameras:
        parts.append(f"cameras {' '.join(guess.cameras)}")
    others = other_candidates(info.roles, guess)
    if others:
        parts.append(f"other candidates: {', '.join(others[:6])}")
    if guess.note:
        parts.append(guess.note)
    return "; ".join(parts)


def check_topics(info: LogInfo, topics: TopicsConfig,
                 base_to_world: tuple[float, ...] = ()) -> list[str]:
    """What the `[topics]` of a config miss in this log, one line each (empty: every role is
    found, with the same cameras for images, intrinsics and poses, and every pose connects
    to `topics.world_frame` as ingest composes it)."""
    roles = TopicRoles(topics)
    found: dict[str, list[tuple[ChannelInfo, str]]] = {r: [] for r in ROLES}
    problems = []
    for c in info.channels:
        for m in roles.match(c.topic):
            if c.kind in ROLE_KINDS[m.role]:
                found[m.role].append((c, m.camera))
            else:
                problems.append(f"topics.{m.role} = {roles.patterns[m.role]!r} matches "
                                f"{c.topic}, whose schema {c.schema_name!r} is not "
                                f"{m.role.replace('_', ' ')}")
    cameras: dict[str, set[str]] = {}
    for role in ROLES:
        pattern = roles.patterns.get(role, "")
        if not found[role]:
            if role in ("tool_pose", "joint_states") and not pattern:
                continue
            hint = " (or \"\" if the log has none)" if role in ("tool_pose",
                                                               "joint_states") else ""
            problems.append(f"topics.{role} = {pattern!r} matches no topic{hint}")
            continue
        ids: set[str] = set()
        for c, cam in found[role]:
            if c.kind != "transforms":
                ids.add(cam)
                continue
            key = "camera_frame" if role == "camera_pose" else "tool_frame"
            frames = info.tf_tree.frames if info.tf_tree is not None else c.child_frames
            if role == "camera_pose":
                ids.update(cid for f in frames if (cid := roles.camera_of_frame(f)) is not None)
            hit = [f for f in frames if (roles.camera_of_frame(f) is not None
                                          if role == "camera_pose" else roles.is_tool_frame(f))]
            if not hit:
                problems.append(f"topics.{key} = {getattr(topics, key)!r} matches no TF frame")
        if role in ("image", "camera_info", "camera_pose"):
            cameras[role] = {i for i in ids if i}
    if cameras.get("image"):
        for role in ("camera_info", "camera_pose"):
            lacking = sorted(cameras["image"] - cameras.get(role, set()))
            if role in cameras and lacking:
                problems.append(f"topics.{role} finds no topic/frame for camera(s) "
                                f"{', '.join(lacking)} of topics.image")
    posed = sort_ids(cameras.get("image", set()) & cameras.get("camera_pose", set()))
    plan = plan_poses(info.channels, info.tf_tree, topics, posed, bool(base_to_world))
    problems += grouped_problems(plan.chains)
    world = suggest_world(info.channels, info.tf_tree, topics, posed)
    if world != topics.world_frame and any(c.problem and c.found for c in plan.cameras):
        problems.append(f"the camera poses lead to {world!r}: set topics.world_frame = "
                        f"{world!r} if that is the world")
    return problems


def grouped_problems(chains: Sequence[PoseChain]) -> list[str]:
    """One line per distinct problem of the chains whose topic or frame was found, naming
    every camera (and the tool) that has it."""
    who: dict[str, list[str]] = {}
    for c in chains:
        if c.problem and c.found:
            who.setdefault(c.problem, []).append(c.who)
    lines = []
    for problem, names in who.items():
        cams = [n.removeprefix("camera ") for n in names if n != "tool"]
        label = [f"camera{'s' if len(cams) > 1 else ''} {', '.join(cams)}"] if cams else []
        lines.append(f"{' and '.join(label + ['tool'] * ('tool' in names))}: {problem}")
    return lines
