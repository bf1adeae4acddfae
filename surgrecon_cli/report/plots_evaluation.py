"""Evaluation figures (scores against ground truth), in the style of report/plots.py: Agg
canvas, no pyplot, PNG bytes out."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from matplotlib import rc_context
from matplotlib.colors import LinearSegmentedColormap
from matplotlib.ticker import FuncFormatter

from .palette import CLASS_COLOURS
from .plots import STYLE, label_frame_axes, new_figure, to_png


def error_over_time(frames: np.ndarray, median: np.ndarray, p95: np.ndarray, maximum: np.ndarray,
                    limit_mm: float = 1.0) -> bytes:
    """Registration error per frame: median, 95th percentile (band) and max, mm."""
    with rc_context(STYLE):
        fig = new_figure(7.5, 2.8)
        ax = fig.add_subplot()
        ax.fill_between(frames, median, p95, color="#dbe6f1", label="median–p95")
        ax.plot(frames, median, color="#1f3b5a", marker="o", markersize=3, label="median")
        ax.plot(frames, p95, color="#4C78A8", marker="o", markersize=3, label="p95")
        ax.plot(frames, maximum, color="#D1495B", linestyle=":", marker=".", label="max")
        ax.axhline(limit_mm, color="#333333", linestyle="--", linewidth=1,
                   label=f"{limit_mm:g} mm (clinical)")
        ax.set_yscale("log")
        finite = np.concatenate([median, p95, maximum])
        finite = finite[np.isfinite(finite) & (finite > 0)]
        low = max(float(finite.min()) / 1.5, 1e-3) if finite.size else 1e-2
        ax.set_ylim(min(low, limit_mm / 2), max(float(finite.max()) * 1.5 if finite.size else 1,
                                                limit_mm * 2))
        ax.yaxis.set_major_formatter(FuncFormatter(lambda y, _p: f"{y:g}"))
        label_frame_axes(ax, frames, "error (mm, log scale)",
                          "registration error vs. followed material point", legend=True)
        return to_png(fig)


def error_histograms(frames: np.ndarray, errors_mm: Sequence[np.ndarray],
                     limit_mm: float = 1.0) -> bytes:
    """Per-frame registration error distributions as stacked ridge lines (mm)."""
    finite = [np.asarray(e, float)[np.isfinite(e)] for e in errors_mm]
    everything = np.concatenate(finite) if finite else np.zeros(0)
    top = max(float(np.percentile(everything, 99)) if everything.size else 1.0, limit_mm * 1.5)
    edges = np.linspace(0, top, 60)
    centres = (edges[1:] + edges[:-1]) / 2
    cmap = LinearSegmentedColormap.from_list("ridge", ["#9ecae1", "#08306b"])
    with rc_context({**STYLE, "axes.grid": False}):
        fig = new_figure(7.5, min(1.2 + 0.32 * len(frames), 8.0))
        ax = fig.add_subplot()
        for i, e in enumerate(finite):
            if not e.size:
                continue
            h = np.histogram(np.minimum(e, top), bins=edges)[0].astype(float)
            h = h / max(h.max(), 1) * 1.6
            base = -i
            colour = cmap(i / max(len(frames) - 1, 1))
            ax.fill_between(centres, base, base + h, color=colour, alpha=0.75, linewidth=0)
            ax.plot(centres, base + h, color="white", linewidth=0.6)
        ax.axvline(limit_mm, color="#D1495B", linestyle="--", linewidth=1)
        ax.set_yticks([-i for i in range(len(frames))], [str(f) for f in frames], fontsize=7)
        if len(frames) > 25:
            for j, label in enumerate(ax.get_yticklabels()):
                label.set_visible(j % max(len(frames) // 20, 1) == 0)
        ax.set_ylabel("frame")
        ax.set_xlabel(f"registration error (mm; > {top:.1f} in the last bin)")
        ax.set_title("registration error per frame", loc="left")
        ax.spines["left"].set_visible(False)
        return to_png(fig)


def confusion(matrix: np.ndarray, rows: Sequence[str], cols: Sequence[str]) -> bytes:
    """Confusion matrix (rows truth, cols predicted): colour = row-normalised share,
    text = count and share."""
    m = np.asarray(matrix, float)
    share = m / np.maximum(m.sum(1, keepdims=True), 1)
    with rc_context({**STYLE, "axes.grid": False}):
        fig = new_figure(4.6, 3.4)
        ax = fig.add_subplot()
        ax.imshow(share, cmap="Blues", vmin=0, vmax=1)
        for i in range(m.shape[0]):
            for j in range(m.shape[1]):
                ax.text(j, i, f"{int(m[i, j])}\n{share[i, j]:.0%}", ha="center", va="center",
                        fontsize=8, color="white" if share[i, j] > 0.55 else "#222222")
        ax.set_xticks(range(len(cols)), cols, rotation=20)
        ax.set_yticks(range(len(rows)), rows)
        ax.set_xlabel("predicted")
        ax.set_ylabel("truth")
        ax.set_title("labels, frames 1..", loc="left")
        return to_png(fig)


def f1_over_time(frames: np.ndarray, per_class: dict[str, np.ndarray], macro: np.ndarray) -> bytes:
    """Per-class F1 and macro-F1 per frame."""
    with rc_context(STYLE):
        fig = new_figure(7.5, 2.6)
        ax = fig.add_subplot()
        for name, values in per_class.items():
            ax.plot(frames, values, color=CLASS_COLOURS[name], marker="o", markersize=3, label=name)
        ax.plot(frames, macro, color="#222222", linewidth=2, label="macro-F1")
        ax.set_ylim(-0.02, 1.02)
        label_frame_axes(ax, frames, "F1", "label F1 per frame", legend=True)
        return to_png(fig)
