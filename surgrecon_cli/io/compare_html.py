"""`surgrecon compare RUN... --html OUT.html`: the comparison as a self-contained page, with
the runs' per-frame figures (RUN/metrics/frames.csv) overlaid, one line per run.

Figures are drawn with matplotlib's Agg canvas in the report's style (io/plots.py), without
pyplot or global state.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from matplotlib import rc_context
from matplotlib.ticker import MaxNLocator

from . import report_html as rh
from .compare import RunFigures, config_differences, figure_rows, format_value
from .plots import STYLE, new_figure, to_png

# (frames.csv column, title, y label)
PER_FRAME: tuple[tuple[str, str, str], ...] = (
    ("residual_median_mm", "residual to the targets, median", "mm"),
    ("displacement_p95_mm", "displacement from the template, p95", "mm"),
    ("error_median_mm", "registration error against ground truth, median", "mm"),
    ("macro_f1", "label macro F1 against ground truth", "F1"),
    ("unknown_fraction", "points labelled unknown", "fraction"),
    ("sigma_median_mm", "registered position uncertainty σ, median", "mm"),
    ("seconds_register", "registration time", "s"),
)
_PALETTE = ("#4C78A8", "#D1495B", "#59A14F", "#F2A541", "#9C6ADE", "#2CA3A3", "#7F7F7F")


def overlaid(runs: Sequence[RunFigures], column: str, title: str, ylabel: str) -> bytes | None:
    """One line per run of a frames.csv column against the frame (None if no run has it)."""
    series = []
    for run in runs:
        frames = np.array([row["frame"] for row in run.frames if column in row], float)
        values = np.array([row[column] for row in run.frames if column in row], float)
        series.append((run.label, frames, values))
    if not any(len(v) for _, _, v in series):
        return None
    with rc_context(STYLE):
        fig = new_figure(7.5, 2.6)
        ax = fig.add_subplot()
        for i, (label, frames, values) in enumerate(series):
            if len(values):
                ax.plot(frames, values, marker="o", markersize=3, linewidth=1.4,
                        color=_PALETTE[i % len(_PALETTE)], label=label)
        ax.set_xlabel("frame")
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.set_ylabel(ylabel)
        ax.set_title(title, loc="left")
        ax.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0))
        return to_png(fig)


def comparison_html(runs: Sequence[RunFigures]) -> str:
    """The whole page: figures table, differing config keys, overlaid per-frame plots."""
    labels = [run.label for run in runs]
    figures = rh.Section("figures", "Key figures").add(
        rh.paragraph("From each run's metrics/summary.json, metrics/evaluation.json and the "
                     "stage timings in run.json; '-' = the run has no such figure (e.g. not "
                     "evaluated).", note=True),
        rh.table(["", *labels], figure_rows(runs)))
    diffs = config_differences(runs)
    config = rh.Section("config", "Config keys that differ")
    if diffs:
        config.add(rh.table(["key", *labels],
                            [[key, *(format_value(v) for v in values)] for key, values in diffs]))
    else:
        config.add(rh.paragraph("The runs have the same config."))
    plots = rh.Section("frames", "Per frame")
    drawn = [png for column, title, unit in PER_FRAME
             if (png := overlaid(runs, column, title, unit)) is not None]
    if drawn:
        plots.add(*(rh.figure(png) for png in drawn))
    else:
        plots.add(rh.paragraph("No run has metrics/frames.csv (run `surgrecon report`)."))
    paths = rh.Section("runs", "Runs").add(rh.table(["run", "folder"],
                                                    [[r.label, str(r.path)] for r in runs]))
    return rh.render("surgrecon compare", " · ".join(labels), [figures, config, plots, paths],
                     footer="written by surgrecon compare")
