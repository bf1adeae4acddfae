"""`surgrecon compare`: key figures of runs side by side and the config keys that differ."""

from __future__ import annotations

import shutil

import pytest

from surgrecon_cli.cli.main import main
from surgrecon_cli.io.run.layout import RunLayout
from surgrecon_cli.report.compare import config_differences, load_runs


@pytest.fixture(scope="module")
def two_runs(pipeline_log, pipeline_run, tmp_path_factory):
    """The session's run and a copy rerun with one key changed (classify and later)."""
    root = tmp_path_factory.mktemp("compare")
    base = pipeline_run[0]
    other = root / "significance"
    shutil.copytree(base, other)
    assert main(["run", str(pipeline_log), "-o", str(other), "-q",
                 "--set", "classify.significance=0.001"]) == 0
    return base, other


def test_table_has_the_key_figures_and_the_one_differing_key(two_runs, capsys):
    base, other = two_runs
    assert main(["compare", str(base), str(other)]) == 0
    out = capsys.readouterr().out
    header = out.splitlines()[0].split()
    assert header == [base.name, other.name]
    for row in ("template points", "template error median (mm)",
                "registration error median (mm)", "macro F1", "static fraction",
                "pixel noise (px)", "register (s)", "total (s)"):
        line = next(line for line in out.splitlines() if line.startswith(row))
        cells = line[len(row):].split()
        assert len(cells) == 2 and "-" not in cells, line
    assert "config keys that differ (1):" in out
    (line,) = [line for line in out.splitlines() if line.startswith("classify.significance")]
    assert line.split()[1:] == ["0.01", "0.001"]
    runs = load_runs([base, other])
    assert config_differences(runs) == [("classify.significance", [0.01, 0.001])]
    same = [r.figures["template points"] for r in runs]
    assert same[0] == same[1]  # the template was not rebuilt


def test_same_config_and_clashing_names(two_runs, capsys):
    base, _ = two_runs
    assert main(["compare", str(base), str(base)]) == 0
    out = capsys.readouterr().out
    assert "config: the same in every run" in out
    assert out.splitlines()[0].split() == [str(base), str(base)]  # labelled by path


def test_html_overlays_the_per_frame_figures(two_runs, tmp_path, capsys):
    base, other = two_runs
    page = tmp_path / "compare.html"
    assert main(["compare", str(base), str(other), "--html", str(page), "-q"]) == 0
    html = page.read_text()
    assert html.count("data:image/png;base64,") >= 5
    assert "classify.significance" in html and "macro F1" in html
    assert f"html -> {page}" in capsys.readouterr().out


def test_missing_figures_are_dashes(two_runs, tmp_path, capsys):
    base, _ = two_runs
    bare = tmp_path / "bare"
    shutil.copytree(base, bare)
    shutil.rmtree(RunLayout(bare).metrics_dir)
    assert main(["compare", str(base), str(bare), "--html", str(tmp_path / "p.html")]) == 0
    out = capsys.readouterr().out
    line = next(line for line in out.splitlines() if line.startswith("macro F1"))
    assert line.split()[-1] == "-"
    assert "config: the same in every run" in out


def test_not_a_run_folder_is_one_line(tmp_path, capsys):
    assert main(["compare", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and "run.json" in err[0]
