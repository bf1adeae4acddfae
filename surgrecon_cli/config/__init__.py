"""Typed, frozen configuration loaded from TOML.

Defaults are the dataclass defaults of `schema.py`; `configs/default.toml` mirrors them (a
test keeps the two equal). A user file needs only the keys it changes; `--set
section.key=value` overrides single keys (`load.py`). Unknown sections/keys, wrong types and
out-of-range values raise `ConfigError` naming the key. Lengths are metres unless the key
name ends in `_mm`/`_px`. `write.py` serialises a config back to TOML.
"""

from ..errors import ConfigError
from .load import from_dict, load_config
from .schema import (
    ClassifyConfig,
    Config,
    DeformationConfig,
    IngestConfig,
    LabelsConfig,
    RegistrationConfig,
    RunConfig,
    TargetConfig,
    TemplateConfig,
    ToolConfig,
    TopicsConfig,
)
from .write import to_dict, to_toml

__all__ = [
    "ClassifyConfig",
    "Config",
    "ConfigError",
    "DeformationConfig",
    "IngestConfig",
    "LabelsConfig",
    "RegistrationConfig",
    "RunConfig",
    "TargetConfig",
    "TemplateConfig",
    "ToolConfig",
    "TopicsConfig",
    "from_dict",
    "load_config",
    "to_dict",
    "to_toml",
]
