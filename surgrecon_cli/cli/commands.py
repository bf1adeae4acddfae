"""The list of subcommands; each lives in its own `cmd_*.py` module."""

from __future__ import annotations

from .cmd_config import config_cmd

ALL = [config_cmd]
