"""`run --tag LABEL`: RUN-LABEL beside RUN, starting from RUN's outputs whose config keys did
not change (hard links), computing only the rest; the result equals a from-scratch run."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from surgrecon_cli.config import Config
from surgrecon_cli.io.run.folder import RunFolder
from surgrecon_cli.pipeline import run_pipeline, tagged
from surgrecon_cli.planning import reusable_stages
from surgrecon_cli.report.compare import load_runs


def _inode(path: Path) -> int:
    return path.stat().st_ino


def test_tagged_run_reuses_unchanged_stages_and_equals_a_fresh_run(pipeline_log: Path,
                                                                    pipeline_run, copy_run):
    fresh, _ = pipeline_run  # from scratch, default config
    # the copy's labels were made (so run.json says) with another classify.significance
    folder = RunFolder(copy_run)
    data = folder.read()
    data["config"]["classify"]["significance"] = 0.123
    for stage in ("classify", "measure", "evaluate", "report"):
        data["stages"][stage]["config"]["classify"]["significance"] = 0.123
    folder.write(data)
    assert reusable_stages(folder, Config(), None) == ("ingest", "build-template", "register")

    out = tagged(copy_run, "default")
    assert out == copy_run.parent / "run-default"
    result = run_pipeline(pipeline_log, out, Config(), seed_from=copy_run)

    assert [result.actions[s] for s in ("ingest", "build-template", "register")] == ["reused"] * 3
    assert result.actions["classify"] == "ran" and result.actions["report"] == "ran"
    assert not {"ingest", "build-template", "register"} & set(result.seconds)
    for rel in ("ingest/frames.npz", "template.ply", "registration/000001.npz"):
        assert _inode(out / rel) == _inode(copy_run / rel), rel  # the same file, linked
    assert _inode(out / "classify/labels.npz") != _inode(copy_run / "classify/labels.npz")
    stages = RunFolder(out).read()["stages"]
    assert stages["register"]["reused_from"] == str(copy_run.resolve())
    made_with = stages["classify"]["config"]["classify"]["significance"]
    assert made_with == Config().classify.significance

    with (np.load(out / "classify/labels.npz") as got,
          np.load(fresh / "classify/labels.npz") as want):
        np.testing.assert_array_equal(got["labels"], want["labels"])
    last = sorted((fresh / "clouds").iterdir())[-1].name
    assert (out / "clouds" / last).read_bytes() == (fresh / "clouds" / last).read_bytes()
    ev_got = json.loads((out / "metrics/evaluation.json").read_text())
    ev_want = json.loads((fresh / "metrics/evaluation.json").read_text())
    assert ev_got["labels"]["overall"] == ev_want["labels"]["overall"]
    assert "<tr><td>register</td><td>reused</td>" in (out / "report.html").read_text()
    (figures,) = load_runs([out])
    assert figures.figures["register (s)"] == "reused"
    assert figures.figures["classify (s)"] == stages["classify"]["seconds"]
    # the original run is untouched
    assert RunFolder(copy_run).read()["config"]["classify"]["significance"] == 0.123


def test_nothing_reused_from_another_logs_run_or_into_an_existing_run(pipeline_run, tmp_path):
    from surgrecon_cli.planning import seed_run

    fresh, _ = pipeline_run
    assert seed_run(fresh, tmp_path / "a", Config(), "0" * 64, None) == ()
    assert not (tmp_path / "a").exists()
    (tmp_path / "b").mkdir()
    RunFolder(tmp_path / "b").write({"stages": {}})
    sha = RunFolder(fresh).input_hash
    assert seed_run(fresh, tmp_path / "b", Config(), sha, None) == ()
