"""The command line: help texts with examples, one-line errors, exit codes."""

from __future__ import annotations

import pytest

from surgrecon_cli.cli.main import cli, main


def test_top_level_help_lists_the_pipeline(capsys):
    assert main(["--help"]) == 0
    out = capsys.readouterr().out
    for command in ("simulate", "ingest", "build-template", "register", "config"):
        assert command in out


# Commands that take no config: export and compare read finished runs with the config they
# were made with; convert writes the config that runs its log.
NO_CONFIG_COMMANDS = {"export", "compare", "convert"}


@pytest.mark.parametrize("command", sorted(cli.commands))
def test_every_subcommand_has_help_with_an_example(command, capsys):
    assert main([command, "--help"]) == 0
    out = capsys.readouterr().out
    assert "Example" in out
    assert "surgrecon " + command in out
    assert "--quiet" in out and "--debug" in out
    if command not in NO_CONFIG_COMMANDS:
        assert "--config" in out and "--set" in out


def test_config_error_is_one_line_and_nonzero(capsys):
    assert main(["config", "--set", "registration.nope=1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["error: registration.nope: unknown key (known: " + err[0].split("(known: ")[1]]


def test_missing_run_folder_is_a_clean_error(tmp_path, capsys):
    assert main(["build-template", str(tmp_path)]) == 2
    errors = [line for line in capsys.readouterr().err.splitlines() if line.startswith("error")]
    assert len(errors) == 1 and "surgrecon ingest LOG.mcap -o" in errors[0]


def test_debug_shows_the_traceback(tmp_path):
    from surgrecon_cli.errors import RunFolderError

    with pytest.raises(RunFolderError):
        main(["build-template", str(tmp_path), "--debug"])
