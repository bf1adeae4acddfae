"""Ingest's poses in one frame, `topics.world_frame`: per camera and for the tool, a pose
stream from its pose topic (moved into the world through the TF tree when given in another
frame) or from the TF tree itself (the chain from `topics.camera_frame` / `tool_frame` to
the world, through any intermediate frames; `/tf_static` latched for the whole log).

Nothing is taken on trust: a frame the tree cannot connect to the world is refused in one
line naming both frames and the config key that chose them.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..config import Config
from ..core.geometry.poses import invert_pose, make_pose, rectified_rig_pose
from ..core.sync.streams import PoseStream, base_to_world_pose, fmt_stamp
from ..core.sync.tf_samples import concat_samples
from ..core.sync.tf_tree import TfTree, build_tf_tree
from ..core.sync.world_poses import (
    WorldTree,
    chain_stream,
    fixed_stream,
    moved_by,
    stream_to_world,
    transformed,
)
from ..errors import GeometryError, InputError, quoted
from ..io.logs.reader import LogReader
from ..io.logs.transforms import read_transforms
from .ingest_streams import CameraStreams, Poses

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class WorldPoses:
    """Camera-to-world pose streams (one per camera, sorted ids), the tool tip's (empty
    without a robot), each `[[tools]]` tool's, and for the report where each came from and
    how many stamps of conflicting samples its topic or TF chain had (by camera id, "tool"
    and "tools[k]")."""

    cameras: list[PoseStream]
    tool: PoseStream
    sources: dict[str, str]
    conflicts: dict[str, int]
    extra_tools: list[PoseStream]


def world_poses(ids: Sequence[str], cams: Sequence[CameraStreams], tool: Poses,
                reader: LogReader, config: Config, span_ns: tuple[int, int],
                allow_truncated: bool, extra_tools: dict[int, Poses] | None = None,
                shared: Poses | None = None) -> WorldPoses:
    """Every pose stream of the log in `topics.world_frame` (see the module docstring);
    `shared`: the poses of one camera_pose topic without {camera} (`topics.camera_from_ecm`
    places each camera on it)."""
    topics = config.topics
    world = topics.world_frame
    gap_ns = round(config.ingest.pose_gap_ms * 1e6)
    tree = _tree(reader, config, allow_truncated)
    conflicts = _Conflicts(tree, world)
    streams: list[PoseStream] = []
    sources: dict[str, str] = {}
    if topics.poses_from_camera_info:  # a fixed rig: no pose topic to read
        streams, sources = _camera_info_rig(ids, cams, span_ns)
    by_topic = () if topics.poses_from_camera_info else zip(ids, cams, strict=True)
    for index, (cid, cam) in enumerate(by_topic):
        what = f"camera {cid}"
        if topics.camera_from_ecm and cam.poses is None and shared is not None:
            hand_eye = _hand_eye(topics.camera_from_ecm, index, len(ids))
            streams.append(moved_by(stream_to_world(
                shared.validated(), shared.name, shared.frame, WorldTree(tree, world, gap_ns),
                what), hand_eye, f"{shared.name} with topics.camera_from_ecm"))
            sources[cid] = (f"{_topic_text(shared.name, shared.frame, world)}, then "
                            f"topics.camera_from_ecm[{index}]")
            continue
        if reader.role_uses_transforms("camera_pose"):
            frame = topics.camera_frame.replace("{camera}", cid)
            streams.append(_chain(tree, world, frame, span_ns, gap_ns,
                                  f"{what} (topics.camera_frame = {topics.camera_frame!r})"))
            sources[cid] = _chain_text(tree, world, frame)
            conflicts.chain(cid, frame)
            continue
        if cam.poses is None or not len(cam.poses.stamps):
            raise InputError(f"{what}: images on {cam.image_topic} but no pose on "
                             f"topics.camera_pose = {topics.camera_pose!r}")
        frame = cam.poses.frame
        streams.append(stream_to_world(conflicts.topic(cid, cam.poses), cam.pose_topic, frame,
                                       WorldTree(tree, world, gap_ns), what))
        sources[cid] = _topic_text(cam.pose_topic, frame, world)
        conflicts.chain(cid, frame)
    if topics.rectified:
        streams = _rectified(ids, cams, streams)
        sources = {cid: f"{text}, turned by its CameraInfo R (rectified images)"
                   for cid, text in sources.items()}
    if not topics.tool_pose:
        tool_stream = tool.validated()
    else:
        tool_stream, sources["tool"] = _tool_stream(
            tool, reader.role_uses_transforms("tool_pose"), topics.tool_frame,
            config.tool.base_to_world, conflicts, span_ns, gap_ns,
            ("tool", "topics.tool_frame", "tool.base_to_world"))
    extra = []
    for k, cfg in enumerate(config.tools):
        poses = (extra_tools or {}).get(k, Poses(f"{cfg.pose} (tools[{k}])"))
        if not cfg.frame and not len(poses.stamps):
            raise InputError(f"tools[{k}].pose = {cfg.pose!r}: no pose of this tool in the log")
        stream, sources[f"tools[{k}]"] = _tool_stream(
            poses, cfg.pose in reader.transform_topics, cfg.frame, cfg.base_to_world, conflicts,
            span_ns, gap_ns, (f"tools[{k}]", f"tools[{k}].frame", f"tools[{k}].base_to_world"))
        extra.append(stream)
    return WorldPoses(streams, tool_stream, sources, conflicts.counts, extra)


def _camera_info_rig(ids: Sequence[str], cams: Sequence[CameraStreams], span_ns: tuple[int, int]
                     ) -> tuple[list[PoseStream], dict[str, str]]:
    """`topics.camera_pose = "camera_info"`: each camera fixed in the world where its
    CameraInfo's R and P place it in the rig (`core.geometry.poses.rectified_rig_pose`), the
    first camera's raw frame the world; InputError naming the topic when a camera's info has
    no R and P, or when they give the rig no baseline."""
    in_rectified = []
    for cid, cam in zip(ids, cams, strict=True):
        if cam.rectification is None:
            raise InputError(
                f"camera {cid}: topics.camera_pose = \"camera_info\" but {cam.info_topic} "
                "carries no stereo rectification R and projection P; record the cameras' poses "
                "(a pose topic or TF), or convert the images with a calibration file")
        try:
            in_rectified.append(rectified_rig_pose(*cam.rectification))
        except GeometryError as exc:
            raise InputError(f"camera {cid}: {cam.info_topic}: {exc}") from exc
    to_world = invert_pose(in_rectified[0])
    poses = [to_world @ pose for pose in in_rectified]
    if len(poses) > 1 and max(np.linalg.norm(p[:3, 3]) for p in poses) == 0.0:
        raise InputError(
            f"topics.camera_pose = \"camera_info\": the CameraInfo projections of cameras "
            f"{', '.join(ids)} give the rig no baseline (P's Tx and Ty are 0 in every one); "
            "record the cameras' poses (a pose topic or TF)")
    streams = [fixed_stream(f"{cam.info_topic} R, P", pose, span_ns[0])
               for cam, pose in zip(cams, poses, strict=True)]
    sources = {cid: f"{cam.info_topic} R and P (a fixed rig, {ids[0]} at the world origin)"
               for cid, cam in zip(ids, cams, strict=True)}
    return streams, sources


def _rectified(ids: Sequence[str], cams: Sequence[CameraStreams], streams: list[PoseStream]
               ) -> list[PoseStream]:
    """The poses of rectified images (`topics.image_rectified`): each camera's raw pose
    turned by its CameraInfo's rectification R (x_rect = R x_raw; the centre stays)."""
    out = []
    for cid, cam, stream in zip(ids, cams, streams, strict=True):
        if cam.rectification is None:
            raise InputError(f"camera {cid}: {cam.info_topic} carries no rectification R for "
                             "the rectified images (topics.image_rectified)")
        turn = np.eye(4)
        turn[:3, :3] = cam.rectification[0].T
        out.append(moved_by(stream, turn, f"camera {cid} turned by {cam.info_topic} R"))
    return out


class _Conflicts:
    """Warns, once per stream, about the conflicting samples at one stamp that
    `sync.validate_pose_stream` dropped: on the pose topics and on the TF edges that the
    poses go through; `counts` their stamps by user (camera id, "tool" or "tools[k]")."""

    def __init__(self, tree: TfTree | None, world: str) -> None:
        self.tree, self.world = tree, world
        self.warned: set[str] = set()
        self.counts: dict[str, int] = {}

    def topic(self, user: str, poses: Poses) -> PoseStream:
        """The validated stream of a pose topic, warned about."""
        stream = poses.validated()
        self._warn(user, poses.name, stream)
        return stream

    def chain(self, user: str, frame: str) -> None:
        """Warn about the TF edges between `frame` and the world."""
        if self.tree is None or frame in ("", self.world):
            return
        up, down = self.tree.chain(self.world, frame)
        for edge in (*up, *down):
            self._warn(user, f"TF {edge.parent!r} -> {edge.child!r}", edge.stream)

    def _warn(self, user: str, name: str, stream: PoseStream) -> None:
        n = len(stream.conflict_stamps_ns)
        self.counts[user] = self.counts.get(user, 0) + n
        if not n or name in self.warned:
            return
        self.warned.add(name)
        metres, radians = stream.conflict_sizes.max(axis=0)
        logger.warning(
            "%s: %d stamp%s with pose samples that disagree (first at %s; up to %.3g mm and "
            "%.3g deg apart); neither is trusted: the samples at %s dropped and the stream "
            "interpolated across %s", name, n, "s" if n > 1 else "",
            fmt_stamp(int(stream.conflict_stamps_ns[0])), metres * 1e3, np.degrees(radians),
            "those stamps are" if n > 1 else "that stamp is", "them" if n > 1 else "it")


def _hand_eye(values: Sequence[float], index: int, n_cameras: int) -> np.ndarray:
    """Camera `index`'s pose (4, 4) in the shared pose frame from `topics.camera_from_ecm`."""
    rows = np.asarray(values, float).reshape(-1, 7)
    if len(rows) not in (1, n_cameras):
        raise InputError(f"topics.camera_from_ecm holds {len(rows)} poses for {n_cameras} "
                         "cameras: give one (x y z qx qy qz qw) per camera, or one for all")
    row = rows[index if len(rows) > 1 else 0]
    norm = np.linalg.norm(row[3:])
    if not np.isfinite(row).all() or abs(norm - 1) > 1e-3:
        raise InputError(f"topics.camera_from_ecm[{index}]: quaternion norm {norm:.6g} is not 1")
    return make_pose(row[:3], row[3:] / norm)


def _tool_stream(tool: Poses, on_tf: bool, frame: str, base_to_world: tuple[float, ...],
                 conflicts: _Conflicts, span_ns: tuple[int, int], gap_ns: int,
                 keys: tuple[str, str, str]) -> tuple[PoseStream, str]:
    """A tool's tip pose stream in the world and where it came from: the TF chain of its
    frame (`on_tf`: its topic carries transforms), its topic through `base_to_world`, or its
    topic moved into the world through the tree (conflicting samples warned about).
    keys: the tool ("tool" or "tools[k]"), its frame key, its base key (for messages)."""
    user, frame_key, base_key = keys
    what = "tool" if user == "tool" else f"tool {user}"
    tree, world = conflicts.tree, conflicts.world
    if on_tf:
        stream = _chain(tree, world, frame, span_ns, gap_ns, f"{what} ({frame_key} = {frame!r})")
        conflicts.chain(user, frame)
        return stream, _chain_text(tree, world, frame)
    if base_to_world:  # the tip in the robot's base frame
        return (transformed(conflicts.topic(user, tool), base_to_world_pose(base_to_world),
                            tool.name), f"{tool.name} through {base_key}")
    stream = stream_to_world(conflicts.topic(user, tool), tool.name, tool.frame,
                             WorldTree(tree, world, gap_ns), what)
    conflicts.chain(user, tool.frame)
    return stream, _topic_text(tool.name, tool.frame, world)


def _tree(reader: LogReader, config: Config, allow_truncated: bool) -> TfTree | None:
    """The log's TF tree (None when it has no transform channel)."""
    samples = concat_samples([
        read_transforms(path, config.ingest.time_source, allow_truncated).samples
        for path in reader.input.files])
    if not len(samples):
        return None
    tree = build_tf_tree(samples)
    for frame, problem in tree.problems.items():  # an error only if a pose needs that edge
        logger.warning("%s (TF frame %s left out of the tree)", problem, quoted(frame))
    return tree


def _chain(tree: TfTree | None, world: str, frame: str, span_ns: tuple[int, int],
           gap_ns: int, what: str) -> PoseStream:
    if tree is None:
        raise InputError(f"{what}: the pose topic carries transforms but the log has no TF "
                         "tree (no transform was read)")
    if world not in tree.frames:  # the world, not the camera/tool frame `what` names
        raise InputError(f"topics.world_frame = {world!r} is not a frame of the log's TF tree "
                         f"(roots: {', '.join(tree.roots)}); set topics.world_frame to the "
                         "frame the reconstruction is to be in (`surgrecon info LOG` shows "
                         "the tree)")
    try:
        return chain_stream(tree, world, frame, span_ns, gap_ns, f"TF {world} <- {frame}")
    except InputError as exc:
        raise InputError(f"{what}: {exc}") from exc


def _chain_text(tree: TfTree | None, world: str, frame: str) -> str:
    assert tree is not None  # _chain succeeded on it
    up, down = tree.chain(world, frame)
    path = [frame, *(e.parent for e in up)]
    path += [e.child for e in reversed(down)]
    kinds = "".join("s" if e.static else "d" for e in (*up, *down))
    return f"TF {' -> '.join(path)} ({kinds.count('d')} dynamic, {kinds.count('s')} static)"


def _topic_text(topic: str, frame: str, world: str) -> str:
    if frame in ("", world):
        return f"{topic} in {world}"
    return f"{topic} in {frame}, moved into {world} through the TF tree"


def log_span(stamps: Sequence[np.ndarray]) -> tuple[int, int]:
    """First and last stamp (ns) over the image streams."""
    return (int(min(s.min() for s in stamps)), int(max(s.max() for s in stamps)))


def check_clocks(cams: Sequence[CameraStreams], stamps: Sequence[np.ndarray],
                 pose_streams: Sequence[PoseStream], usable: np.ndarray, reader: LogReader,
                 config: Config) -> None:
    """Fail at once, naming the streams and their clocks, when no camera's images overlap
    its pose stream in time (e.g. images stamped on the log clock, poses on the header
    clock): nothing could be used, and later stages would fail obscurely. (A truncated
    log has its own message.)"""
    gap = config.ingest.pose_gap_ms * 1e6
    if usable.any() or reader.damage or any(
            len(s) and len(p.stamps_ns) and s.min() <= p.stamps_ns.max() + gap
            and p.stamps_ns.min() - gap <= s.max() for s, p in zip(stamps, pose_streams,
                                                                   strict=True)):
        return
    lines = []
    for cam, image_stamps, poses in zip(cams, stamps, pose_streams, strict=True):
        pose_topic = cam.pose_topic or config.topics.camera_pose  # "" when through the TF tree
        lines.append(
            f"camera {cam.camera_id}: images on {cam.image_topic} at "
            f"{_span(image_stamps)} ({reader.clock_of(cam.image_topic)}), poses on "
            f"{pose_topic} at {_span(poses.stamps_ns)} "
            f"({reader.clock_of(pose_topic)})")
    raise InputError(
        f"{reader.path}: no camera's images overlap its poses in time: the streams are on "
        "different clocks? "
        f"{'; '.join(lines)}; try --set ingest.time_source=log_time, or fix the stamps")


def _span(stamps_ns: np.ndarray) -> str:
    if not len(stamps_ns):
        return "no stamps"
    return f"{stamps_ns.min() / 1e9:.3f}..{stamps_ns.max() / 1e9:.3f} s"
