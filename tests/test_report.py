"""stages.report: frames.csv, summary.json and a self-contained report.html."""

from __future__ import annotations

import base64
import csv
import itertools
import json
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest

from surgrecon_cli.config import Config
from surgrecon_cli.io.run.folder import RunFolder
from surgrecon_cli.stages.report import CLASS_COLUMNS, FRAME_COLUMNS, STATUS_COLUMNS, run_report

VOID = {"meta", "img", "br", "hr", "link", "input"}


class _Checker(HTMLParser):
    """Collects images, links and section ids; checks that tags nest properly."""

    def __init__(self) -> None:
        super().__init__()
        self.stack: list[str] = []
        self.images: list[str] = []
        self.links: list[str] = []
        self.sections: list[str] = []
        self.errors: list[str] = []

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "img":
            self.images.append(a.get("src", ""))
        if tag == "a" or "href" in a:
            self.links.append(a.get("href", ""))
        if tag == "section":
            self.sections.append(a.get("id", ""))
        if tag not in VOID:
            self.stack.append(tag)

    def handle_endtag(self, tag):
        if not self.stack or self.stack[-1] != tag:
            self.errors.append(f"unexpected </{tag}> (open: {self.stack[-3:]})")
        else:
            self.stack.pop()


def _check_html(path: Path) -> _Checker:
    text = path.read_text(encoding="utf-8")
    assert text.startswith("<!DOCTYPE html>")
    checker = _Checker()
    checker.feed(text)
    checker.close()
    assert not checker.errors and checker.stack == [], checker.errors[:3]
    for src in checker.images:  # self-contained: every image embedded, and a real PNG
        assert src.startswith("data:image/png;base64,")
        assert base64.b64decode(src.split(",", 1)[1])[:8] == b"\x89PNG\r\n\x1a\n"
    # links: sections of the page, or files of the run folder (relative, so the folder moves)
    assert all(link.startswith("#") or (link and not link.startswith("/") and ":" not in link)
               for link in checker.links)
    assert "http://" not in text and "https://" not in text
    return checker


def _rows(path: Path) -> tuple[list[str], list[dict[str, str]]]:
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        return list(reader.fieldnames or []), list(reader)


def test_full_report(pipeline_run):
    run_dir, result = pipeline_run
    assert result.report == run_dir / "report.html"
    checker = _check_html(result.report)
    for section in ("overview", "cameras", "labels", "clouds", "registration", "timing",
                    "evaluation", "files"):
        assert section in checker.sections
    assert len(checker.images) >= 12

    columns, rows = _rows(run_dir / "metrics" / "frames.csv")
    assert columns == list(FRAME_COLUMNS)
    n_frames = RunFolder(run_dir).read()["ingest"]["frames"]
    assert [int(r["frame"]) for r in rows] == list(range(n_frames))
    n = int(rows[0]["points"])
    assert int(rows[0]["static"]) == n
    for row in rows:
        assert sum(int(row[c]) for c in CLASS_COLUMNS) == n
    for row in rows[1:]:
        assert sum(int(row[c]) for c in STATUS_COLUMNS) == n
        for col in ("residual_median_mm", "displacement_p95_mm", "seconds_register",
                    "error_median_mm", "macro_f1"):
            assert np.isfinite(float(row[col])), col
        assert float(row["residual_median_mm"]) <= float(row["residual_p95_mm"])
        # a departure counts from deform_mm at best (every direction measured well)
        assert float(row["deform_floor_median_mm"]) >= 0.25 * (1 - 1e-6)

    summary = json.loads((run_dir / "metrics" / "summary.json").read_text(),
                         parse_constant=lambda c: (_ for _ in ()).throw(AssertionError(c)))
    assert summary["frames"] == n_frames and summary["template_points"] == n
    assert set(summary["classes_frames_1_on"]["counts"]) == set(CLASS_COLUMNS)
    assert summary["camera_pairs"]["groups"] and summary["camera_pairs"]["sequence"]
    assert summary["evaluation"]["registration_error_mm"]["count"] == n * (n_frames - 1)
    assert {"ingest", "build-template", "register", "classify"} <= set(summary["seconds"])
    floors = [float(r["deform_floor_median_mm"]) for r in rows[1:]]
    # frames.csv holds 6 significant digits: half a unit of the last is up to 5e-6 of it
    assert summary["classify"]["deform_floor_mm"] == pytest.approx(float(np.median(floors)),
                                                                   rel=5e-6)


def test_report_with_only_the_template(copy_run):
    run = RunFolder(copy_run)
    data = run.read()
    for stage in ("register", "classify", "evaluate", "report"):
        data["stages"].pop(stage)
    run.write(data)
    files = run_report(copy_run, Config())
    checker = _check_html(files.html)
    assert "cameras" in checker.sections and "clouds" in checker.sections
    assert "evaluation" not in checker.sections and "registration" not in checker.sections
    columns, rows = _rows(files.frames_csv)
    assert columns == list(FRAME_COLUMNS) and rows[1]["static"] == "" and rows[1]["intra"] == ""
    assert run.is_done("report")


def test_per_frame_plots_label_their_ticks_by_frame(monkeypatch):
    """A log of more frames than ticks: every tick of a per-frame box plot sits at a frame
    and is labelled with that frame's number, not the box's rank."""
    from surgrecon_cli.report import plots

    drawn: list = []
    monkeypatch.setattr(plots, "to_png", lambda fig: drawn.append(fig) or b"")
    frames = np.arange(5, 81, 2)  # 38 sampled frames: 5, 7, ..., 79
    values = [np.random.default_rng(int(k)).random(20) for k in frames]
    plots.per_frame_boxes(frames, values, "displacement", "mm", lines={"static": 1.0})
    ax = drawn[0].axes[0]
    ticks = ax.get_xticks()
    assert len(ticks) >= 2 and set(ticks) <= set(frames.tolist())
    assert [t.get_text() for t in ax.get_xticklabels()] == [f"{t:g}" for t in ticks]


def test_frame_ticks_do_not_overlap(monkeypatch):
    """The quality panel's half-width axes over 38 frames: the frame numbers on x, drawn,
    keep a space between them (they touched at 19 ticks), and still mark at least every
    10th frame."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    from surgrecon_cli.report import plots

    drawn: list = []
    monkeypatch.setattr(plots, "to_png", lambda fig: drawn.append(fig) or b"")
    frames = np.arange(1, 39)
    shares = {"observed": np.full(38, 0.9), "outlier": np.full(38, 0.05)}
    plots.quality_over_time(frames, shares, np.full(38, 0.9), np.full(38, 0.1))
    fig = drawn[0]
    FigureCanvasAgg(fig).draw()
    for ax in fig.axes:
        boxes = sorted((t.get_window_extent() for t in ax.get_xticklabels()),
                       key=lambda b: b.x0)
        assert len(boxes) >= 38 // 10
        gap_px = 0.05 * fig.dpi  # a visible space between two numbers (0.05 in)
        assert all(b.x0 - a.x1 >= gap_px for a, b in itertools.pairwise(boxes))
