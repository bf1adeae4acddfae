"""io.run.folder: run.json creation, atomic stage updates, input and config checks."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest

from surgrecon_cli.config import Config, IngestConfig, load_config
from surgrecon_cli.errors import RunFolderError
from surgrecon_cli.io.run.folder import RunFolder, file_sha256, package_versions


def test_start_mark_and_read(tmp_path: Path):
    log = tmp_path / "log.mcap"
    log.write_bytes(b"abc")
    run = RunFolder(tmp_path / "run")
    assert not run.exists() and run.stage_status("ingest") is None
    with pytest.raises(RunFolderError, match="not a run folder"):
        run.read()
    run.start(log, Config())
    assert (tmp_path / "run/config.toml").is_file()
    assert load_config(tmp_path / "run/config.toml") == Config()
    run.mark_stage("ingest", "running")
    assert run.stage_status("ingest") == "running" and not run.is_done("ingest")
    with pytest.raises(RunFolderError, match="stage ingest is running"):
        run.require_done("ingest")
    run.update(input={"path": str(log), "sha256": file_sha256(log), "bytes": 3})
    run.mark_stage("ingest", "done", frames=4, cameras=("0", "1"))
    run.require_done("ingest")
    assert run.stage("ingest") == {"status": "done", "frames": 4, "cameras": ["0", "1"]}
    assert run.input_hash == file_sha256(log)
    run.check_input(log)
    log.write_bytes(b"abd")
    with pytest.raises(RunFolderError, match="another log"):
        run.check_input(log)
    with pytest.raises(ValueError):
        run.mark_stage("ingest", "finished")
    assert [p.name for p in run.path.iterdir() if p.name.startswith(".")] == []
    assert json.loads(run.run_json.read_text())["versions"] == package_versions()


def test_check_config_names_the_changed_key(tmp_path: Path):
    log = tmp_path / "log.mcap"
    log.write_bytes(b"x")
    run = RunFolder(tmp_path)
    run.start(log, Config())
    run.check_config(Config())
    changed = dataclasses.replace(Config(), ingest=IngestConfig(pose_gap_ms=50.0))
    with pytest.raises(RunFolderError, match=r"ingest\.pose_gap_ms = 100\.0, now 50\.0"):
        run.check_config(changed)
    run.check_config(changed, keys=("topics", "registration"))


def test_corrupt_run_json(tmp_path: Path):
    (tmp_path / "run.json").write_text("{not json")
    with pytest.raises(RunFolderError, match="unreadable"):
        RunFolder(tmp_path).read()
