"""What a log holds, for `surgrecon info`: channels, the TF tree, which topics and frames
look like each `[topics]` role, how ingest would compose every pose, and a starter config.

Data flow, one module each:

  channels.py     scan the files (log_input) once: channel statistics merged over the files,
                  every transform, the first message of the other channels
  patterns.py     `{camera}` patterns from names (pure)
  roles.py        channels + TF tree -> role guesses and the suggested `[topics]`
  poses.py        `[topics]` + channels + TF tree -> world frame and per-camera / tool chains
  scan.py         `scan_log`: the above in order -> `LogInfo`
  config_text.py  `LogInfo` -> the `[topics]` TOML block; a config's `[topics]` checked
  render.py       `LogInfo` -> the printed text
"""

from .channels import ChannelInfo, FileInfo
from .config_text import check_topics, topics_toml
from .patterns import camera_pattern, captures
from .poses import Hop, PoseChain, PosePlan
from .render import format_info
from .roles import ROLE_NAMES, RoleGuess
from .scan import LogInfo, scan_log

__all__ = ["ROLE_NAMES", "ChannelInfo", "FileInfo", "Hop", "LogInfo", "PoseChain", "PosePlan",
           "RoleGuess", "camera_pattern", "captures", "check_topics", "format_info",
           "scan_log", "topics_toml"]
