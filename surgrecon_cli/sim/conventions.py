"""How a recording describes its poses: the simulated log rewritten in the conventions real
recordings use, with the same true poses (so ingest must give the same cameras and tool).

  topics         camera/tool PoseStamped in `world`, one topic each (the default)
  tf             the same poses as transforms world -> optical frame on /tf
  tf-tree        a navigation system's tree: /tf_static world -> tracker, /tf tracker ->
                 endoscope_C_marker (the tracked marker), /tf_static endoscope_C_marker ->
                 endoscope_C_optical (hand-eye calibration); the robot as /tf_static world
                 -> psm1_base and /tf psm1_base -> raven_tool_tip
  tracker-frame  camera PoseStamped in the tracker's frame, the tool in `world`, and
                 /tf_static world -> tracker relating them
  robot-base     the tool PoseStamped in the robot's base frame `psm1_base`, placed by the
                 config key tool.base_to_world (no TF)
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

from ..core.geometry.poses import invert_pose, make_pose, matrix_to_quat
from ..io.logs.records import PoseRecord, Record

Message = tuple[str, int, Record]
WORLD = "world"
# Fixed, non-trivial placements (m, unit quaternion x y z w): the tracker above the table,
# each marker's hand-eye offset, the robot's base beside the patient.
TRACKER = make_pose(np.array([0.35, -0.20, 0.90]), np.array([0.2, -0.3, 0.1, 0.927362]))
ROBOT_BASE = make_pose(np.array([-0.42, 0.15, -0.05]), np.array([0.0, 0.0, 0.6, 0.8]))
_BASE_QUAT = (0.0, 0.0, 0.6, 0.8)


def hand_eye(camera: str) -> np.ndarray:
    """marker -> optical frame of camera `camera` (a few cm along the scope, rotated)."""
    k = int(camera) if camera.isdigit() else len(camera)
    angle = 0.3 + 0.2 * k
    quat = np.array([np.sin(angle / 2) * 0.6, np.sin(angle / 2) * 0.8, 0.0, np.cos(angle / 2)])
    return make_pose(np.array([0.01 * k, 0.02, 0.08]), quat)


def _record(stamp_ns: int, parent: str, child: str, pose: np.ndarray) -> PoseRecord:
    return PoseRecord(stamp_ns, parent, child, pose[:3, 3].copy(), matrix_to_quat(pose[:3, :3]))


def _pose(record: PoseRecord) -> np.ndarray:
    return make_pose(record.position, record.orientation)


def _camera_of(topic: str) -> str | None:
    if topic.startswith("/navigation/endoscope_") and topic.endswith("/pose"):
        return topic.split("/")[2].removeprefix("endoscope_")
    return None


def _with_statics(messages: Iterator[Message], statics: Callable[[int], list[Message]]
                  ) -> Iterator[Message]:
    """Publish the static transforms once, at the first message's log time."""
    first = True
    for message in messages:
        if first:
            yield from statics(message[1])
            first = False
        yield message


def tf(messages: Iterator[Message]) -> Iterator[Message]:
    for topic, log_ns, record in messages:
        camera = _camera_of(topic)
        if camera is not None and isinstance(record, PoseRecord):
            yield "/tf", log_ns, _record(record.stamp_ns, WORLD, f"endoscope_{camera}_optical",
                                         _pose(record))
        elif topic == "/raven/tool_tip" and isinstance(record, PoseRecord):
            yield "/tf", log_ns, _record(record.stamp_ns, WORLD, "raven_tool_tip", _pose(record))
        else:
            yield topic, log_ns, record


def tf_tree(messages: Iterator[Message]) -> Iterator[Message]:
    to_tracker, to_base = invert_pose(TRACKER), invert_pose(ROBOT_BASE)
    cameras: set[str] = set()

    def rewritten() -> Iterator[Message]:
        for topic, log_ns, record in messages:
            camera = _camera_of(topic)
            if camera is not None and isinstance(record, PoseRecord):
                cameras.add(camera)
                marker = to_tracker @ _pose(record) @ invert_pose(hand_eye(camera))
                yield "/tf", log_ns, _record(record.stamp_ns, "tracker",
                                             f"endoscope_{camera}_marker", marker)
            elif topic == "/raven/tool_tip" and isinstance(record, PoseRecord):
                yield "/tf", log_ns, _record(record.stamp_ns, "psm1_base", "raven_tool_tip",
                                             to_base @ _pose(record))
            else:
                yield topic, log_ns, record

    out = list(rewritten())  # the cameras are known once their poses are seen
    t0 = out[0][1] if out else 0
    statics = [("/tf_static", t0, _record(t0, WORLD, "tracker", TRACKER)),
               ("/tf_static", t0, _record(t0, WORLD, "psm1_base", ROBOT_BASE))]
    statics += [("/tf_static", t0, _record(t0, f"endoscope_{c}_marker",
                                           f"endoscope_{c}_optical", hand_eye(c)))
                for c in sorted(cameras)]
    yield from statics
    yield from out


def tracker_frame(messages: Iterator[Message]) -> Iterator[Message]:
    to_tracker = invert_pose(TRACKER)

    def rewritten() -> Iterator[Message]:
        for topic, log_ns, record in messages:
            if _camera_of(topic) is not None and isinstance(record, PoseRecord):
                yield topic, log_ns, _record(record.stamp_ns, "tracker", "",
                                             to_tracker @ _pose(record))
            else:
                yield topic, log_ns, record

    return _with_statics(rewritten(),
                         lambda t0: [("/tf_static", t0, _record(t0, WORLD, "tracker", TRACKER))])


def robot_base(messages: Iterator[Message]) -> Iterator[Message]:
    to_base = invert_pose(ROBOT_BASE)
    for topic, log_ns, record in messages:
        if topic == "/raven/tool_tip" and isinstance(record, PoseRecord):
            yield topic, log_ns, _record(record.stamp_ns, "psm1_base", "",
                                         to_base @ _pose(record))
        else:
            yield topic, log_ns, record


@dataclass(frozen=True)
class Convention:
    """A pose convention: how to rewrite the messages, and the config keys (`--set`
    arguments) a log in it is ingested with."""

    rewrite: Callable[[Iterator[Message]], Iterator[Message]] | None
    settings: tuple[str, ...] = ()


_BASE = [*ROBOT_BASE[:3, 3].round(12).tolist(), *_BASE_QUAT]
CONVENTIONS = {
    "topics": Convention(None),
    "tf": Convention(tf, ("topics.camera_pose=/tf", "topics.tool_pose=/tf")),
    "tf-tree": Convention(tf_tree, ("topics.camera_pose=/tf", "topics.tool_pose=/tf")),
    "tracker-frame": Convention(tracker_frame),
    "robot-base": Convention(robot_base, (f"tool.base_to_world={_BASE}",)),
}
