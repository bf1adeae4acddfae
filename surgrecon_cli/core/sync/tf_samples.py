"""Transform samples as `/tf` and `/tf_static` carry them, stored compactly per edge.

Sample i of an edge is the pose of frame `child` in frame `parent` at stamp i (translation
m, unit quaternion x y z w), i.e. p_parent = T_i @ p_child. An hour of robot TF is tens of
millions of samples: they are kept per (parent, child, static) edge in growing typed arrays
(`SampleCollector`: 64 bytes a sample, the frame names once per edge), never as Python
objects per sample. Frame ids longer than `MAX_FRAME_ID_BYTES` are refused by the readers
(`frame_id_problem`). Pure numpy, no I/O.
"""

from __future__ import annotations

from array import array
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

MAX_FRAME_ID_BYTES = 256
"""Longest frame id accepted (UTF-8 bytes); ROS frame ids are short names."""
_ECHO_CHARS = 40


def frame_id_problem(frame: str) -> str | None:
    """Why `frame` cannot be a frame id (longer than `MAX_FRAME_ID_BYTES`), echoing only
    its start; None when it can."""
    if len(frame) <= MAX_FRAME_ID_BYTES // 4 or len(frame.encode("utf-8", "replace")) <= (
            MAX_FRAME_ID_BYTES):
        return None
    size = len(frame.encode("utf-8", "replace"))
    return (f"a frame id of {size} bytes ({frame[:_ECHO_CHARS]!r}...), more than the "
            f"{MAX_FRAME_ID_BYTES} a frame id may have")


@dataclass(frozen=True)
class EdgeSamples:
    """The samples of one edge in arrival order: stamps_ns (n,) int64 ns, values (n, 7):
    translation (m) and quaternion x y z w; `static`: latched (from `/tf_static`)."""

    parent: str
    child: str
    static: bool
    stamps_ns: np.ndarray
    values: np.ndarray


@dataclass(frozen=True)
class TransformSamples:
    """Transform samples grouped by edge (edges in order of first arrival).

    The flat (N,) views (`parent`, `child`, `stamps_ns`, `translations`, `quats`,
    `static`, edge after edge) are for inspecting small sets; they allocate.
    """

    edges: tuple[EdgeSamples, ...] = ()

    def __len__(self) -> int:
        return sum(len(e.stamps_ns) for e in self.edges)

    def _repeat(self, values: list) -> np.ndarray:
        counts = [len(e.stamps_ns) for e in self.edges]
        return np.repeat(np.array(values, dtype=object), counts)

    @property
    def parent(self) -> np.ndarray:
        return self._repeat([e.parent for e in self.edges])

    @property
    def child(self) -> np.ndarray:
        return self._repeat([e.child for e in self.edges])

    @property
    def static(self) -> np.ndarray:
        return self._repeat([e.static for e in self.edges]).astype(bool)

    @property
    def stamps_ns(self) -> np.ndarray:
        return np.concatenate([np.zeros(0, np.int64), *(e.stamps_ns for e in self.edges)])

    @property
    def translations(self) -> np.ndarray:
        return self._values()[:, :3]

    @property
    def quats(self) -> np.ndarray:
        return self._values()[:, 3:]

    def _values(self) -> np.ndarray:
        return np.concatenate([np.zeros((0, 7)), *(e.values for e in self.edges)])


class SampleCollector:
    """Growing per-edge arrays: `add` one sample, `samples()` the result (which shares the
    collector's memory: add nothing after it)."""

    def __init__(self) -> None:
        self._edges: dict[tuple[str, str, bool], tuple[array, array]] = {}

    def add(self, parent: str, child: str, static: bool, stamp_ns: int,
            values: Sequence[float]) -> None:
        """One sample: `values` translation (3,) m then quaternion (4,) x y z w."""
        key = (parent, child, static)
        edge = self._edges.get(key)
        if edge is None:
            edge = self._edges[key] = (array("q"), array("d"))
        edge[0].append(stamp_ns)
        edge[1].extend(values)

    def samples(self) -> TransformSamples:
        return TransformSamples(tuple(
            EdgeSamples(parent, child, static, np.frombuffer(stamps, np.int64),
                        np.frombuffer(values, float).reshape(-1, 7))
            for (parent, child, static), (stamps, values) in self._edges.items()))


def make_samples(
    parent: Sequence[str] | np.ndarray,
    child: Sequence[str] | np.ndarray,
    stamps_ns: Sequence[int] | np.ndarray,
    translations: Sequence[Sequence[float] | np.ndarray] | np.ndarray,
    quats: Sequence[Sequence[float] | np.ndarray] | np.ndarray,
    static: bool | Sequence[bool] | np.ndarray = False,
) -> TransformSamples:
    """`TransformSamples` from array-likes of N samples (shapes checked); `static` may be one
    bool for all. Raises ValueError on mismatched lengths or shapes."""
    par = [str(p) for p in np.asarray(parent, dtype=object).reshape(-1)]
    chi = [str(c) for c in np.asarray(child, dtype=object).reshape(-1)]
    n = len(par)
    stamps = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
    trans = np.asarray(translations, dtype=float).reshape(-1, 3) if n else np.zeros((0, 3))
    q = np.asarray(quats, dtype=float).reshape(-1, 4) if n else np.zeros((0, 4))
    stat = np.broadcast_to(np.asarray(static, dtype=bool), (n,))
    if not (len(chi) == len(stamps) == len(trans) == len(q) == n):
        raise ValueError(f"transform samples: {n} parents, {len(chi)} children, "
                         f"{len(stamps)} stamps, {len(trans)} translations, {len(q)} quats")
    groups: dict[tuple[str, str, bool], list[int]] = {}
    for i, key in enumerate(zip(par, chi, stat.tolist(), strict=True)):
        groups.setdefault(key, []).append(i)
    values = np.concatenate([trans, q], axis=1)
    return TransformSamples(tuple(EdgeSamples(p, c, s, stamps[idx], values[idx])
                                  for (p, c, s), idx in groups.items()))


def concat_samples(parts: Sequence[TransformSamples]) -> TransformSamples:
    """All samples of `parts`, in order (an edge's samples joined across the parts)."""
    groups: dict[tuple[str, str, bool], list[EdgeSamples]] = {}
    for part in parts:
        for e in part.edges:
            groups.setdefault((e.parent, e.child, e.static), []).append(e)
    return TransformSamples(tuple(
        es[0] if len(es) == 1 else EdgeSamples(
            p, c, s, np.concatenate([e.stamps_ns for e in es]),
            np.concatenate([e.values for e in es]))
        for (p, c, s), es in groups.items()))
