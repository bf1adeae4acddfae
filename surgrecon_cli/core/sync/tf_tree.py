"""A time-indexed TF tree: transforms between named frames, composed through the tree.

Pure numpy, no I/O. Input are transform samples as `/tf` and `/tf_static` carry them (ROS
`tf2_msgs/TFMessage`, Foxglove `FrameTransform(s)`), stored per edge (`tf_samples`): a sample
is the pose of frame `child` in frame `parent` at a stamp (translation m, unit quaternion
x y z w), i.e. p_parent = T @ p_child. Each child has one parent (the tf2 convention), so
the frames form a forest; an *edge* is one (parent, child) pair with all its samples.

- A dynamic edge (from `/tf`) is interpolated to the query stamps like the tracker streams
  (`sync.validate_pose_stream` + `geometry.interpolate_poses`: linear translation, slerp
  rotation); a query before its first sample, after its last, or inside a gap between two
  samples longer than `max_gap_ns`, is invalid (NaN), never extrapolated.
- A static edge (from `/tf_static`) is latched: constant over the whole log whatever its stamp;
  when it is published several times the last sample wins (as in tf2). So is an edge on `/tf`
  whose every sample (two or more) is the same transform: a fixed transform re-sent every
  period (ROS 1's tf `static_transform_publisher`), whose period's jitter would otherwise
  leave images in "gaps" of a pose that never changes.

`TfTree.lookup(target, source, stamps)` returns T_target_source (Q, 4, 4): the pose of `source`
in `target` (p_target = T @ p_source), composed from the source up to the frames' common
ancestor and down to the target. A camera-to-world pose is `lookup("world", camera_frame, t)`.
Stamps are int64 nanoseconds.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ...errors import InputError, cut, quoted
from ..geometry.poses import invert_pose, make_pose
from .streams import PoseStream, poses_at, rate_hz, validate_pose_stream
from .tf_samples import EdgeSamples, TransformSamples

_MAX_LISTED = 40


@dataclass(frozen=True)
class TfEdge:
    """The transforms of `child` in `parent`: `stream` holds the samples sorted by stamp with
    repeated stamps resolved (`sync.validate_pose_stream`: conflicting ones dropped and
    listed); a static edge: its one latched sample; `published` counts the samples
    received."""

    parent: str
    child: str
    static: bool
    stream: PoseStream
    published: int

    @property
    def rate_hz(self) -> float:
        """Mean sample rate (Hz); 0 for a static edge."""
        return 0.0 if self.static else rate_hz(self.stream.stamps_ns)

    def at(self, stamps_ns: np.ndarray, max_gap_ns: int) -> np.ndarray:
        """Poses of child in parent (Q, 4, 4) at stamps (Q,) ns; NaN where invalid (module
        docstring); a static edge is valid everywhere."""
        query = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
        if self.static:
            pose = make_pose(self.stream.positions[0], self.stream.quats[0])
            return np.broadcast_to(pose, (len(query), 4, 4)).copy()
        return poses_at(self.stream, query, max_gap_ns)[0]


@dataclass(frozen=True)
class FrameSummary:
    """One frame of the tree, for display: `parent` "" for a root (then `static` False and
    `samples` 0); `depth` 0 for a root; `samples` = transforms received for the edge to the
    parent; rate (Hz, 0 when static) and first/last stamps (ns) of that edge."""

    frame: str
    parent: str
    depth: int
    static: bool
    samples: int
    rate_hz: float
    first_ns: int
    last_ns: int


@dataclass(frozen=True)
class TfTree:
    """Frames connected by edges (one per child frame); build with `build_tf_tree`.
    `problems`: why the edge to a frame's parent was left out (by frame); a lookup that
    needs that edge raises InputError with it."""

    edges: tuple[TfEdge, ...]
    problems: dict[str, str] = field(default_factory=dict, compare=False)
    _by_child: dict[str, TfEdge] = field(init=False, repr=False, compare=False)
    _children: dict[str, tuple[str, ...]] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        by_child = {e.child: e for e in self.edges}
        if len(by_child) != len(self.edges):
            raise ValueError("TfTree: one edge per child frame")
        children: dict[str, list[str]] = {}
        for e in self.edges:
            children.setdefault(e.parent, []).append(e.child)
        object.__setattr__(self, "_by_child", by_child)
        object.__setattr__(self, "_children",
                           {p: tuple(sorted(c)) for p, c in children.items()})
        if _cycles(by_child):
            raise ValueError("TfTree: the edges form a cycle")

    # -- structure -----------------------------------------------------------------------
    @property
    def frames(self) -> tuple[str, ...]:
        """Every frame name, sorted."""
        return tuple(sorted(set(self._by_child) | set(self._children)))

    @property
    def roots(self) -> tuple[str, ...]:
        """Frames without a parent, sorted."""
        return tuple(sorted(set(self._children) - set(self._by_child)))

    def parent(self, frame: str) -> str | None:
        """The parent of `frame`, None for a root; InputError for an unknown frame."""
        self._check_frame(frame)
        edge = self._by_child.get(frame)
        return None if edge is None else edge.parent

    def children(self, frame: str) -> tuple[str, ...]:
        """Child frames of `frame`, sorted."""
        return self._children.get(frame, ())

    def edge(self, child: str) -> TfEdge | None:
        """The edge from `child` to its parent, None for a root or an unknown frame."""
        return self._by_child.get(child)

    def root_of(self, frame: str) -> str:
        """The root of the tree holding `frame`."""
        return self._up(frame)[-1]

    def is_connected(self, frame_a: str, frame_b: str) -> bool:
        """True when both frames exist and share a root."""
        known = set(self.frames)
        return frame_a in known and frame_b in known and self.root_of(frame_a) == self.root_of(
            frame_b)

    def chain(self, target_frame: str, source_frame: str) -> tuple[list[TfEdge], list[TfEdge]]:
        """Edges from the source up to the common ancestor and from the target up to it.

        Raises InputError naming both frames (and listing the frames) when a frame is unknown
        or the two are in different trees.
        """
        self._check_frame(source_frame)
        self._check_frame(target_frame)
        up_source = self._up(source_frame)
        up_target = self._up(target_frame)
        for top in (up_source[-1], up_target[-1]):
            if top in self.problems:  # the chain needs an edge that was left out
                raise InputError(self.problems[top])
        if up_source[-1] != up_target[-1]:
            raise InputError(
                f"TF frames {quoted(target_frame)} and {quoted(source_frame)} are not "
                f"connected: {quoted(source_frame)} is in the tree under "
                f"{quoted(up_source[-1])}, {quoted(target_frame)} under "
                f"{quoted(up_target[-1])}; {self._listing()}")
        on_target_path = set(up_target)
        ancestor = next(f for f in up_source if f in on_target_path)
        source_edges = [self._by_child[f] for f in up_source[: up_source.index(ancestor)]]
        target_edges = [self._by_child[f] for f in up_target[: up_target.index(ancestor)]]
        return source_edges, target_edges

    # -- lookup --------------------------------------------------------------------------
    def lookup(self, target_frame: str, source_frame: str, stamps_ns: np.ndarray,
               max_gap_ns: int) -> np.ndarray:
        """T_target_source (Q, 4, 4): pose of `source_frame` in `target_frame` at stamps (Q,)
        int64 ns, composed through the common ancestor. A row is NaN where any dynamic edge
        on the chain is invalid (outside its samples or in a gap > `max_gap_ns`); validity is
        `np.isfinite(T[:, 0, 0])`. Raises InputError when the frames are not connected."""
        query = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
        source_edges, target_edges = self.chain(target_frame, source_frame)
        ancestor_source = _compose(source_edges, query, max_gap_ns)
        ancestor_target = _compose(target_edges, query, max_gap_ns)
        valid = np.isfinite(ancestor_source).all(axis=(1, 2)) & np.isfinite(
            ancestor_target).all(axis=(1, 2))
        out = np.full((len(query), 4, 4), np.nan)
        out[valid] = invert_pose(ancestor_target[valid]) @ ancestor_source[valid]
        return out

    # -- description ---------------------------------------------------------------------
    def describe(self) -> tuple[FrameSummary, ...]:
        """Every frame in depth-first order from the roots (children sorted by name)."""
        out: list[FrameSummary] = []
        stack = [(root, 0) for root in reversed(self.roots)]
        while stack:
            frame, depth = stack.pop()
            e = self._by_child.get(frame)
            if e is None:
                out.append(FrameSummary(frame, "", depth, False, 0, 0.0, 0, 0))
            else:
                s = e.stream.stamps_ns
                out.append(FrameSummary(frame, e.parent, depth, e.static, e.published,
                                        e.rate_hz, int(s[0]), int(s[-1])))
            stack.extend((c, depth + 1) for c in reversed(self.children(frame)))
        return tuple(out)

    # -- helpers -------------------------------------------------------------------------
    def _up(self, frame: str) -> list[str]:
        """`frame`, its parent, ... up to its root."""
        path = [frame]
        while path[-1] in self._by_child:
            path.append(self._by_child[path[-1]].parent)
        return path

    def _check_frame(self, frame: str) -> None:
        if frame not in self._by_child and frame not in self._children:
            raise InputError(self.problems.get(frame) or f"TF frame {quoted(frame)} is not in "
                             f"the TF tree; {self._listing()}")

    def _listing(self) -> str:
        frames = self.frames
        more = f", ... ({len(frames) - _MAX_LISTED} more)" if len(frames) > _MAX_LISTED else ""
        listed = ", ".join(cut(f) for f in frames[:_MAX_LISTED])
        return f"frames in the tree: {listed or 'none'}{more}"


def _compose(edges: list[TfEdge], query: np.ndarray, max_gap_ns: int) -> np.ndarray:
    """Product of the edges' poses (Q, 4, 4), the edge nearest the ancestor leftmost:
    T_ancestor_frame for `edges` listed from the frame up to the ancestor."""
    out = np.broadcast_to(np.eye(4), (len(query), 4, 4)).copy()
    for e in edges:
        out = e.at(query, max_gap_ns) @ out
    return out


def build_tf_tree(samples: TransformSamples) -> TfTree:
    """Group the samples' edges by child frame and check them.

    As in tf2, a bad edge matters only to a lookup that needs it: an edge whose child has two
    parents (naming the child and both parents), that is both static and dynamic, that
    transforms a frame to itself, that lies on a cycle, or (naming the edge and stamp) that
    has a non-finite value or a non-unit quaternion is left out of the tree, its message kept
    in `TfTree.problems` under its child frame.
    """
    by_child: dict[str, list[EdgeSamples]] = {}
    for e in samples.edges:
        by_child.setdefault(e.child, []).append(e)
    edges, problems = {}, {}
    for child in sorted(by_child):
        try:
            edges[child] = _edge(child, by_child[child])
        except InputError as exc:
            problems[child] = str(exc)
    problems.update(_cycles(edges))
    return TfTree(tuple(e for child, e in edges.items() if child not in problems), problems)


def _edge(child: str, group: list[EdgeSamples]) -> TfEdge:
    """The edge of `child` from its samples (one `EdgeSamples` per parent and kind)."""
    counts: dict[str, int] = {}
    for e in group:
        counts[e.parent] = counts.get(e.parent, 0) + len(e.stamps_ns)
    if len(counts) > 1:
        listed = ", ".join(f"{quoted(p)} ({c} transform{'s' if c > 1 else ''})"
                           for p, c in sorted(counts.items()))
        raise InputError(
            f"TF frame {quoted(child)} has {len(counts)} parents: {listed}; a frame has one "
            "parent in a TF tree (fix the publishers, or drop one of the transforms)")
    e = group[0]
    if e.parent == child:
        raise InputError(f"TF transform from frame {quoted(child)} to itself")
    name = f"TF transform {quoted(e.parent)} -> {quoted(child)}"
    if len(group) > 1:
        static = sum(len(g.stamps_ns) for g in group if g.static)
        raise InputError(
            f"{name} is published both as static ({static} on /tf_static) and as "
            f"dynamic ({counts[e.parent] - static} on /tf); publish it on one of them")
    stamps, values = e.stamps_ns, e.values
    static = e.static or (len(stamps) >= 2 and bool((values == values[0]).all()))
    if static:  # latched: the last one published wins
        stamps, values = stamps[-1:], values[-1:]
    stream = validate_pose_stream(name, stamps, values[:, :3], values[:, 3:])
    return TfEdge(e.parent, child, static, stream, len(e.stamps_ns))


def _cycles(by_child: dict[str, TfEdge]) -> dict[str, str]:
    """{frame: message naming the cycle's frames} for every frame on a cycle of the edges."""
    parent_of = {child: e.parent for child, e in by_child.items()}
    done: set[str] = set()
    found: dict[str, str] = {}
    for start in parent_of:
        path: list[str] = []
        on_path: set[str] = set()
        frame: str | None = start
        while frame is not None and frame not in done:
            if frame in on_path:
                cycle = [*path[path.index(frame):], frame][::-1]
                found.update(dict.fromkeys(cycle, "TF transforms form a cycle: " + " -> ".join(
                    cut(f) for f in cycle) + " (parent -> child); a TF tree has no cycles"))
                break
            path.append(frame)
            on_path.add(frame)
            frame = parent_of.get(frame)
        done.update(path)
    return found
