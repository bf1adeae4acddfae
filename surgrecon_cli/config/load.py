"""Config loading: TOML files and `--set section.key=value` overrides merged over the
defaults, each value checked against its field's type (ints are accepted for floats)."""

from __future__ import annotations

import dataclasses
import logging
import tomllib
import typing
from pathlib import Path
from typing import Any

from ..errors import ConfigError, cut
from .schema import Config, ExtraToolConfig, _require

logger = logging.getLogger(__name__)
# Keys renamed so that each name carries its unit; the old names are still read.
RENAMED = {
    "tool.shaft_radius": "shaft_radius_m",
    "tool.shaft_length": "shaft_length_m",
    "tool.margin": "margin_m",
    "template.working_distance": "working_distance_m",
    "target.occlusion_depth": "occlusion_depth_m",
}


def _coerce(value: Any, annotation: Any, key: str) -> Any:
    """Check a TOML value against a field's type; ints are accepted for floats."""
    origin = typing.get_origin(annotation)
    if origin is tuple:
        _require(isinstance(value, list | tuple), key, f"expected a list, got {value!r}")
        item = (typing.get_args(annotation) or (float,))[0]
        return tuple(_coerce(v, item, key) for v in value)
    if annotation is float:
        _require(
            isinstance(value, int | float) and not isinstance(value, bool),
            key,
            f"expected a number, got {value!r}",
        )
        return float(value)
    if annotation is int:
        _require(
            isinstance(value, int) and not isinstance(value, bool),
            key,
            f"expected an integer, got {value!r}",
        )
        return value
    if annotation is bool:
        _require(isinstance(value, bool), key, f"expected true/false, got {value!r}")
        return value
    _require(isinstance(value, str), key, f"expected a string, got {value!r}")
    return value


def _section_types(section_cls: type) -> dict[str, Any]:
    return typing.get_type_hints(section_cls)


def from_dict(data: dict[str, Any], base: Config | None = None) -> Config:
    """Merge a nested dict (as read from TOML) over `base` (default: the defaults)."""
    base = base or Config()
    sections: dict[str, Any] = {}
    section_types = _section_types(Config)
    for name, values in data.items():
        _require(
            name in section_types,
            name,
            f"unknown config section (known: {', '.join(section_types)})",
        )
        if name == "tools":
            sections[name] = _tools(values)
            continue
        _require(isinstance(values, dict), name, "must be a table")
        cls = section_types[name]
        hints = _section_types(cls)
        current = getattr(base, name)
        updates = {}
        for key, value in values.items():
            full = f"{name}.{key}"
            _require(full not in RENAMED or RENAMED[full] not in values, full,
                     f"is the old name of {name}.{RENAMED.get(full)}; give only the new one")
            if full in RENAMED:
                logger.warning("config key %s is now %s.%s (same unit); please rename it",
                               full, name, RENAMED[full])
                key, full = RENAMED[full], f"{name}.{RENAMED[full]}"
            _require(key in hints, full, f"unknown key (known: {', '.join(hints)})")
            updates[key] = _coerce(value, hints[key], full)
        sections[name] = dataclasses.replace(current, **updates)
    return dataclasses.replace(base, **sections)


def _tools(values: Any) -> tuple[ExtraToolConfig, ...]:
    """`[[tools]]`: an array of tables, one per tool."""
    _require(isinstance(values, list) and all(isinstance(v, dict) for v in values), "tools",
             "must be an array of tables ([[tools]] with pose = ... and the [tool] keys)")
    hints = _section_types(ExtraToolConfig)
    tools = []
    for k, table in enumerate(values):
        for key in table:
            _require(key in hints, f"tools[{k}].{key}", f"unknown key (known: {', '.join(hints)})")
        tools.append(ExtraToolConfig(**{key: _coerce(v, hints[key], f"tools[{k}].{key}")
                                        for key, v in table.items()}))
    return tuple(tools)


def parse_override(text: str) -> dict[str, Any]:
    """`section.key=value` -> {section: {key: value}}; the value is read as TOML, else a string."""
    if "=" not in text or "." not in text.split("=", 1)[0]:
        raise ConfigError(f"--set {text!r}: expected section.key=value")
    path, raw = text.split("=", 1)
    section, key = path.strip().split(".", 1)
    try:
        value = tomllib.loads(f"v = {raw}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw
    except RecursionError as exc:
        raise ConfigError(f"--set {path}: value nested too deeply") from exc
    return {section: {key: value}}


def load_config(path: Path | None = None, overrides: typing.Sequence[str] = ()) -> Config:
    """Defaults, then the TOML file at `path`, then each `--set` override in order."""
    config = Config()
    if path is not None:
        try:  # (utf-8-sig: a byte-order mark some editors write is accepted)
            data = tomllib.loads(Path(path).read_text(encoding="utf-8-sig"))
        except FileNotFoundError as exc:
            raise ConfigError(f"{path}: config file not found") from exc
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
            raise ConfigError(f"{path}: not valid TOML ({cut(str(exc))})") from exc
        except RecursionError as exc:
            raise ConfigError(f"{path}: not valid TOML (nested too deeply)") from exc
        except OSError as exc:
            raise ConfigError(f"{path}: unreadable ({exc.strerror or type(exc).__name__})"
                              ) from exc
        config = from_dict(data, config)
    for text in overrides:
        config = from_dict(parse_override(text), config)
    return config
