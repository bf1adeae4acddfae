"""Pose streams in the world frame, through the TF tree (core/sync/tf_tree.py).

A camera's pose is the chain from its optical frame to the world frame, whatever lies
between (tracker -> marker -> hand-eye -> optical). The chain is sampled where it is
measured, at the stamps of its dynamic edges, so that ingest interpolates it to image
stamps exactly as it interpolates a pose topic. A pose message given in another frame is
moved into the world through the tree at its own stamps.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ...errors import InputError, quoted
from ..geometry.poses import make_pose, matrix_to_quat
from .streams import PoseStream, validate_pose_stream
from .tf_tree import TfTree


@dataclass(frozen=True)
class WorldTree:
    """How a pose reaches the world: the log's TF tree (None: the log has none), the world
    frame's name and the longest gap (ns) a tree lookup interpolates over."""

    tree: TfTree | None
    world_frame: str
    max_gap_ns: int


def _stream(name: str, stamps_ns: np.ndarray, poses: np.ndarray,
            constant: bool = False) -> PoseStream:
    """A validated stream from poses (M, 4, 4), dropping stamps where it is unknown (NaN);
    `constant`: it holds at every stamp (`PoseStream.constant`)."""
    valid = np.isfinite(poses).all(axis=(1, 2))
    poses = poses[valid]
    stream = validate_pose_stream(name, stamps_ns[valid], poses[:, :3, 3],
                                  matrix_to_quat(poses[:, :3, :3]))
    return replace(stream, constant=constant)


def chain_stream(tree: TfTree, world_frame: str, frame: str, span_ns: tuple[int, int],
                 max_gap_ns: int, name: str) -> PoseStream:
    """The pose of `frame` in `world_frame` sampled at its chain's dynamic stamps (the
    union over the chain's dynamic edges); a chain of static edges only is constant: one
    sample (at the start of `span_ns`, the log's time span) that holds at every stamp,
    however long the log (a rig fixed in the world, published once on `/tf_static`).
    Raises InputError (naming both frames) when they are not connected."""
    source_edges, target_edges = tree.chain(world_frame, frame)
    dynamic = [e.stream.stamps_ns for e in (*source_edges, *target_edges) if not e.static]
    if not dynamic:
        stamps = np.array([min(span_ns)], np.int64)
        return _stream(name, stamps, tree.lookup(world_frame, frame, stamps, max_gap_ns), True)
    stamps = np.unique(np.concatenate(dynamic))
    return _stream(name, stamps, tree.lookup(world_frame, frame, stamps, max_gap_ns))


def fixed_stream(name: str, pose: np.ndarray, stamp_ns: int) -> PoseStream:
    """A pose (4, 4) that holds at every stamp (`PoseStream.constant`), given at `stamp_ns`."""
    return _stream(name, np.array([stamp_ns], np.int64), np.asarray(pose, float)[None], True)


def transformed(stream: PoseStream, pose: np.ndarray, name: str) -> PoseStream:
    """The stream `name` left-multiplied by a fixed pose (4, 4), e.g. the robot's base in
    the world (`tool.base_to_world`)."""
    return _stream(name, stream.stamps_ns, pose @ make_pose(stream.positions, stream.quats),
                   stream.constant)


def moved_by(stream: PoseStream, offset: np.ndarray, name: str) -> PoseStream:
    """The stream `name` right-multiplied by a fixed pose (4, 4): the poses of a frame
    rigidly attached to the stream's (e.g. a camera on the ECM, by its hand-eye pose)."""
    return _stream(name, stream.stamps_ns, make_pose(stream.positions, stream.quats) @ offset,
                   stream.constant)


def stream_to_world(stream: PoseStream, name: str, frame: str, world: WorldTree,
                    what: str) -> PoseStream:
    """A pose stream `name` (its topic) given in `frame`, in `world.world_frame`: unchanged
    when `frame` is the world (or unnamed, ""); else composed with the tree's world <- frame
    transform at each stamp. InputError naming both frames (`what`: whose poses) when the
    log has no tree connecting them."""
    tree, world_frame = world.tree, world.world_frame
    if frame in ("", world_frame):
        return stream
    if tree is None or not tree.is_connected(world_frame, frame):
        raise InputError(
            f"{what}: poses on {name} are in frame {quoted(frame)}, not in topics.world_frame "
            f"= {quoted(world_frame)}, and the log has no TF tree connecting the two; set "
            f"topics.world_frame = {quoted(frame)} if that frame is your world, or record the "
            "transform between them on /tf or /tf_static")
    poses = make_pose(stream.positions, stream.quats)
    in_world = tree.lookup(world_frame, frame, stream.stamps_ns, world.max_gap_ns) @ poses
    return _stream(name, stream.stamps_ns, in_world)
