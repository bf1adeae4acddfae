"""What an MCAP log holds, for `surgrecon info`: channels, the TF tree, and which topics and
frames look like each `[topics]` role, with a starter `[topics]` config.

Fast: counts and log-time spans come from the summary and message indexes when the log has
them (`mcap.scan`); only transform messages are decoded in full, and of every other channel
that surgrecon can read only its first message (for its frame id and a detail such as the
image format). A log without indexes is streamed once.

Role guesses use schemas first (an image topic is one whose schema decodes to images) and
names second: camera ids are the part of the image topic names that differs between cameras
(`/endoscope_{camera}/color/compressed`), then the same ids are looked for in the intrinsics
and pose topics and in the TF frames; the tool is the remaining pose topic (or TF leaf frame)
whose name says tool, tip, psm, ...
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mcap.records import Channel, Message, Schema

from ..config import TopicsConfig
from ..core.tf_tree import TfTree, build_tf_tree
from ..errors import InputError
from .mcap.base import KINDS
from .mcap.registry import DECODERS, DESERIALIZERS, find_decoder
from .mcap.scan import ALL, FIRST, SKIP, ChannelScan, scan_mcap
from .mcap.topics import pattern_regex
from .mcap.transforms import TransformCollector, TransformLog, is_static_channel
from .records import CameraInfoRecord, ImageRecord, JointStateRecord, PoseRecord

ROLE_NAMES = ("image", "camera_info", "camera_pose", "tool_pose", "joint_states", "tf")
_TOKEN = re.compile(r"[A-Za-z0-9]+")
_TOOL_WORDS = ("tool", "tip", "psm", "instrument", "end_effector", "effector", "gripper",
               "jaw", "ee", "robot", "raven", "arm")
_IMAGE_WORDS = ("compressed", "color", "rgb", "rect")
_POSE_WORDS = ("pose", "navigation", "tracker", "tracking", "endoscope", "camera")
_CAMERA_FRAME_WORDS = ("optical",)


@dataclass(frozen=True)
class ChannelInfo:
    """One channel: `kind` what its schema carries ("" if surgrecon cannot read it), message
    count, log times (ns) of the first and last message (-1 if none), mean rate (Hz), the
    first message's frame id ("" if none or not read), a short `detail`, and for transform
    channels `static` (latched) and the child frames."""

    topic: str
    schema_name: str
    message_encoding: str
    kind: str
    count: int
    first_ns: int
    last_ns: int
    rate_hz: float
    frame_id: str = ""
    detail: str = ""
    static: bool = False
    child_frames: tuple[str, ...] = ()

    @property
    def span_s(self) -> float:
        """Seconds from the first to the last message (0 with fewer than two)."""
        return (self.last_ns - self.first_ns) * 1e-9 if self.count > 1 else 0.0


@dataclass(frozen=True)
class RoleGuess:
    """The candidate topics of one role (`ROLE_NAMES`): `topics` every channel of a fitting
    schema, `pattern` the chosen `[topics]` value ("" none), `cameras` the ids it captures,
    `frames` the frame ids found (image / intrinsics frame ids, or TF child frames),
    `parent_frames` the frames that pose topics are given in, `frame_pattern` the
    `camera_frame`/`tool_frame` value when poses come as transforms, `note` a remark."""

    role: str
    topics: tuple[str, ...] = ()
    pattern: str = ""
    cameras: tuple[str, ...] = ()
    frames: tuple[str, ...] = ()
    frame_pattern: str = ""
    note: str = ""
    parent_frames: tuple[str, ...] = ()


@dataclass(frozen=True)
class LogInfo:
    """Everything `surgrecon info` prints; `topics` is the suggested `[topics]` block
    ({key: value}, only keys that were found) and `world_frame` the root of the camera
    frames in the TF tree ("" without one)."""

    path: Path
    size: int
    profile: str
    library: str
    indexed: bool
    damage: str | None
    channels: tuple[ChannelInfo, ...]
    tf_tree: TfTree | None
    tf_error: str
    roles: tuple[RoleGuess, ...]
    topics: dict[str, str] = field(default_factory=dict)
    world_frame: str = ""

    @property
    def message_count(self) -> int:
        return sum(c.count for c in self.channels)

    @property
    def start_ns(self) -> int:
        return min((c.first_ns for c in self.channels if c.count), default=-1)

    @property
    def end_ns(self) -> int:
        return max((c.last_ns for c in self.channels if c.count), default=-1)

    def role(self, name: str) -> RoleGuess:
        return next(r for r in self.roles if r.role == name)


# -- scanning --------------------------------------------------------------------------------
class _FirstMessages:
    """Decodes the first message of each readable non-transform channel: kind, frame, detail."""

    def __init__(self) -> None:
        self._deserializers: dict[str, Any] = {}
        self.found: dict[int, tuple[str, str, str]] = {}  # channel id -> kind, frame, detail

    def select(self, channel: Channel, schema: Schema | None) -> str:
        name = schema.name if schema else ""
        return FIRST if find_decoder(channel.message_encoding, name, KINDS) else SKIP

    def add(self, channel: Channel, schema: Schema | None, message: Message) -> None:
        name = schema.name if schema else ""
        decoder = find_decoder(channel.message_encoding, name, KINDS)
        if decoder is None:
            return
        enc = channel.message_encoding
        try:
            if enc not in self._deserializers:
                self._deserializers[enc] = DESERIALIZERS[enc]()
            records = decoder.convert(self._deserializers[enc].for_schema(schema)(message.data))
        except Exception as exc:  # third-party decoders raise anything on malformed bytes
            if (enc, name) in DECODERS:
                self.found[channel.id] = (decoder.kind, "", "first message does not decode "
                                                            f"({type(exc).__name__})")
            return  # generic JSON that is not joint states
        record = records[0] if records else None
        if decoder.kind == "joint_states" and not (
                isinstance(record, JointStateRecord) and len(record.positions)):
            if (enc, name) in DECODERS:
                self.found[channel.id] = (decoder.kind, "", "no joints")
            return
        self.found[channel.id] = (decoder.kind, *_frame_and_detail(record))


def _frame_and_detail(record: Any) -> tuple[str, str]:
    if isinstance(record, ImageRecord):
        if record.width:
            return record.frame_id, f"{record.width}x{record.height} {record.format}"
        return record.frame_id, record.format
    if isinstance(record, CameraInfoRecord):
        return record.frame_id, f"{record.width}x{record.height} {record.distortion_model}"
    if isinstance(record, PoseRecord):
        return record.frame_id, f"in {record.frame_id}" if record.frame_id else ""
    if isinstance(record, JointStateRecord):
        return "", f"{len(record.positions)} joints"
    return "", ""


def scan_log(path: Path, time_source: str = "header") -> LogInfo:
    """Scan the MCAP log at `path` (see the module docstring). Damage does not raise: what was
    read before it is described and `damage` says where it is. Raises InputError when the
    file is not MCAP or a transform message does not decode."""
    path = Path(path)
    transforms = TransformCollector(path, use_log_time=time_source == "log_time")
    firsts = _FirstMessages()

    def select(channel: Channel, schema: Schema | None) -> str:
        if transforms.select(channel, schema) == ALL:
            return ALL
        return firsts.select(channel, schema)

    def on_message(channel: Channel, schema: Schema | None, message: Message) -> None:
        if select(channel, schema) == ALL:
            transforms.add(channel, schema, message)
        else:
            firsts.add(channel, schema, message)

    scan = scan_mcap(path, select, on_message)
    tf_log = transforms.result(scan)
    channels = tuple(_channel_info(c, firsts.found.get(c.id), tf_log) for c in scan.channels)
    tree, tf_error = None, ""
    if tf_log.topics:
        try:
            tree = build_tf_tree(tf_log.samples)
        except InputError as exc:
            tf_error = str(exc)
    roles, topics, world = guess_roles(channels, tree)
    return LogInfo(path, scan.size, scan.profile, scan.library, scan.indexed, scan.damage,
                   channels, tree, tf_error, roles, topics, world)


def _channel_info(c: ChannelScan, first: tuple[str, str, str] | None, tf_log: TransformLog
                  ) -> ChannelInfo:
    rate = 0.0
    if c.count > 1 and c.last_log_ns > c.first_log_ns:
        rate = (c.count - 1) / ((c.last_log_ns - c.first_log_ns) * 1e-9)
    if c.topic in tf_log.topics and find_decoder(c.message_encoding, c.schema_name,
                                                 ("transforms",)):
        frames = tf_log.child_frames.get(c.topic, ())
        static = is_static_channel(c.topic, c.metadata)
        detail = (f"{tf_log.counts.get(c.topic, 0)} transforms, {len(frames)} child frames"
                  + (", static" if static else ""))
        return ChannelInfo(c.topic, c.schema_name, c.message_encoding, "transforms", c.count,
                           c.first_log_ns, c.last_log_ns, rate, "", detail, static, frames)
    kind, frame, detail = first or ("", "", "")
    return ChannelInfo(c.topic, c.schema_name, c.message_encoding, kind, c.count,
                       c.first_log_ns, c.last_log_ns, rate, frame, detail)


# -- camera-id patterns (pure) ---------------------------------------------------------------
def captures(pattern: str, names: Iterable[str]) -> dict[str, str]:
    """{name: camera id} of the names that `pattern` (with `{camera}`) matches in full."""
    regex = pattern_regex(pattern)
    out = {}
    for name in names:
        m = regex.match(name)
        if m is not None:
            out[name] = m.groupdict().get("camera") or ""
    return out


def _candidates(names: Sequence[str], ids: Iterable[str]) -> set[str]:
    """Templates made by putting `{camera}` in place of one name token (a run of letters and
    digits) or of one occurrence of a known id."""
    out = set()
    for name in names:
        for m in _TOKEN.finditer(name):
            out.add(name[: m.start()] + "{camera}" + name[m.end():])
        for cam in ids:
            if cam:
                for m in re.finditer(re.escape(cam), name):
                    out.add(name[: m.start()] + "{camera}" + name[m.end():])
    return {t for t in out if t.count("{camera}") == 1}


def camera_pattern(
    names: Sequence[str],
    ids: Sequence[str] = (),
    prefer: Sequence[str] = (),
    leaves: frozenset[str] | None = None,
) -> tuple[str, dict[str, str]]:
    """The `{camera}` pattern that best explains `names`, and its {name: id} captures.

    Without `ids`: the pattern capturing the most distinct ids (the varying part of the
    names). With `ids` (the cameras found from another role): the one capturing most of them
    and fewest others; ("", {}) if none captures any. Ties: more `prefer` words in the
    pattern, more captured names in `leaves`, ids with digits, shorter ids, then the
    alphabetically first pattern.
    """
    known = set(ids)
    best: tuple[Any, ...] | None = None
    chosen: tuple[str, dict[str, str]] = ("", {})
    for template in sorted(_candidates(names, known)):
        caps = captures(template, names)
        got = set(caps.values())
        if known:
            primary: tuple[int, ...] = (len(got & known), -len(got - known))
            if not got & known:
                continue
        else:
            primary = (len(got),)
        lower = template.lower()
        key = (
            *primary,
            sum(w in lower for w in prefer),
            sum(n in leaves for n in caps) if leaves is not None else 0,
            all(any(ch.isdigit() for ch in g) for g in got),
            -sum(len(g) for g in got),
        )
        if best is None or key > best:
            best, chosen = key, (template, caps)
    return chosen


def _sort_ids(ids: Iterable[str]) -> tuple[str, ...]:
    """Camera ids sorted naturally (numbers by value)."""
    return tuple(sorted(set(ids), key=lambda s: (not s.isdigit(), int(s) if s.isdigit() else 0,
                                                 s)))


def _word_score(name: str, words: Sequence[str]) -> int:
    """How many of `words` the name holds: as a token, as the start of a token (3+ letters),
    or, for words with `_`, anywhere."""
    lower = name.lower()
    tokens = [t for t in re.split(r"[^a-z0-9]+", lower) if t]
    return sum(1 for w in words if w in tokens or ("_" in w and w in lower) or (
        len(w) >= 3 and any(t.startswith(w) for t in tokens)))


# -- roles -----------------------------------------------------------------------------------
def guess_roles(channels: Sequence[ChannelInfo], tree: TfTree | None
                ) -> tuple[tuple[RoleGuess, ...], dict[str, str], str]:
    """Role guesses, the suggested `[topics]` values and the world frame ("" unknown)."""
    by_kind: dict[str, list[ChannelInfo]] = {}
    for c in channels:
        by_kind.setdefault(c.kind, []).append(c)
    topics: dict[str, str] = {}
    roles: dict[str, RoleGuess] = {}

    images = by_kind.get("image", [])
    image_names = sorted(c.topic for c in images)
    image_pattern, image_caps = camera_pattern(image_names, prefer=_IMAGE_WORDS)
    ids = _sort_ids(image_caps.values())
    image_frames = [c.frame_id for c in images if c.topic in image_caps and c.frame_id]
    frame_from_images, _ = camera_pattern(image_frames, ids) if image_frames else ("", {})
    roles["image"] = RoleGuess("image", tuple(image_names), image_pattern, ids,
                               tuple(sorted(set(image_frames))), frame_from_images)
    if image_pattern:
        topics["image"] = image_pattern

    infos = by_kind.get("camera_info", [])
    info_names = sorted(c.topic for c in infos)
    info_pattern, info_caps = camera_pattern(info_names, ids) if ids else camera_pattern(
        info_names)
    roles["camera_info"] = RoleGuess(
        "camera_info", tuple(info_names), info_pattern, _sort_ids(info_caps.values()),
        tuple(sorted({c.frame_id for c in infos if c.topic in info_caps and c.frame_id})),
        note=_missing(ids, info_caps.values()))
    if info_pattern:
        topics["camera_info"] = info_pattern

    poses = by_kind.get("pose", [])
    pose_names = sorted(c.topic for c in poses)
    pose_pattern, pose_caps = (camera_pattern(pose_names, ids, prefer=_POSE_WORDS)
                               if ids else ("", {}))
    tf_channels = sorted(by_kind.get("transforms", []), key=lambda c: c.topic)
    tf_guess = _tf_cameras(tree, tf_channels, ids, frame_from_images) if tree else None
    world = ""
    use_tf = tf_guess is not None and len(set(tf_guess[2].values())) > len(
        set(pose_caps.values()))
    if use_tf and tf_guess is not None:
        tf_topic, frame_pattern, frame_caps, world = tf_guess
        roles["camera_pose"] = RoleGuess(
            "camera_pose", (tf_topic, *pose_names), tf_topic, _sort_ids(frame_caps.values()),
            tuple(sorted(frame_caps)), frame_pattern,
            note=_join("through the TF tree", _missing(ids, frame_caps.values())),
            parent_frames=(world,))
        topics["camera_pose"] = tf_topic
        topics["camera_frame"] = frame_pattern
        pose_caps = {}
    else:
        pose_frames = tuple(sorted({c.frame_id for c in poses if c.topic in pose_caps
                                    and c.frame_id}))
        roles["camera_pose"] = RoleGuess(
            "camera_pose", tuple(pose_names), pose_pattern, _sort_ids(pose_caps.values()),
            note=_missing(ids, pose_caps.values()), parent_frames=pose_frames)
        if pose_pattern:
            topics["camera_pose"] = pose_pattern
            if frame_from_images:
                topics["camera_frame"] = frame_from_images
            if len(pose_frames) == 1:
                world = pose_frames[0]

    tool_names = [n for n in pose_names if n not in pose_caps]
    roles["tool_pose"], tool_keys = _tool(tool_names, poses, tree, tf_channels,
                                          roles["camera_pose"])
    topics.update(tool_keys)

    joints = by_kind.get("joint_states", [])
    joint_names = sorted((c.topic for c in joints),
                         key=lambda n: (-_word_score(n, ("joint", "joints", "states")), n))
    roles["joint_states"] = RoleGuess("joint_states", tuple(joint_names),
                                      joint_names[0] if joint_names else "")
    if joint_names:
        topics["joint_states"] = joint_names[0]

    roles["tf"] = RoleGuess(
        "tf", tuple(c.topic for c in tf_channels), "", (),
        tuple(sorted({f for c in tf_channels for f in c.child_frames})),
        note=", ".join(f"{c.topic} {'static' if c.static else 'dynamic'}" for c in tf_channels))
    return tuple(roles[r] for r in ROLE_NAMES), topics, world


def _missing(ids: Sequence[str], got: Iterable[str]) -> str:
    lacking = [i for i in ids if i not in set(got)]
    return f"no topic for camera(s) {', '.join(lacking)}" if lacking else ""


def _join(*parts: str) -> str:
    return "; ".join(p for p in parts if p)


def _publisher(tree: TfTree, frame: str, tf_channels: Sequence[ChannelInfo]) -> str:
    """The transform topic publishing most dynamic edges on the chain from `frame` to its
    root (a static topic if the chain is all static)."""
    chain = set()
    while (edge := tree.edge(frame)) is not None:
        chain.add((edge.child, edge.static))
        frame = edge.parent
    best = max(tf_channels, key=lambda c: (
        sum(1 for child, static in chain if not static and child in c.child_frames),
        sum(1 for child, _ in chain if child in c.child_frames), not c.static, c.topic == "/tf"))
    return best.topic


def _tf_cameras(tree: TfTree, tf_channels: Sequence[ChannelInfo], ids: Sequence[str],
                from_images: str) -> tuple[str, str, dict[str, str], str] | None:
    """(pose topic, camera_frame pattern, {frame: id}, world frame) from the TF tree."""
    if not ids or not tf_channels:
        return None
    frames = tree.frames
    caps = captures(from_images, frames) if from_images else {}
    pattern = from_images
    if not set(caps.values()) & set(ids):
        leaves = frozenset(f for f in frames if not tree.children(f))
        pattern, caps = camera_pattern(frames, ids, prefer=_CAMERA_FRAME_WORDS, leaves=leaves)
    if not pattern:
        return None
    first = sorted(caps)[0]
    world = tree.root_of(first)
    return _publisher(tree, first, tf_channels), pattern, caps, world


def _tool(names: Sequence[str], poses: Sequence[ChannelInfo], tree: TfTree | None,
          tf_channels: Sequence[ChannelInfo], camera: RoleGuess
          ) -> tuple[RoleGuess, dict[str, str]]:
    scored = sorted(names, key=lambda n: (-_word_score(n, _TOOL_WORDS), n))
    if scored and (_word_score(scored[0], _TOOL_WORDS) > 0 or len(scored) == 1):
        topic = scored[0]
        frame = next((c.frame_id for c in poses if c.topic == topic and c.frame_id), "")
        note = "" if _word_score(topic, _TOOL_WORDS) > 0 else "guessed: the only other pose topic"
        return RoleGuess("tool_pose", tuple(scored), topic, note=note,
                         parent_frames=(frame,) if frame else ()), {"tool_pose": topic}
    if tree is not None and tf_channels:
        camera_frames = set(camera.frames)
        above = set()
        for f in camera_frames:
            while (edge := tree.edge(f)) is not None:
                above.add(edge.parent)
                f = edge.parent
        leaves = [f for f in tree.frames if not tree.children(f) and tree.edge(f) is not None
                  and f not in camera_frames and f not in above]
        ranked = sorted(leaves, key=lambda f: (-_word_score(f, _TOOL_WORDS), f))
        if ranked and _word_score(ranked[0], _TOOL_WORDS) > 0:
            frame = ranked[0]
            topic = _publisher(tree, frame, tf_channels)
            return (RoleGuess("tool_pose", (topic, *scored), topic, (), tuple(ranked), frame,
                              note="through the TF tree", parent_frames=(tree.root_of(frame),)),
                    {"tool_pose": topic, "tool_frame": frame})
    note = "no tool pose found: tool_pose = \"\" (no robot, tool removal off)"
    return RoleGuess("tool_pose", tuple(scored), "", note=note), {"tool_pose": ""}


# -- config ----------------------------------------------------------------------------------
_KEY_ORDER = ("image", "camera_info", "camera_pose", "camera_frame", "tool_pose", "tool_frame",
              "joint_states")


def _quote(value: str) -> str:
    """A TOML basic string (control characters escaped)."""
    escaped = "".join(
        {"\\": "\\\\", '"': '\\"'}.get(c) or (c if c.isprintable() else f"\\U{ord(c):08x}")
        for c in value)
    return f'"{escaped}"'


def topics_toml(info: LogInfo) -> str:
    """A `[topics]` TOML block for the log (keys in the order of configs/default.toml), with
    a comment per key saying what was found; keys that were not found are commented out."""
    comments = {
        "image": _role_comment(info, info.role("image")),
        "camera_info": _role_comment(info, info.role("camera_info")),
        "camera_pose": _role_comment(info, info.role("camera_pose")),
        "camera_frame": "camera child frame pattern (poses as transforms)",
        "tool_pose": _role_comment(info, info.role("tool_pose")),
        "tool_frame": "tool child frame (poses as transforms)",
        "joint_states": _role_comment(info, info.role("joint_states")),
    }
    lines = [f"# [topics] for {info.path.name}, written by `surgrecon info --write-config`.",
             "# Check the patterns; {camera} captures the camera id.", "[topics]"]
    for key in _KEY_ORDER:
        if key in info.topics:
            lines.append(f"# {comments[key]}")
            lines.append(f"{key} = {_quote(info.topics[key])}")
        elif key in ("image", "camera_info", "camera_pose"):
            lines.append(f"# {key}: no candidate found; set it by hand")
            lines.append(f"# {key} = \"\"")
    if info.world_frame and info.world_frame != "world":
        lines.append(f"# the cameras' TF root is {info.world_frame!r}: set world_frame to it")
    return "\n".join(lines) + "\n"


def other_candidates(info: LogInfo, guess: RoleGuess) -> list[str]:
    """Candidate topics of a role that no chosen `[topics]` value matches."""
    chosen = [r.pattern for r in info.roles if r.pattern]
    return [t for t in guess.topics if not any(captures(p, [t]) for p in chosen)]


def _role_comment(info: LogInfo, guess: RoleGuess) -> str:
    parts = [guess.role]
    if guess.cameras:
        parts.append(f"cameras {' '.join(guess.cameras)}")
    others = other_candidates(info, guess)
    if others:
        parts.append(f"other candidates: {', '.join(others[:6])}")
    if guess.note:
        parts.append(guess.note)
    return "; ".join(parts)



# -- config check ----------------------------------------------------------------------------
def check_topics(info: LogInfo, topics: TopicsConfig) -> list[str]:
    """What the `[topics]` of a config miss in this log, one line each (empty: every role is
    found, with the same cameras for images, intrinsics and poses)."""
    from .mcap.topics import ROLE_KINDS, ROLES, TopicRoles

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
        pattern = roles.patterns[role]
        if not found[role]:
            if role == "tool_pose" and not pattern:
                continue
            optional = " (optional)" if role == "joint_states" else ""
            problems.append(f"topics.{role} = {pattern!r} matches no topic{optional}")
            continue
        ids: set[str] = set()
        for c, cam in found[role]:
            if c.kind != "transforms":
                ids.add(cam)
                continue
            key = "camera_frame" if role == "camera_pose" else "tool_frame"
            frames = info.tf_tree.frames if info.tf_tree is not None else c.child_frames
            if role == "camera_pose":
                ids.update(cam_id for f in frames
                           if (cam_id := roles.camera_of_frame(f)) is not None)
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
    return problems
