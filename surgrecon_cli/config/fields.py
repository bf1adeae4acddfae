"""Helpers of the config schema: documented fields with bounds, and range checks."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import field
from typing import Any

from ..errors import ConfigError


def _doc(default: Any, doc: str, bounds: tuple[float, float] | None = None) -> Any:
    """A dataclass field with a one-line docstring (shown by `surgrecon config`) and, for a
    number (or each number of a list), its inclusive bounds (`check_bounds`)."""
    metadata: dict[str, Any] = {"doc": doc}
    if bounds is not None:
        metadata["bounds"] = bounds
    return field(default=default, metadata=metadata)


def _require(cond: bool, key: str, message: str) -> None:
    if not cond:
        raise ConfigError(f"{key}: {message}")


def check_bounds(section: Any, name: str) -> None:
    """ConfigError naming `name.key` for a number of config section `section` that is not
    finite or lies outside its field's bounds (a size or count beyond them would ask for
    more memory or time than any log needs)."""
    for f in dataclasses.fields(section):
        if "bounds" not in f.metadata:
            continue
        low, high = f.metadata["bounds"]
        value = getattr(section, f.name)
        for v in value if isinstance(value, tuple) else (value,):
            _require(math.isfinite(v) and low <= v <= high, f"{name}.{f.name}",
                     f"must be between {low:g} and {high:g}, got {v!r}")
