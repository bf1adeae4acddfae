"""Which topics and frames look like each `[topics]` role, from the channels and the TF tree.

Schemas first (an image topic is one whose schema decodes to images), names second: camera
ids are the part of the image topic names that differs between cameras, then the same ids
are looked for in the intrinsics and pose topics and in the TF frames; the tool is the
remaining pose topic (or TF leaf frame) whose name says tool, tip, psm, ... A robot role the
log does not record is suggested as "" (`tool_pose = ""`, `joint_states = ""`), which
ingest takes as "no robot" / "no joints".
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

from ..config.schema import CAMERA_INFO_POSES
from ..core.sync.tf_tree import TfTree
from .channels import ChannelInfo
from .dvrk import dvrk_arms, psm_topics
from .patterns import camera_pattern, captures, sort_ids, word_score

ROLE_NAMES = ("image", "camera_info", "camera_pose", "tool_pose", "joint_states", "tf")
_TOOL_WORDS = ("tool", "tip", "psm", "instrument", "end_effector", "effector", "gripper",
               "jaw", "ee", "robot", "raven", "arm")
_IMAGE_WORDS = ("compressed", "color", "rgb", "rect")
_POSE_WORDS = ("pose", "navigation", "tracker", "tracking", "endoscope", "camera")
_CAMERA_FRAME_WORDS = ("optical",)


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
    extra_tools: tuple[str, ...] = ()  # tool_pose: more tools' topics (`[[tools]]`)


def guess_roles(channels: Sequence[ChannelInfo], tree: TfTree | None
                ) -> tuple[tuple[RoleGuess, ...], dict[str, str]]:
    """Role guesses (in `ROLE_NAMES` order) and the suggested `[topics]` values."""
    by_kind: dict[str, list[ChannelInfo]] = {}
    for c in channels:
        by_kind.setdefault(c.kind, []).append(c)
    topics: dict[str, str] = {}
    roles: dict[str, RoleGuess] = {}

    images = by_kind.get("image", [])
    image_names = sorted(c.topic for c in images)
    image_pattern, image_caps = camera_pattern(image_names, prefer=_IMAGE_WORDS)
    ids = sort_ids(image_caps.values())
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
        "camera_info", tuple(info_names), info_pattern, sort_ids(info_caps.values()),
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
    if tf_guess is not None and len(set(tf_guess[2].values())) > len(set(pose_caps.values())):
        tf_topic, frame_pattern, frame_caps, root = tf_guess
        roles["camera_pose"] = RoleGuess(
            "camera_pose", (tf_topic, *pose_names), tf_topic, sort_ids(frame_caps.values()),
            tuple(sorted(frame_caps)), frame_pattern,
            note=_join("through the TF tree", _missing(ids, frame_caps.values())),
            parent_frames=(root,))
        topics["camera_pose"] = tf_topic
        topics["camera_frame"] = frame_pattern
        pose_caps = {}
    else:
        pose_frames = tuple(sorted({c.frame_id for c in poses if c.topic in pose_caps
                                    and c.frame_id}))
        roles["camera_pose"] = RoleGuess(
            "camera_pose", tuple(pose_names), pose_pattern, sort_ids(pose_caps.values()),
            note=_missing(ids, pose_caps.values()), parent_frames=pose_frames)
        if pose_pattern:
            topics["camera_pose"] = pose_pattern
            if frame_from_images:
                topics["camera_frame"] = frame_from_images
        elif len(info_caps) > 1 and any(c.stereo_baseline_m > 0 for c in infos
                                        if c.topic in info_caps) and not tf_channels:
            baseline = max(c.stereo_baseline_m for c in infos if c.topic in info_caps)
            roles["camera_pose"] = RoleGuess(
                "camera_pose", tuple(pose_names), CAMERA_INFO_POSES, ids,
                note=f"no pose topic: a stereo rig fixed in the world, placed by its "
                     f"CameraInfo R and P (baseline {baseline * 1e3:.1f} mm)")
            topics["camera_pose"] = CAMERA_INFO_POSES
        elif "ECM" in dvrk_arms(pose_names):
            ecm = dvrk_arms(pose_names)["ECM"]
            roles["camera_pose"] = RoleGuess(
                "camera_pose", tuple(pose_names), ecm, ids,
                note="the dVRK ECM's pose: set each camera's hand-eye pose on it in "
                     "topics.camera_from_ecm (x y z qx qy qz qw per camera, sorted ids)")
            topics["camera_pose"] = ecm

    tool_names = [n for n in pose_names if n not in pose_caps]
    roles["tool_pose"], tool_keys = _tool(tool_names, poses, tree, tf_channels,
                                          roles["camera_pose"])
    topics.update(tool_keys)

    joints = by_kind.get("joint_states", [])
    joint_names = sorted((c.topic for c in joints),
                         key=lambda n: (-word_score(n, ("joint", "joints", "states")), n))
    roles["joint_states"] = RoleGuess(
        "joint_states", tuple(joint_names), joint_names[0] if joint_names else "",
        note="" if joint_names else "no joint states found: joint_states = \"\"")
    topics["joint_states"] = joint_names[0] if joint_names else ""

    roles["tf"] = RoleGuess(
        "tf", tuple(c.topic for c in tf_channels), "", (),
        tuple(sorted({f for c in tf_channels for f in c.child_frames})),
        note=", ".join(f"{c.topic} {'static' if c.static else 'dynamic'}" for c in tf_channels))
    return tuple(roles[r] for r in ROLE_NAMES), topics


def other_candidates(roles: Sequence[RoleGuess], guess: RoleGuess) -> list[str]:
    """Candidate topics of a role that no chosen `[topics]` value matches."""
    chosen = [r.pattern for r in roles if r.pattern]
    return [t for t in guess.topics if not any(captures(p, [t]) for p in chosen)]


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
    """(pose topic, camera_frame pattern, {frame: id}, root frame) from the TF tree."""
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
    return _publisher(tree, first, tf_channels), pattern, caps, tree.root_of(first)


def _tool(names: Sequence[str], poses: Sequence[ChannelInfo], tree: TfTree | None,
          tf_channels: Sequence[ChannelInfo], camera: RoleGuess
          ) -> tuple[RoleGuess, dict[str, str]]:
    scored = sorted(names, key=lambda n: (-word_score(n, _TOOL_WORDS), n))
    arms = dvrk_arms(names)
    psms = psm_topics(names)
    if psms:
        ecm = (f"; ECM on {arms['ECM']}: the endoscope's pose, the cameras' only with the "
               "hand-eye transform" if "ECM" in arms else "")
        note = (f"dVRK arms {' '.join(arms)}: {psms[0]} the tool, "
                f"{' '.join(psms[1:]) or 'no other PSM'} as [[tools]]{ecm}")
        return (RoleGuess("tool_pose", tuple(scored), psms[0], note=note,
                          extra_tools=tuple(psms[1:])), {"tool_pose": psms[0]})
    if scored and (word_score(scored[0], _TOOL_WORDS) > 0 or len(scored) == 1):
        topic = scored[0]
        frame = next((c.frame_id for c in poses if c.topic == topic and c.frame_id), "")
        note = "" if word_score(topic, _TOOL_WORDS) > 0 else "guessed: the only other pose topic"
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
        ranked = sorted(leaves, key=lambda f: (-word_score(f, _TOOL_WORDS), f))
        if ranked and word_score(ranked[0], _TOOL_WORDS) > 0:
            frame = ranked[0]
            topic = _publisher(tree, frame, tf_channels)
            return (RoleGuess("tool_pose", (topic, *scored), topic, (), tuple(ranked), frame,
                              note="through the TF tree", parent_frames=(tree.root_of(frame),)),
                    {"tool_pose": topic, "tool_frame": frame})
    note = "no tool pose found: tool_pose = \"\" (no robot, tool removal off)"
    return RoleGuess("tool_pose", tuple(scored), "", note=note), {"tool_pose": ""}
