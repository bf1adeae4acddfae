"""Typed config: defaults file, overrides, rejection of bad keys and values."""

from __future__ import annotations

from pathlib import Path

import pytest

from surgrecon_cli.config import Config, load_config, to_toml
from surgrecon_cli.config.schema import ExtraToolConfig, ToolConfig
from surgrecon_cli.errors import ConfigError

ROOT = Path(__file__).resolve().parents[1]


def test_default_toml_mirrors_the_dataclass_defaults():
    assert load_config(ROOT / "configs" / "default.toml") == Config()
    body = (ROOT / "configs" / "default.toml").read_text()
    assert to_toml(Config()).strip() in body


def test_example_config_is_valid():
    load_config(ROOT / "configs" / "example.toml")


def test_user_file_and_set_overrides(tmp_path):
    path = tmp_path / "user.toml"
    path.write_text('[topics]\nimage = "/cam_{camera}/image"\n[registration]\nalpha = 0.03\n')
    config = load_config(path, ["registration.alpha=0.02", "tool.base_to_world=[0,0,0,0,0,0,1]"])
    assert config.topics.image == "/cam_{camera}/image"
    assert config.registration.alpha == 0.02
    assert config.tool.base_to_world == (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)
    assert config.template == Config().template  # untouched sections keep their defaults


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("registration.nope=1", "registration.nope: unknown key"),
        ("nosection.key=1", "nosection: unknown config section"),
        ("registration.k_neighbors=2.5", "registration.k_neighbors: expected an integer"),
        ("tool.shaft_radius_m=-1", "tool.shaft_radius_m: must be > 0"),
        ("ingest.time_source=wall", "ingest.time_source"),
        ("topics.image=/no/placeholder", "topics.image: needs a {camera} placeholder"),
        ("registration", "expected section.key=value"),
    ],
)
def test_bad_overrides_name_the_key(override, message):
    with pytest.raises(ConfigError, match=message.replace("{", r"\{").replace("}", r"\}")):
        load_config(None, [override])


def test_bad_file(tmp_path):
    path = tmp_path / "bad.toml"
    path.write_text("[topics\n")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(path)
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "missing.toml")


def test_keys_renamed_with_their_unit_are_still_read():
    config = load_config(overrides=["tool.shaft_radius=0.005", "target.occlusion_depth=0.01"])
    assert config.tool.shaft_radius_m == 0.005 and config.target.occlusion_depth_m == 0.01
    assert load_config(overrides=["tool.margin=0.002"]).tool.margin_m == 0.002


@pytest.mark.parametrize(
    ("override", "key"),
    [
        ("ingest.sync_tolerance_ms=inf", "ingest.sync_tolerance_ms"),
        ("ingest.pose_gap_ms=nan", "ingest.pose_gap_ms"),
        ("target.klt_window_px=100000", "target.klt_window_px"),
        ("deformation.ring_points=100000000", "deformation.ring_points"),
        ("target.klt_levels=-3", "target.klt_levels"),
        ("tool.base_to_world=[0,0,0,0,0,0,inf]", "tool.base_to_world"),
    ],
)
def test_values_that_would_fail_later_are_refused_at_load(override, key):
    with pytest.raises(ConfigError, match=rf"{key}: must be"):
        load_config(None, [override])


def test_every_numeric_key_has_bounds_that_hold_its_default():
    import dataclasses

    tool_tables = {f.name for f in dataclasses.fields(ExtraToolConfig)}
    assert {f.name for f in dataclasses.fields(ToolConfig)} <= tool_tables  # bounded as [tool]
    for section in dataclasses.fields(Config):
        if not dataclasses.is_dataclass(getattr(Config(), section.name)):
            continue  # [[tools]]: a tuple of tables, each a ToolConfig (above)
        for f in dataclasses.fields(section.type if isinstance(section.type, type)
                                    else type(getattr(Config(), section.name))):
            default = getattr(getattr(Config(), section.name), f.name)
            if isinstance(default, bool) or not isinstance(default, int | float | tuple):
                continue
            if "str" in str(f.type):  # a list of strings (tool.camera_offsets: checked as parsed)
                continue
            low, high = f.metadata["bounds"]
            assert all(low <= v <= high for v in (default if isinstance(default, tuple)
                                                  else (default,))), (section.name, f.name)


def test_bom_deep_nesting_and_old_with_new_key(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text("\ufeff[ingest]\nsync_tolerance_ms = 20\n", encoding="utf-8")
    assert load_config(path).ingest.sync_tolerance_ms == 20.0
    path.write_text("[ingest]\nx = " + "[" * 50_000 + "]" * 50_000 + "\n")
    with pytest.raises(ConfigError, match="nested too deeply"):
        load_config(path)
    path.write_text("[tool]\nshaft_radius = 0.005\nshaft_radius_m = 0.006\n")
    with pytest.raises(ConfigError, match=r"tool\.shaft_radius: is the old name of "
                                          r"tool\.shaft_radius_m"):
        load_config(path)
