"""Report figures, rendered with matplotlib's Agg canvas to PNG bytes.

No pyplot and no global matplotlib state: every figure is a `matplotlib.figure.Figure`
drawn in an `rc_context`, so importing this module (or a report) changes nothing for
other code. Inputs are plain arrays (millimetres where the name says `_mm`, mm² and N
likewise). Sections: the run's figures; contact and indentation (issue 17); scores against
ground truth.
"""

from __future__ import annotations

import io
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
from matplotlib import rc_context
from matplotlib.colors import LinearSegmentedColormap
from matplotlib.figure import Figure
from matplotlib.ticker import FuncFormatter, MaxNLocator

from ..core.classify.labels import CLASS_COLOURS

if TYPE_CHECKING:
    from matplotlib.typing import RcKeyType

STYLE: dict[RcKeyType, Any] = {
    "font.size": 9, "axes.titlesize": 10, "axes.titleweight": "bold", "axes.labelsize": 9,
    "axes.spines.top": False, "axes.spines.right": False, "axes.grid": True,
    "grid.color": "#e6e6e6", "grid.linewidth": 0.6, "axes.edgecolor": "#888888",
    "legend.frameon": False, "legend.fontsize": 8, "figure.facecolor": "white",
    "savefig.facecolor": "white", "xtick.color": "#444444", "ytick.color": "#444444",
}


def to_png(fig: Figure) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    return buf.getvalue()


TICK_DIGIT_IN = 0.09  # width of a tick label's digit at the style's 9 pt (in)
TICK_GAP_IN = 0.2  # least space between two tick labels (in)


def new_figure(width: float, height: float) -> Figure:
    return Figure(figsize=(width, height), layout="constrained")


def stacked_counts(frames: np.ndarray, counts: dict[str, np.ndarray], colours: dict[str, str],
                   title: str, ylabel: str = "points") -> bytes:
    """Stacked areas of per-frame counts {name: (T,)} (e.g. points per class)."""
    with rc_context(STYLE):
        fig = new_figure(7.5, 2.8)
        ax = fig.add_subplot()
        names = [n for n in counts if np.asarray(counts[n]).sum() > 0] or list(counts)
        values = [np.asarray(counts[n], float) for n in names]
        if len(frames) > 1:
            ax.stackplot(frames, values, labels=names, colors=[colours[n] for n in names],
                         alpha=0.9, linewidth=0)
        else:
            bottom: float | np.ndarray = 0.0
            for name, v in zip(names, values, strict=True):
                ax.bar(frames, v, bottom=bottom, color=colours[name], label=name, width=0.6)
                bottom += v
        ax.set_xlim(frames.min() - 0.5 if len(frames) == 1 else frames.min(),
                    frames.max() + 0.5 if len(frames) == 1 else frames.max())
        label_frame_axes(ax, frames, ylabel, title, legend=True)
        return to_png(fig)


def per_frame_boxes(frames: np.ndarray, values: Sequence[np.ndarray], title: str, ylabel: str,
                    lines: dict[str, float] | None = None, log: bool = False) -> bytes:
    """Box plots (whiskers 5–95 %) of one distribution per frame, with labelled horizontal
    reference lines {label: y}."""
    with rc_context(STYLE):
        fig = new_figure(7.5, 2.8)
        ax = fig.add_subplot()
        data = [np.asarray(v, float)[np.isfinite(v)] for v in values]
        keep = [i for i, d in enumerate(data) if d.size]
        if keep:
            ax.boxplot([data[i] for i in keep], positions=np.asarray(frames)[keep], widths=0.6,
                       whis=(5, 95), showfliers=False, patch_artist=True,
                       boxprops={"facecolor": "#dbe6f1", "edgecolor": "#4C78A8"},
                       medianprops={"color": "#1f3b5a", "linewidth": 1.4},
                       whiskerprops={"color": "#4C78A8"}, capprops={"color": "#4C78A8"})
        for i, (label, y) in enumerate((lines or {}).items()):
            ax.axhline(y, color=["#D1495B", "#F2A541", "#59A14F"][i % 3], linestyle="--",
                       linewidth=1, label=label)
        if lines:
            ax.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0))
        if log:
            ax.set_yscale("symlog", linthresh=0.1)
        label_frame_axes(ax, frames, ylabel, title)
        return to_png(fig)


def histogram(values: np.ndarray, title: str, xlabel: str, lines: dict[str, float] | None = None,
              by: dict[str, np.ndarray] | None = None, colours: dict[str, str] | None = None,
              clip: float | None = None) -> bytes:
    """Histogram of finite values (optionally split into overlaid groups {name: mask})."""
    v = np.asarray(values, float)
    finite = np.isfinite(v)
    with rc_context(STYLE):
        fig = new_figure(5.2, 2.8)
        ax = fig.add_subplot()
        top = clip if clip is not None else (np.percentile(v[finite], 99.5) if finite.any() else 1)
        edges = np.linspace(0, max(float(top), 1e-6), 50)
        groups = by or {"all": np.ones(len(v), bool)}
        for name, mask in groups.items():
            sel = v[finite & np.asarray(mask, bool)]
            if sel.size:  # `bins` takes an array; matplotlib's stub omits arrays
                ax.hist(np.minimum(sel, edges[-1]), bins=edges,  # type: ignore[arg-type]
                        histtype="stepfilled", alpha=0.55,
                        color=(colours or {}).get(name, "#4C78A8"), label=f"{name} ({sel.size})")
        for label, x in (lines or {}).items():
            ax.axvline(x, color="#333333", linestyle="--", linewidth=1, label=label)
        ax.set_xlabel(xlabel)
        ax.set_ylabel("points")
        ax.set_title(title, loc="left")
        if by or lines:
            ax.legend()
        return to_png(fig)


def timing(stage_seconds: dict[str, float], frames: np.ndarray,
           per_frame: dict[str, np.ndarray]) -> bytes:
    """Wall time per stage (bars) and per frame (stacked bars of {part: (T,)} seconds)."""
    with rc_context(STYLE):
        fig = new_figure(9.0, 2.8)
        left, right = fig.subplots(1, 2, width_ratios=[1, 1.6])
        names = list(stage_seconds)
        secs = [stage_seconds[n] for n in names]
        left.barh(names[::-1], secs[::-1], color="#4C78A8")
        for y, s in enumerate(secs[::-1]):
            left.text(s, y, f" {s:.1f} s", va="center", fontsize=8)
        left.set_xlabel("seconds")
        left.set_title("wall time per stage", loc="left")
        left.grid(axis="y", visible=False)
        left.set_xlim(0, max([*secs, 1e-3]) * 1.3)
        bottom = np.zeros(len(frames))
        palette = ["#59A14F", "#4C78A8", "#F2A541", "#D1495B"]
        for i, (name, values) in enumerate(per_frame.items()):
            v = np.nan_to_num(np.asarray(values, float))
            right.bar(frames, v, bottom=bottom, color=palette[i % 4], label=name, width=0.7)
            bottom += v
        right.set_xlabel("frame")
        right.set_ylabel("seconds")
        right.set_title("registration time per frame", loc="left")
        if per_frame:
            right.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0))
        thin_ticks(right, frames)
        return to_png(fig)


def camera_layout(points: np.ndarray, centres: np.ndarray, axes: np.ndarray,
                  names: Sequence[str], groups: Sequence[Sequence[str]],
                  sequences: Sequence[Sequence[Sequence[str]]]) -> bytes:
    """Top view (x-y, mm) of the template, the cameras (centres (C, 3) m, viewing
    directions (C, 3)) and the pair sequence of each camera group (edges numbered in
    matching order)."""
    with rc_context(STYLE):
        fig = new_figure(5.5, 4.6)
        ax = fig.add_subplot()
        if len(points):
            ax.scatter(points[:, 0] * 1e3, points[:, 1] * 1e3, s=1.5, color="#c9c9c9",
                       rasterized=True, label="template")
        index = {n: i for i, n in enumerate(names)}
        palette = ["#4C78A8", "#D1495B", "#59A14F", "#F2A541", "#8E6C8A"]
        for g, (group, seq) in enumerate(zip(groups, sequences, strict=False)):
            colour = palette[g % len(palette)]
            for order, (a, b) in enumerate(seq):
                if a not in index or b not in index:
                    continue
                pa, pb = centres[index[a]] * 1e3, centres[index[b]] * 1e3
                ax.plot([pa[0], pb[0]], [pa[1], pb[1]], color=colour, linewidth=1.2, alpha=0.7)
                mid = (pa + pb) / 2
                ax.text(mid[0], mid[1], str(order + 1), fontsize=7, color=colour, ha="center",
                        va="center", bbox={"boxstyle": "circle,pad=0.15", "fc": "white",
                                           "ec": colour, "lw": 0.6})
            for cam in group:
                if cam in index:
                    c = centres[index[cam]] * 1e3
                    ax.scatter([c[0]], [c[1]], s=60, color=colour, zorder=3, edgecolor="white")
        finite = np.isfinite(centres).all(axis=1)
        middle = float(np.mean(centres[finite, 0])) * 1e3 if finite.any() else 0.0
        for i, name in enumerate(names):
            c, d = centres[i] * 1e3, axes[i]
            if not finite[i]:
                continue
            ax.annotate("", xy=(c[0] + 12 * d[0], c[1] + 12 * d[1]), xytext=(c[0], c[1]),
                        arrowprops={"arrowstyle": "->", "color": "#555555", "lw": 0.8})
            # each name on the side away from the cameras' middle: a stereo pair's two
            # names (centres a few mm apart) do not print over each other
            side = 1 if c[0] >= middle else -1
            ax.annotate(name, xy=(c[0], c[1]), xytext=(6 * side, 3), textcoords="offset points",
                        fontsize=9, fontweight="bold", va="bottom",
                        ha="left" if side > 0 else "right")
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("y (mm)")
        ax.set_title("cameras at frame 0 and pair sequence (top view)", loc="left")
        return to_png(fig)


def labelled_views(title: str, image: np.ndarray | None, uv: np.ndarray | None,
                   xyz: np.ndarray, labels: np.ndarray, class_names: dict[int, str]) -> bytes:
    """One frame's labelled cloud: projected into a camera image (uv (N, 2) px, NaN = not
    visible) and as a 3D view of xyz (N, 3) m, coloured by class."""
    colours = np.array([CLASS_COLOURS.get(class_names.get(int(c), "unknown"), "#BAB0AC")
                        for c in labels]) if len(labels) else np.zeros(0, str)
    with rc_context({**STYLE, "axes.grid": False}):
        fig = new_figure(10.5, 4.2)
        if image is not None and uv is not None:
            ax_img = fig.add_subplot(1, 2, 1)
            ax_img.imshow(image, interpolation="bilinear")
            ok = np.isfinite(uv).all(1)
            order = np.argsort(labels[ok], kind="stable")  # moving points drawn on top
            ax_img.scatter(uv[ok][order, 0], uv[ok][order, 1], s=5, c=colours[ok][order],
                           linewidths=0.2, edgecolors="white", alpha=0.95)
            ax_img.set_axis_off()
            ax3 = fig.add_subplot(1, 2, 2, projection="3d")
        else:
            ax3 = fig.add_subplot(1, 1, 1, projection="3d")
        ok = np.isfinite(xyz).all(1)
        p = xyz[ok] * 1e3
        if len(p):
            order = np.argsort(labels[ok], kind="stable")
            ax3.scatter(p[order, 0], p[order, 1], p[order, 2], s=2.5, c=colours[ok][order],
                        linewidths=0, depthshade=False)
            lo, hi = np.percentile(p, 1, axis=0), np.percentile(p, 99, axis=0)
            span = (hi - lo)[:2].max() / 2 * 1.05
            mid = (hi + lo) / 2
            ax3.set_xlim(mid[0] - span, mid[0] + span)
            ax3.set_ylim(mid[1] - span, mid[1] + span)
            zspan = max((hi - lo)[2] / 2 * 1.3, span / 6)
            ax3.set_zlim(mid[2] - zspan, mid[2] + zspan)
            ax3.set_box_aspect((1, 1, zspan / span), zoom=1.15)
        ax3.view_init(elev=50, azim=-70)
        ax3.set_xlabel("x (mm)", labelpad=-4)
        ax3.set_ylabel("y (mm)", labelpad=-4)
        ax3.set_zlabel("z (mm)", labelpad=-6)
        ax3.tick_params(labelsize=6, pad=-2)
        ax3.zaxis.set_major_locator(MaxNLocator(3))
        handles = [ax3.scatter([], [], color=CLASS_COLOURS[n], label=n, s=20)
                   for n in ("static", "shifting", "deforming", "unknown")]
        ax3.legend(handles=handles, loc="upper right", bbox_to_anchor=(1.05, 1.0))
        fig.suptitle(title, x=0.01, ha="left", fontsize=10, fontweight="bold")
        return to_png(fig)


def label_frame_axes(ax, frames: np.ndarray, ylabel: str, title: str,
                      legend: bool = False) -> None:
    """Frame on x, `ylabel` on y, a left title, the legend outside on the right."""
    ax.set_xlabel("frame")
    ax.set_ylabel(ylabel)
    ax.set_title(title, loc="left")
    if legend:
        ax.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0))
    thin_ticks(ax, frames)


def thin_ticks(ax, frames: np.ndarray) -> None:
    """x ticks at frames (T,), labelled by frame number (a box plot's own labels count its
    boxes, not the frames), as many as the axes' width holds side by side: at the
    multiples of a round step (1, 2, 5, 10, 20, ...) where the frames have two or more,
    else every k-th frame."""
    frames = np.asarray(frames)
    if len(frames) == 0:
        return
    width_in = ax.get_position().width * ax.figure.get_figwidth()
    digits = max(len(f"{t:g}") for t in frames)
    fit = max(int(width_in / (TICK_DIGIT_IN * digits + TICK_GAP_IN)), 2)
    span = float(frames.max() - frames.min()) + 1.0
    step = next(s for s in (m * 10**e for e in range(12) for m in (1, 2, 5)) if span / s <= fit)
    ticks = frames[np.isclose(np.mod(frames, step), 0)]
    if len(ticks) < 2:
        ticks = frames[::max(int(np.ceil(len(frames) / fit)), 1)]
    ax.set_xticks(ticks, labels=[f"{t:g}" for t in ticks])


def quality_over_time(frames: np.ndarray, fractions: dict[str, np.ndarray],
                      sigma_mm: np.ndarray, residual_ratio: np.ndarray) -> bytes:
    """Quality panel: shares of points per frame (left) and median σ / residual ratio
    (right)."""
    fig = new_figure(9.0, 3.5)
    left, right = fig.subplots(1, 2)
    for name, values in fractions.items():
        left.plot(frames, values * 100, marker="o", ms=3, label=name)
    left.set_ylim(0, 100)
    label_frame_axes(left, frames, "% of template points", "what the data support")
    right.plot(frames, sigma_mm, marker="o", ms=3, color="tab:blue", label="median σ (mm)")
    right.plot(frames, residual_ratio, marker="s", ms=3, color="tab:red",
               label="residual / σ_target")
    right.axhline(1.0, color="grey", lw=0.8, ls=":")
    label_frame_axes(right, frames, "mm  /  ratio", "uncertainty and fit")
    for ax in (left, right):  # below the axes, in one row: never over a curve
        ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.2),
                  ncol=len(ax.get_legend_handles_labels()[1]))
    return to_png(fig)


# -- contact and indentation (issue 17) --------------------------------------------------------
CONTACT_SHADE = "#f6e3e5"


def _shade_contact(ax, frames: np.ndarray, contact: np.ndarray) -> None:
    """Shade the frames in contact (half a frame either side)."""
    for k, on in zip(frames, contact, strict=True):
        if on:
            ax.axvspan(k - 0.5, k + 0.5, color=CONTACT_SHADE, linewidth=0, zorder=0)


def deformation_over_time(frames: np.ndarray, contact: np.ndarray, depth_mm: np.ndarray,
                          depth_sigma_mm: np.ndarray, penetration_mm: np.ndarray,
                          area_mm2: np.ndarray, force_n: np.ndarray | None = None,
                          force_label: str = "", true_depth_mm: np.ndarray | None = None,
                          true_area_mm2: np.ndarray | None = None) -> bytes:
    """Per frame (T,): the depth under the tool tip along its axis (measured from the
    reconstruction, ±2σ band) beside the tool's kinematic penetration below the frame-0
    surface, the deformed area, and (when given) the force proxy; frames in contact shaded,
    the simulator's truth as black markers when given."""
    frames = np.asarray(frames)
    panels = 3 if force_n is not None else 2
    with rc_context(STYLE):
        # fixed margins, not the constrained layout: it draws every figure twice
        fig = Figure(figsize=(4.2 * panels + 1.0, 3.4))
        fig.subplots_adjust(left=0.07 if panels == 2 else 0.05, right=0.98, bottom=0.27,
                            top=0.92, wspace=0.25)
        axes = fig.subplots(1, panels)
        ax = axes[0]
        _shade_contact(ax, frames, contact)
        lo, hi = depth_mm - 2 * depth_sigma_mm, depth_mm + 2 * depth_sigma_mm
        ax.fill_between(frames, lo, hi, color="#dbe6f1", label="±2σ", linewidth=0)
        ax.plot(frames, depth_mm, color="#1f3b5a", marker="o", ms=3, label="measured")
        ax.plot(frames, penetration_mm, color="#D1495B", linestyle="--", marker=".",
                label="tip below frame-0 surface (kinematics)")
        if true_depth_mm is not None:
            ax.plot(frames, true_depth_mm, "kx", ms=5, label="truth")
        top = np.nanmax(np.concatenate([depth_mm, hi, [1.0]]))
        ax.set_ylim(min(-1.0, float(np.nanmin(np.concatenate([depth_mm, [0.0]])) - 0.5)),
                    float(top) * 1.15 + 0.2)
        label_frame_axes(ax, frames, "mm along the tool axis", "indentation at the tool tip")
        ax.legend(loc="upper left", bbox_to_anchor=(-0.02, -0.17), ncol=2, fontsize=7)
        ax = axes[1]
        _shade_contact(ax, frames, contact)
        ax.plot(frames, area_mm2, color="#59A14F", marker="o", ms=3, label="measured")
        if true_area_mm2 is not None:
            ax.plot(frames, true_area_mm2, "kx", ms=5, label="truth")
        ax.set_ylim(bottom=0)
        label_frame_axes(ax, frames, "mm²", "deformed area")
        ax.legend(loc="upper left", bbox_to_anchor=(-0.02, -0.17), ncol=2, fontsize=7)
        if force_n is not None:
            ax = axes[2]
            _shade_contact(ax, frames, contact)
            ax.plot(frames, force_n, color="#8E6C8A", marker="o", ms=3)
            ax.set_ylim(bottom=0)
            label_frame_axes(ax, frames, "N (model output)", "force proxy")
            ax.text(0.02, 0.97, force_label, transform=ax.transAxes, fontsize=7, va="top")
        step = max(int(np.ceil(len(frames) / 10)), 1)  # narrow panels: at most ~10 ticks
        for ax in axes:
            ax.set_xticks(frames[::step])
        return to_png(fig)


def displacement_map(xy_mm: np.ndarray, inward_mm: np.ndarray, deformed: np.ndarray,
                     tip_mm: np.ndarray | None, axis: np.ndarray | None, title: str) -> bytes:
    """Top view (x-y, mm) of the template points coloured by their compensated
    displacement into the tissue (mm), the deformed region ringed, the tool tip and the
    direction of its shaft drawn (grey: the top view of 40 mm of it)."""
    xy = np.asarray(xy_mm, float)
    value = np.asarray(inward_mm, float)
    ok = np.isfinite(value) & np.isfinite(xy).all(1)
    with rc_context({**STYLE, "axes.grid": False}):
        fig = Figure(figsize=(6.2, 4.8))
        fig.subplots_adjust(left=0.12, right=0.97, bottom=0.1, top=0.93)
        ax = fig.add_subplot()
        if ok.any():
            top = max(float(np.nanpercentile(np.abs(value[ok]), 99.5)), 0.5)
            order = np.argsort(value[ok])  # deepest on top
            art = ax.scatter(xy[ok][order, 0], xy[ok][order, 1], c=value[ok][order], s=7,
                             cmap="RdBu_r", vmin=-top, vmax=top, linewidths=0, rasterized=True)
            fig.colorbar(art, ax=ax, label="into the tissue along the normal (mm)", shrink=0.85)
        ring = ok & np.asarray(deformed, bool)
        if ring.any():
            ax.scatter(xy[ring, 0], xy[ring, 1], s=16, facecolors="none", edgecolors="#222222",
                       linewidths=0.4, label="deformed region")
        if tip_mm is not None and np.isfinite(tip_mm).all():
            ax.scatter([tip_mm[0]], [tip_mm[1]], marker="*", s=120, color="#F2A541",
                       edgecolor="black", zorder=5, label="tool tip")
            if axis is not None and np.isfinite(axis).all():
                ax.plot([tip_mm[0], tip_mm[0] + 40 * axis[0]],
                        [tip_mm[1], tip_mm[1] + 40 * axis[1]], color="#555555", lw=3,
                        alpha=0.8, solid_capstyle="round", zorder=4, label="tool shaft")
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("y (mm)")
        ax.set_title(title, loc="left")
        if ring.any() or tip_mm is not None:
            ax.legend(loc="lower left", fontsize=7)
        return to_png(fig)


# -- scores against ground truth ---------------------------------------------------------------
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
