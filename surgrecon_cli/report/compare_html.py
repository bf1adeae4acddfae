"""`surgrecon compare RUN... --html OUT.html`: the comparison as a self-contained page, with
the runs' per-frame figures (RUN/metrics/frames.csv) overlaid, one line per run.

Figures are drawn with matplotlib's Agg canvas in the report's style (report/plots.py), without
pyplot or global state.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from matplotlib import rc_context
from matplotlib.ticker import MaxNLocator

from . import html as rh
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


_LINES = ("-", "--", ":", "-.")
_MARKERS = ("o", "s", "^", "D", "v", "P", "X")


def _series(runs: Sequence[RunFigures], column: str) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(label, frames, values) of a frames.csv column for each run."""
    out = []
    for run in runs:
        frames = np.array([row["frame"] for row in run.frames if column in row], float)
        values = np.array([row[column] for row in run.frames if column in row], float)
        out.append((run.label, frames, values))
    return out


def identical_to(series: list[tuple[str, np.ndarray, np.ndarray]]) -> list[str]:
    """For each series, the label of an earlier one with the same frames and values ("" if
    none): drawn over it, it would hide it."""
    out = []
    for i, (_, frames, values) in enumerate(series):
        twin = next((label for label, f, v in series[:i] if len(values) and f.shape == frames.shape
                     and np.array_equal(f, frames) and np.allclose(v, values, equal_nan=True)),
                    "")
        out.append(twin)
    return out


def overlaid(runs: Sequence[RunFigures], column: str, title: str,
             ylabel: str) -> tuple[bytes, str] | None:
    """One line per run of a frames.csv column against the frame, and a caption naming the
    runs whose lines coincide (None if no run has the column). Each run has its own colour,
    line style and marker, so a line drawn over an identical one leaves both visible."""
    series = _series(runs, column)
    if not any(len(v) for _, _, v in series):
        return None
    twins = identical_to(series)
    caption = "; ".join(f"{label} is identical to {twin} (lines drawn over each other)"
                        for (label, _, _), twin in zip(series, twins, strict=True) if twin)
    with rc_context(STYLE):
        fig = new_figure(7.5, 2.6)
        ax = fig.add_subplot()
        for i, ((label, frames, values), twin) in enumerate(zip(series, twins, strict=True)):
            if len(values):
                ax.plot(frames, values, marker=_MARKERS[i % len(_MARKERS)],
                        markersize=6 if i == 0 else 3.5, linestyle=_LINES[i % len(_LINES)],
                        linewidth=2.4 if i == 0 else 1.4, color=_PALETTE[i % len(_PALETTE)],
                        label=f"{label} (= {twin})" if twin else label, zorder=2 + i)
        ax.set_xlabel("frame")
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.set_ylabel(ylabel)
        ax.set_title(title, loc="left")
        ax.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0))
        return to_png(fig), caption


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
    drawn = [plot for column, title, unit in PER_FRAME
             if (plot := overlaid(runs, column, title, unit)) is not None]
    if drawn:
        plots.add(*(rh.figure(png, caption) for png, caption in drawn))
    else:
        plots.add(rh.paragraph("No run has metrics/frames.csv (run `surgrecon report`)."))
    paths = rh.Section("runs", "Runs").add(rh.table(["run", "folder"],
                                                    [[r.label, str(r.path)] for r in runs]))
    return rh.render("surgrecon compare", " · ".join(labels), [figures, config, plots, paths],
                     footer="written by surgrecon compare")
