"""Contact and indentation figures (issue 17), in the style of report/plots.py: Agg canvas, no
pyplot, PNG bytes out. Inputs in mm, mm² and N as the names say."""

from __future__ import annotations

import numpy as np
from matplotlib import rc_context
from matplotlib.figure import Figure

from .plots import STYLE, label_frame_axes, to_png

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
