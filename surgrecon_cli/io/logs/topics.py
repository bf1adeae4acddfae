"""Topic roles from the `[topics]` config: which channel is which camera's image, intrinsics,
pose, and which carries the tool pose and joint states.

Patterns hold a `{camera}` placeholder that captures the camera id (`[^/]+`). A pose role whose
topic carries transforms (TFMessage, FrameTransform(s)) picks its transforms by child frame:
`camera_frame` (with `{camera}`) for cameras, `tool_frame` for the tool. The robot's roles
(`tool_pose`, `joint_states`) are optional: an empty pattern says the log does not record
it (tool removal is then off); a configured one must be found in the log.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from ...config import TopicsConfig

ROLES = ("image", "camera_info", "camera_pose", "tool_pose", "joint_states")
REQUIRED_ROLES = ("image", "camera_info", "camera_pose")
OPTIONAL_ROLES = ("tool_pose", "joint_states")
EXTRA_TOOL_ROLE = "extra_tool_pose"
"""The role of each `[[tools]]` pose topic; the item's `camera` is the tool's index."""
ROLE_KINDS: dict[str, tuple[str, ...]] = {
    EXTRA_TOOL_ROLE: ("pose", "transforms"),
    "image": ("image",),
    "camera_info": ("camera_info",),
    "camera_pose": ("pose", "transforms"),
    "tool_pose": ("pose", "transforms"),
    "joint_states": ("joint_states",),
}
CAMERA_ROLES = ("image", "camera_info", "camera_pose")


def pattern_regex(pattern: str) -> re.Pattern[str]:
    """`/endoscope_{camera}/pose` -> a regex matching the whole name, group `camera` = the id."""
    parts = [re.escape(p) for p in pattern.split("{camera}")]
    regex = parts[0]
    for i, part in enumerate(parts[1:]):
        regex += ("(?P<camera>[^/]+)" if i == 0 else "(?P=camera)") + part
    return re.compile(regex + r"\Z")


@dataclass(frozen=True)
class RoleMatch:
    """A channel plays `role`; `camera` is the captured id ("" if none in the pattern)."""

    role: str
    camera: str


class TopicRoles:
    """Compiled `[topics]` patterns, and the pose topics of `extra_tools` (`[[tools]]`)."""

    def __init__(self, topics: TopicsConfig, extra_tools: tuple[str, ...] = ()) -> None:
        self.config = topics
        self.patterns = {role: getattr(topics, role) for role in ROLES if getattr(topics, role)
                         and not (role == "camera_pose" and topics.poses_from_camera_info)}
        self._topic_re = {role: pattern_regex(p) for role, p in self.patterns.items()}
        self._extra_re = [pattern_regex(p) for p in extra_tools]
        # Every role the config names must be found in the log.
        self.required = (*(r for r in REQUIRED_ROLES if r in self.patterns),
                         *(r for r in OPTIONAL_ROLES if r in self.patterns))
        if extra_tools:
            self.patterns[EXTRA_TOOL_ROLE] = " ".join(extra_tools)
            self.required = (*self.required, EXTRA_TOOL_ROLE)
        self._camera_frame = pattern_regex(topics.camera_frame)
        self._tool_frame = pattern_regex(topics.tool_frame)

    def match(self, topic: str) -> list[RoleMatch]:
        """Every role whose topic pattern matches `topic` in full."""
        out = []
        for role, regex in self._topic_re.items():
            m = regex.match(topic)
            if m:
                out.append(RoleMatch(role, m.groupdict().get("camera") or ""))
        out += [RoleMatch(EXTRA_TOOL_ROLE, str(k)) for k, regex in enumerate(self._extra_re)
                if regex.match(topic)]
        return out

    def camera_of_frame(self, child_frame_id: str) -> str | None:
        """Camera id of a transform's child frame (`camera_frame` pattern), or None."""
        m = self._camera_frame.match(child_frame_id)
        if m is None:
            return None
        return m.groupdict().get("camera") or ""

    def is_tool_frame(self, child_frame_id: str) -> bool:
        return self._tool_frame.match(child_frame_id) is not None
