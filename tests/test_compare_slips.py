"""`surgrecon compare`: the measure stage is timed like the others, and identical runs are
said to be identical rather than one line hiding the other."""

from __future__ import annotations

from surgrecon_cli.io.run.folder import RunFolder
from surgrecon_cli.report.compare import load_runs
from surgrecon_cli.report.compare_html import comparison_html


def test_measure_stage_is_compared(pipeline_run):
    base, _ = pipeline_run
    (run,) = load_runs([base])
    recorded = RunFolder(base).read()["stages"]["measure"]["seconds"]
    assert run.figures["measure (s)"] == recorded
    stages = ("ingest", "build-template", "register", "classify", "measure", "evaluate",
              "report")
    assert run.figures["total (s)"] == sum(run.figures[f"{s} (s)"] for s in stages)


def test_identical_runs_are_named_as_such(pipeline_run):
    base, _ = pipeline_run
    runs = load_runs([base, base])
    html = comparison_html(runs)
    assert html.count(f"{base} is identical to {base}") >= 5  # one caption per drawn figure
