"""stages/staleness.py: which stage must run again in a run folder for a config, and why.

The run folder is built by hand (run.json entries and empty key outputs), so each rule is
checked alone: changed config keys (cumulative along the pipeline), not done, a missing key
output, changed ground truth, resuming a resumable stage, the upstream-config check."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import pytest

from surgrecon_cli.config import ClassifyConfig, Config, IngestConfig, TemplateConfig
from surgrecon_cli.errors import RunFolderError
from surgrecon_cli.io.run.folder import RunFolder
from surgrecon_cli.io.run.layout import RunLayout
from surgrecon_cli.stages.staleness import (
    NOT_DONE,
    changed_keys,
    check_upstream,
    recorded_config,
    same_config,
    why_stale,
)

DONE = ("ingest", "build-template", "register", "classify", "evaluate")


@pytest.fixture
def run(tmp_path: Path) -> RunFolder:
    """A run folder whose first stages (and evaluate, with ground truth "abc") are done with
    the default config, their key outputs present."""
    log = tmp_path / "log.mcap"
    log.write_bytes(b"x")
    folder = RunFolder(tmp_path / "run")
    folder.start(log, Config())
    layout = RunLayout(folder.path)
    layout.ingest_dir.mkdir()
    layout.registration_dir.mkdir()
    for path in (layout.template_ply, layout.labels, layout.evaluation_json):
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(b"")
    for stage in DONE:
        extra = {"ground_truth": {"sha256": "abc"}} if stage == "evaluate" else {}
        folder.mark_stage(stage, "done", config=recorded_config(Config(), stage), **extra)
    return folder


def _with(**sections: Any) -> Config:
    return dataclasses.replace(Config(), **sections)


def test_valid_outputs_and_not_done(run: RunFolder):
    for stage in DONE:
        assert why_stale(run, stage, Config(), "abc") == "", stage
        assert changed_keys(run, stage, Config()) == []
    assert why_stale(run, "measure", Config(), "abc") == NOT_DONE


def test_changed_keys_accumulate_along_the_pipeline(run: RunFolder):
    later = _with(template=TemplateConfig(max_features=10))
    assert changed_keys(run, "ingest", later) == []
    for stage in ("build-template", "register", "classify"):
        assert changed_keys(run, stage, later) == ["template"]
        assert why_stale(run, stage, later, "abc") == "config changed (template)"
    knob = _with(classify=ClassifyConfig(significance=0.2))
    # classify and every stage after it (evaluate), none before
    assert [s for s in DONE if changed_keys(run, s, knob)] == ["classify", "evaluate"]


def test_the_stage_entry_wins_over_run_json_config(run: RunFolder):
    data = run.read()
    data["config"]["classify"]["significance"] = 0.2  # run.json's config says otherwise
    run.write(data)
    assert changed_keys(run, "classify", Config()) == []  # classify's own record is the default
    del data["stages"]["classify"]["config"]
    run.write(data)
    assert changed_keys(run, "classify", Config()) == ["classify"]


def test_missing_key_output_and_changed_ground_truth(run: RunFolder):
    RunLayout(run.path).template_ply.unlink()
    assert why_stale(run, "build-template", Config(), "abc") == "template.ply is missing"
    assert why_stale(run, "evaluate", Config(), "other") == "ground truth changed"
    assert why_stale(run, "evaluate", Config(), None) == "ground truth changed"


def test_a_resumable_stage_resumes_only_with_its_config(run: RunFolder):
    run.mark_stage("register", "running", config=recorded_config(Config(), "register"))
    assert why_stale(run, "register", Config(), None) == NOT_DONE
    assert why_stale(run, "register", Config(), None, resume=True) == ""
    assert same_config(run, "register", Config())
    moved = _with(classify=ClassifyConfig(significance=0.2))  # not a key register reads
    assert same_config(run, "register", moved)
    other = _with(template=TemplateConfig(max_features=10))
    assert not same_config(run, "register", other)
    assert why_stale(run, "register", other, None, resume=True) == "config changed (template)"
    # a non-resumable stage that is not done must run even when resuming is allowed
    run.mark_stage("classify", "running", config=recorded_config(Config(), "classify"))
    assert why_stale(run, "classify", Config(), None, resume=True) == NOT_DONE


def test_upstream_config_is_checked_only_by_stages_that_read_it(run: RunFolder):
    changed = _with(ingest=IngestConfig(pose_gap_ms=50.0))
    with pytest.raises(RunFolderError, match=r"ingest\.pose_gap_ms"):
        check_upstream(run, "build-template", changed)
    check_upstream(run, "classify", changed)  # classify reads only its own section
    check_upstream(run, "build-template", Config())
