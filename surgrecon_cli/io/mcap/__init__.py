"""Reading MCAP logs: one adapter per message encoding, an explicit schema registry, topic
roles from the config, and a streaming reader that survives truncated files."""

from .reader import LogItem, LogReader
from .registry import DECODERS
from .topics import ROLES, TopicRoles

__all__ = ["DECODERS", "ROLES", "LogItem", "LogReader", "TopicRoles"]
