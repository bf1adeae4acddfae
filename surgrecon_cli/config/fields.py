"""Helpers of the config schema: documented fields and range checks."""

from __future__ import annotations

from dataclasses import field
from typing import Any

from ..errors import ConfigError


def _doc(default: Any, doc: str) -> Any:
    """A dataclass field with a one-line docstring (shown by `surgrecon config`)."""
    return field(default=default, metadata={"doc": doc})


def _require(cond: bool, key: str, message: str) -> None:
    if not cond:
        raise ConfigError(f"{key}: {message}")
