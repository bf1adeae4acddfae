"""A run's tools are the ingested log's: a config naming another number of them is a
one-line error in every stage that reads the tools' poses."""

from __future__ import annotations

import pytest

from surgrecon_cli.cli.main import main
from surgrecon_cli.io.run.layout import RunLayout


@pytest.mark.parametrize("stage", ["classify", "measure"])
def test_a_config_with_more_tools_than_were_ingested_is_a_one_line_error(
        copy_run, tmp_path, capsys, stage):
    """The tools' poses are read at ingest: a `[[tools]]` entry added later names a tool the
    run has no poses for. The stage says so and which command mends it, and its outputs are
    left as they were."""
    config = tmp_path / "more_tools.toml"
    config.write_text('[[tools]]\npose = "/tool2/pose"\n')
    outputs = {"classify": RunLayout(copy_run).labels,
               "measure": RunLayout(copy_run).root / "metrics" / "deformation.csv"}[stage]
    before = outputs.read_bytes()
    assert main([stage, str(copy_run), "--config", str(config), "-q"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert "ingested with 1 tools, the config has 2; ingest again" in err[0]
    assert outputs.read_bytes() == before
