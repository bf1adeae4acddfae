"""`scan_log`: the whole description of a log, in one pass over its files.

files (log_input) -> channels + transforms (channels) -> TF tree -> role guesses and the
suggested `[topics]` (roles) -> world frame and pose chains (poses) -> `LogInfo`, which
render.py prints and config_text.py turns into a config.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from ..config import from_dict
from ..core.sync.tf_tree import TfTree, build_tf_tree
from ..errors import ConfigError
from ..io.logs.log_input import METADATA, resolve_log
from .channels import ChannelInfo, FileInfo, scan_channels
from .poses import PosePlan, plan_poses, suggest_world
from .roles import RoleGuess, guess_roles


@dataclass(frozen=True)
class LogInfo:
    """Everything `surgrecon info` prints. `path` is what was named (a file or a folder),
    `files` its files in recording order; `topics` is the suggested `[topics]` block
    ({key: value}, only keys that were found, `world_frame` included) and `poses` how ingest
    composes each pose with it (None when the block cannot be checked)."""

    path: Path
    files: tuple[FileInfo, ...]
    bag: bool
    profile: str
    library: str
    channels: tuple[ChannelInfo, ...]
    tf_tree: TfTree | None
    tf_error: str
    roles: tuple[RoleGuess, ...]
    topics: dict[str, str] = field(default_factory=dict)
    poses: PosePlan | None = None

    @property
    def size(self) -> int:
        return sum(f.size for f in self.files)

    @property
    def indexed(self) -> bool:
        """Every file's summary and indexes were used."""
        return all(f.indexed for f in self.files)

    @property
    def damage(self) -> str | None:
        """Where each damaged file's valid data ends (the file named when there are several)."""
        damaged = [f for f in self.files if f.damage]
        if len(self.files) == 1:
            return damaged[0].damage if damaged else None
        return "; ".join(f"{f.path.name}: {f.damage}" for f in damaged) or None

    @property
    def has_images(self) -> bool:
        """Some channel carries camera images (without one nothing can be reconstructed)."""
        return any(c.kind == "image" for c in self.channels)

    @property
    def world_frame(self) -> str:
        return self.topics.get("world_frame", "world")

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


def scan_log(path: Path | str, time_source: str = "header") -> LogInfo:
    """Describe the log at `path`: an MCAP file, a rosbag2 bag folder or a folder of split
    .mcap files. Damage does not raise: what was read before it is described and `damage`
    says where it is. Raises InputError when there is no log at `path`, a file is not MCAP,
    or a transform message does not decode."""
    log = resolve_log(path)
    scanned = scan_channels(log.files, time_source)
    tree, tf_error = None, ""
    if scanned.transform_topics:
        tree = build_tf_tree(scanned.samples)
        tf_error = "; ".join(tree.problems.values())
    roles, topics = guess_roles(scanned.channels, tree)
    cameras = next(r.cameras for r in roles if r.role == "image")
    poses = None
    try:
        suggested = from_dict({"topics": dict(topics)}).topics
    except ConfigError:
        suggested = None
    if suggested is not None:
        world = suggest_world(scanned.channels, tree, suggested, cameras)
        topics["world_frame"] = world
        poses = plan_poses(scanned.channels, tree, from_dict({"topics": dict(topics)}).topics,
                           cameras)
    bag = log.path.is_dir() and (log.path / METADATA).is_file()
    return LogInfo(log.path, scanned.files, bag, scanned.profile, scanned.library,
                   scanned.channels, tree, tf_error, roles, topics, poses)
