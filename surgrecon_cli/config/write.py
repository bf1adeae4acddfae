"""Config writing: TOML with each key's docstring as a comment, and a plain dict (run.json)."""

from __future__ import annotations

import dataclasses
from typing import Any

from .schema import Config

_TOML_ESCAPES = {"\\": "\\\\", '"': '\\"'}


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):  # TOML forbids control characters: escape all non-printables
        return '"' + "".join(_TOML_ESCAPES.get(c) or (c if c.isprintable() else f"\\U{ord(c):08x}")
                             for c in value) + '"'
    if isinstance(value, tuple | list):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    return repr(value)


def to_toml(config: Config, with_docs: bool = True) -> str:
    """Serialise a config to TOML (with each key's docstring as a comment)."""
    lines: list[str] = []
    for section in dataclasses.fields(config):
        obj = getattr(config, section.name)
        for table in obj if isinstance(obj, tuple) else (obj,):  # [[tools]]: one per tool
            lines.append(f"[[{section.name}]]" if isinstance(obj, tuple) else
                         f"[{section.name}]")
            for f in dataclasses.fields(table):
                line = f"{f.name} = {_toml_value(getattr(table, f.name))}"
                if with_docs and f.metadata.get("doc"):
                    line = f"# {f.metadata['doc']}\n{line}"
                lines.append(line)
            lines.append("")
    return "\n".join(lines)


def to_dict(config: Config) -> dict[str, Any]:
    """Plain nested dict of the config (for run.json)."""
    return dataclasses.asdict(config)
