"""`surgrecon fit-tools`: per-camera tool offsets fitted to an ingested run's images, written
into a config. On the shipped d-lfd frames (tests/data/dlfd, MIT; pairs with disagreeing
hand-eye results), the config it writes puts every marked tip and shaft point (marked by eye,
frames 93/170/248; the fit sees frame 0) in its arm's mask; the config without it does not."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from surgrecon_cli.cli.main import main
from surgrecon_cli.config import load_config

ROOT = Path(__file__).resolve().parents[1]
DLFD = ROOT / "tests" / "data" / "dlfd"
PAIRS = ["--group", "p1l,p1r", "--group", "p2l,p2r", "--group", "p3l,p3r"]


@pytest.fixture(scope="module")
def unfitted(tmp_path_factory: pytest.TempPathFactory):
    """The shipped frame 0 as a log with a config that has no camera_offsets, ingested."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        import dlfd_conventions
        import dlfd_mcap
    finally:
        sys.path.remove(str(ROOT / "benchmarks"))
    tmp = tmp_path_factory.mktemp("fit_tools")
    d = dlfd_mcap.load_shipped(DLFD)
    log, config = dlfd_mcap.build(d, "dlfd", 1, 0, tmp, fit_shafts=False)
    run = tmp / "run"
    assert main(["ingest", str(log), "-o", str(run), "--config", str(config), "-q"]) == 0
    return d, dlfd_conventions, config, run


def test_written_offsets_put_the_marked_instruments_in_their_masks(unfitted, tmp_path, capsys):
    d, conv, config, run = unfitted
    marks = json.loads((DLFD / "marks.json").read_text(encoding="utf-8"))["marks"]
    hit_before, total, _ = conv.coverage(d, marks, config)
    assert all(not c.camera_offsets for c in load_config(config).tool_configs())
    fitted = tmp_path / "fitted.toml"
    assert main(["fit-tools", str(run), "--config", str(config), *PAIRS,
                 "--write-config", str(fitted), "-q"]) == 0
    out = capsys.readouterr().out
    assert "p2l,p2r tool_1" in out and "used" in out
    new = load_config(fitted)
    assert new.topics == load_config(config).topics  # the rest of the config as it was
    named = {e.split()[0] for c in new.tool_configs() for e in c.camera_offsets}
    assert {"p2l", "p2r"} <= named  # pair 2 is 18-35 px off: both arms get an offset there
    hit, total_after, _ = conv.coverage(d, marks, fitted)
    assert total_after == total == 3 * len(marks)
    assert hit == total and hit_before < total


def test_bad_groups_and_unready_runs_are_one_line_errors(unfitted, tmp_path, capsys):
    _, _, config, run = unfitted
    assert main(["fit-tools", str(run), "--config", str(config), "--group", "p1l,nope"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "'nope'" in err[0] and "p1l" in err[0]
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(["fit-tools", str(empty)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "surgrecon ingest" in err[0]
