"""How ingest will get each camera's and the tool's pose in `topics.world_frame`, for a given
`[topics]` (as stages/ingest_frames.py composes them), and which world frame fits the log.

A pose role whose topic carries transforms gives the TF chain from `camera_frame` /
`tool_frame` up the tree to the world (down again if the world is not an ancestor); a pose
topic gives its poses in the frame its messages name, moved into the world through the TF
tree when that frame is another one. The tool pose in a frame no transform connects to the
world needs `tool.base_to_world`, which a log does not hold.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass

from ..config import TopicsConfig
from ..config.schema import CAMERA_INFO_POSES
from ..core.sync.tf_tree import TfTree
from ..io.logs.topics import TopicRoles
from .channels import ChannelInfo

WORLD = "world"


def _rate(rate_hz: float, before: str = "") -> str:
    """"40.0 Hz" (after `before`), or "" for no rate (one message, or a burst)."""
    return f"{before}{rate_hz:.1f} Hz" if rate_hz > 0 else ""


@dataclass(frozen=True)
class Hop:
    """One step of a chain, from frame `start` to frame `end` over one TF edge: `up` when
    `start` is the edge's child (its transform as published), else down it (its inverse)."""

    start: str
    end: str
    static: bool
    rate_hz: float
    up: bool = True

    def text(self) -> str:
        kind = "static" if self.static else f"dynamic{_rate(self.rate_hz, ' ')}"
        return f" -({kind}{'' if self.up else ', inverted'})-> {self.end}"


@dataclass(frozen=True)
class PoseChain:
    """Where one pose comes from: `who` ("camera 0", "tool"); `topic` the pose or transform
    topic; `frame` the camera / tool frame (`via_tf`) or the frame the pose messages are
    given in ("" unnamed); `rate_hz` the pose topic's rate; `hops` the TF edges from
    `frame` to `world`; `problem` why ingest cannot compose it ("" when it can); `note`;
    `found` False when the topic or the TF frame itself is missing (the config check
    reports that per role)."""

    who: str
    topic: str
    frame: str
    via_tf: bool
    world: str
    rate_hz: float = 0.0
    hops: tuple[Hop, ...] = ()
    problem: str = ""
    note: str = ""
    found: bool = True  # False: its topic or TF frame is not in the log

    def text(self) -> str:
        """`optical -(static)-> marker -(dynamic 40.0 Hz)-> tracker -(static)-> world`, or
        `/pose/topic (40.0 Hz) in tracker -(static)-> world` for a pose topic."""
        if self.via_tf:
            head = self.frame
        elif self.topic == CAMERA_INFO_POSES:
            head = f"its CameraInfo R and P, fixed in {self.world}"
        else:
            rate = _rate(self.rate_hz)
            head = (f"{self.topic}{f' ({rate})' if rate else ''} in "
                    f"{self.frame or f'{self.world} (no frame id)'}")
        return head + "".join(h.text() for h in self.hops)


@dataclass(frozen=True)
class PosePlan:
    """The chains of every camera (by id) and of the tool (None without a robot)."""

    world: str
    cameras: tuple[PoseChain, ...]
    tool: PoseChain | None

    @property
    def chains(self) -> tuple[PoseChain, ...]:
        return (*self.cameras, *((self.tool,) if self.tool is not None else ()))

    @property
    def problems(self) -> list[str]:
        return [f"{c.who}: {c.problem}" for c in self.chains if c.problem]


def _matching(channels: Sequence[ChannelInfo], roles: TopicRoles, role: str
              ) -> list[tuple[ChannelInfo, str]]:
    return [(c, m.camera) for c in channels for m in roles.match(c.topic) if m.role == role]


def _connect(tree: TfTree | None, world: str, frame: str) -> tuple[tuple[Hop, ...], str]:
    """The hops from `frame` to `world` through the tree, or a problem."""
    if frame == world:
        return (), ""
    if tree is None:
        return (), f"the log has no TF tree to connect frame {frame!r} to {world!r}"
    known = set(tree.frames)
    if frame not in known:
        return (), f"frame {frame!r} is not in the TF tree"
    if world not in known:
        root = tree.root_of(frame)
        under = f" ({frame!r} is under {root!r})" if frame != root else ""
        return (), (f"world frame {world!r} is not in the TF tree{under}: set "
                    f"topics.world_frame = {root!r}")
    if not tree.is_connected(world, frame):
        return (), (f"frame {frame!r} is in the TF tree under {tree.root_of(frame)!r}, not "
                    f"connected to {world!r}")
    up, down = tree.chain(world, frame)
    hops = [Hop(e.child, e.parent, e.static, e.rate_hz) for e in up]
    hops += [Hop(e.parent, e.child, e.static, e.rate_hz, up=False) for e in reversed(down)]
    return tuple(hops), ""


def _anchors(channels: Sequence[ChannelInfo], tree: TfTree | None, topics: TopicsConfig,
             cameras: Sequence[str]) -> list[str]:
    """The frames the cameras' poses start from: their TF frames, or the frames their pose
    messages are given in (unnamed ones left out)."""
    roles = TopicRoles(topics)
    found = _matching(channels, roles, "camera_pose")
    if any(c.kind == "transforms" for c, _ in found):
        frames = [topics.camera_frame.replace("{camera}", cid) for cid in cameras]
        return [f for f in frames if tree is not None and f in tree.frames]
    return [c.frame_id for c, cid in found if c.kind == "pose" and c.frame_id
            and (cid in cameras or not cameras)]


def suggest_world(channels: Sequence[ChannelInfo], tree: TfTree | None, topics: TopicsConfig,
                  cameras: Sequence[str]) -> str:
    """The world frame for these `[topics]`: "world" when every camera's frame connects to
    it (or the poses name no frame), else the root of the cameras' TF tree, or the one frame
    their pose messages are given in when no tree holds it (the most common one if the
    cameras disagree)."""
    anchors = _anchors(channels, tree, topics, cameras)
    if not anchors:
        return WORLD
    known = set(tree.frames) if tree is not None else set()

    def world_of(frame: str) -> str:
        if frame not in known:
            return frame
        if WORLD in known and tree is not None and tree.is_connected(WORLD, frame):
            return WORLD
        return tree.root_of(frame) if tree is not None else frame

    votes = Counter(world_of(f) for f in anchors)
    return min(votes, key=lambda w: (-votes[w], w != WORLD, w))


def plan_poses(channels: Sequence[ChannelInfo], tree: TfTree | None, topics: TopicsConfig,
               cameras: Sequence[str], base_to_world: bool = False) -> PosePlan:
    """The chain of each camera in `cameras` and of the tool, in `topics.world_frame`, as
    ingest composes them with these `[topics]` (and `tool.base_to_world` set or not)."""
    roles = TopicRoles(topics)
    world = topics.world_frame
    found = _matching(channels, roles, "camera_pose")
    tf_topics = [c.topic for c, _ in found if c.kind == "transforms"]
    out = []
    for cid in cameras:
        who = f"camera {cid}"
        if topics.poses_from_camera_info:
            out.append(PoseChain(who, CAMERA_INFO_POSES, "", False, world))
            continue
        if tf_topics:
            frame = topics.camera_frame.replace("{camera}", cid)
            hops, problem = _connect(tree, world, frame)
            out.append(PoseChain(who, tf_topics[0], frame, True, world, 0.0, hops, problem,
                                 found=tree is not None and frame in tree.frames))
            continue
        channel = next((c for c, got in found if got == cid and c.kind == "pose"), None)
        if channel is None:
            out.append(PoseChain(who, topics.camera_pose, "", False, world, problem=(
                f"no pose topic matches topics.camera_pose = {topics.camera_pose!r}"),
                found=False))
            continue
        hops, problem = _connect(tree, world, channel.frame_id or world)
        out.append(PoseChain(who, channel.topic, channel.frame_id, False, world,
                             channel.rate_hz, hops, problem))
    return PosePlan(world, tuple(out), _tool_chain(channels, tree, topics, roles,
                                                    base_to_world))


def _tool_chain(channels: Sequence[ChannelInfo], tree: TfTree | None, topics: TopicsConfig,
                roles: TopicRoles, base_to_world: bool) -> PoseChain | None:
    if not topics.tool_pose:
        return None
    world = topics.world_frame
    found = [c for c, _ in _matching(channels, roles, "tool_pose")]
    transforms = [c for c in found if c.kind == "transforms"]
    if transforms:
        hops, problem = _connect(tree, world, topics.tool_frame)
        if problem:
            problem += ("; record the missing transform on /tf_static, or set "
                        "topics.tool_pose = \"\" to ingest without the robot")
        return PoseChain("tool", transforms[0].topic, topics.tool_frame, True, world, 0.0,
                         hops, problem,
                         found=tree is not None and topics.tool_frame in tree.frames)
    channel = next((c for c in found if c.kind == "pose"), None)
    if channel is None:
        return PoseChain("tool", topics.tool_pose, "", False, world, problem=(
            f"no pose topic matches topics.tool_pose = {topics.tool_pose!r}"), found=False)
    frame = channel.frame_id
    if frame and frame != world and base_to_world:
        return PoseChain("tool", channel.topic, frame, False, world, channel.rate_hz,
                         note="placed in the world by tool.base_to_world")
    hops, problem = _connect(tree, world, frame or world)
    if problem and not (tree is not None and frame in tree.frames and world not in tree.frames):
        problem = (f"{problem}: ingest needs tool.base_to_world = [x, y, z, qx, qy, qz, qw], "
                   f"the pose of {frame!r} in {world!r} (m, quaternion), which the log does "
                   "not hold, so `info` cannot write it; or topics.tool_pose = \"\" to "
                   "ingest without the robot")
    return PoseChain("tool", channel.topic, frame, False, world, channel.rate_hz, hops,
                     problem)
