"""Report layer 4: the HTML page, composed last from the run data, its metrics and the
figures already drawn (report/figures.py); report/html.py has the blocks. Pure.

A figure is placed by its name with its caption when it was drawn; a section left with
nothing to show is left out. Sections in the order of the page; tool-tissue contact and
indentation in report/contact_page.py.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np

from .. import __version__
from ..config import Config
from ..core.classify.quality import (
    MAX_RESIDUAL_RATIO,
    MAX_UNKNOWN,
    MIN_OBSERVED,
    pooled_within_2sigma,
    verdict,
)
from ..errors import counted
from ..io.run.layout import DESCRIBED_FILES, RunLayout
from . import html as rh
from .contact_page import contact_section
from .figures import cloud_key
from .frames import FrameFigures
from .gather import CloudView, RunData
from .metrics import TIMED_STAGES, Metrics, calibration_tile, floor_words, stage_seconds

Figures = Mapping[str, bytes]


def compose(layout: RunLayout, data: RunData, metrics: Metrics, views: list[CloudView],
            config: Config, pngs: Figures, created: datetime) -> str:
    """The report's HTML document; `created` (UTC) dates the footer."""
    log = data.log
    sections = [_overview(data, metrics), _cameras(data, pngs)]
    if data.frames is not None and metrics.noise is not None and log.n_frames > 1:
        sections.append(_quality(data, data.frames, metrics, pngs))
    sections += [_labels(config, metrics, pngs), _clouds(views, pngs), _registration(pngs),
                 contact_section(data, config, pngs), _timing(data.run, pngs)]
    if data.evaluation:
        sections.append(_evaluation(data.evaluation, pngs))
    sections.append(rh.Section("files", "Files").add(rh.table(("file", "contents"), [
        (rh.Link(layout.relative(path), layout.relative(path)), what) for path, what in
        ((getattr(layout, name), what) for name, what in DESCRIBED_FILES) if path.exists()])))
    subtitle = (f"{Path(str(data.run.get('input', {}).get('path', ''))).name} · "
                f"{counted(log.n_frames, 'frame')} · {counted(len(log.cameras), 'camera')} · "
                f"{layout.root.name}")
    return rh.render("surgrecon run report", subtitle, [s for s in sections if s.blocks],
                     footer=f"surgrecon {__version__} · generated "
                            f"{created.strftime('%Y-%m-%d %H:%M UTC')} · Su, Huang & "
                            "Hannaford, IROS 2019", caveats=metrics.caveats)


def _overview(data: RunData, metrics: Metrics) -> rh.Section:
    """Headline tiles, the input and the stages."""
    log, summary, rows = data.log, metrics.summary, metrics.rows
    items = [("frames", str(log.n_frames), ""), ("cameras", str(len(log.cameras)), "")]
    if data.template is not None:
        items.append(("template points", f"{len(data.template):,}", ""))
    fractions = summary.get("classes_frames_1_on", {}).get("fractions")
    if fractions:
        items.append(("moving (frames 1..)",
                      f"{fractions['shifting'] + fractions['deforming']:.1%}", ""))
    ev = summary.get("evaluation")
    if ev and ev.get("registration_error_mm"):
        med = ev["registration_error_mm"]["median_mm"]
        items.append(("median registration error", _fmt_mm(med),
                      "good" if med is not None and med <= 1.0 else "bad"))
    if ev and ev.get("macro_f1") is not None:
        items.append(("label macro-F1", f"{ev['macro_f1']:.3f}", ""))
    tile = calibration_tile((data.evaluation or {}).get("labels") or {})
    if tile is not None:
        items.append(tile)
    inp = data.run.get("input", {})
    seconds = stage_seconds(data.run)
    stage_rows = [(name, "reused" if entry.get("reused_from") else entry.get("status"),
                   seconds.get(name))
                  for name, entry in data.run.get("stages", {}).items() if name in TIMED_STAGES]
    return rh.Section("overview", "Overview").add(
        rh.tiles(items),
        rh.table(("input", ""), [
            ("log", inp.get("path")), ("SHA-256", (inp.get("sha256") or "")[:16] + "…"),
            ("size", f"{(inp.get('bytes') or 0) / 1e6:.1f} MB"),
            ("duration", f"{rows[-1]['time_s']:.2f} s" if rows else "–"),
            ("surgrecon", __version__)]),
        rh.table(("stage", "status", "seconds"), stage_rows))


_NUMBER = re.compile(r"\d+(?:\.\d+)?")


def grouped_warnings(warnings: list[tuple[int, str]]) -> list[str]:
    """Per-frame warnings ("frame k: text", in frame order) with each run of consecutive
    frames that say the same thing (its numbers aside) merged into one: "frames a–b: text",
    each number that varies over the run given as its range. A long clip whose template
    leaves the view says so in a few lines instead of two sentences a frame."""
    runs: list[tuple[list[int], list[str]]] = []  # (frames, texts) per run, in order
    latest: dict[str, tuple[list[int], list[str]]] = {}  # kind -> its latest run
    for frame, text in warnings:
        body = text.split(": ", 1)[1] if text.startswith(f"frame {frame}: ") else text
        kind = _NUMBER.sub("#", body)
        run = latest.get(kind)
        if run is not None and run[0][-1] == frame - 1:
            run[0].append(frame)
            run[1].append(body)
        else:
            latest[kind] = ([frame], [body])
            runs.append(latest[kind])
    out = []
    for frames, texts in sorted(runs, key=lambda r: r[0][0]):
        if len(frames) == 1:
            out.append(f"frame {frames[0]}: {texts[0]}")
            continue
        out.append(f"frames {frames[0]}–{frames[-1]}: {_merged(texts)}")
    return out


def _merged(texts: list[str]) -> str:
    """Texts that differ only in their numbers (as many in each) as one: the first, with
    each number that varies replaced by its range ("31–97%")."""
    values = np.array([[float(v) for v in _NUMBER.findall(t)] for t in texts])
    spans = iter(zip(values.min(0), values.max(0), strict=True))

    def span(match: re.Match[str]) -> str:
        lo, hi = next(spans)
        return match.group() if lo == hi else f"{lo:g}–{hi:g}"

    return _NUMBER.sub(span, texts[0])


def _tracker_rate(hz: Any) -> Any:
    """A camera's pose rate for the table: "fixed" for a pose given once (a rig fixed in the
    world, a static transform), which reads 0 Hz, as if the tracker had stopped."""
    return "fixed" if hz == 0 else hz


def _cameras(data: RunData, pngs: Figures) -> rh.Section:
    """The camera layout over the template, the pair plan, per-camera ingest counts and the
    template's counts."""
    log = data.log
    sec = rh.Section("cameras", "Cameras and template")
    sec.add(*_place(pngs, "camera-layout",
                    "Camera positions at frame 0 over the template (grey). Lines: pairs matched "
                    "when building the template, numbered in matching order; one colour per "
                    "camera group."))
    pairs = (data.template_summary or {}).get("pairs", {})
    groups, sequences = pairs.get("groups", []), pairs.get("sequence", [])
    for g, group in enumerate(groups):
        seq = sequences[g] if g < len(sequences) else []
        sec.add(rh.paragraph(f"Group {g + 1}: cameras {', '.join(group)}; pair sequence "
                             + (" → ".join(f"{a}-{b}" for a, b in seq) or "none")))
    cam_report = log.report.get("cameras", {})
    if cam_report:
        sec.add(rh.table(("camera", "images", "frames", "dropped", "late", "pose gaps", "usable",
                          "image Hz", "tracker Hz"),
                         [(cid, r.get("images"), r.get("frames"), r.get("dropped"), r.get("late"),
                           r.get("pose_gaps"), r.get("usable"), r.get("image_rate_hz"),
                           _tracker_rate(r.get("tracker_rate_hz")))
                          for cid, r in cam_report.items()]))
    stats = (data.template_summary or {}).get("stats", {})
    if stats:
        sec.add(rh.paragraph(
            f"Template: {stats.get('points')} points from {stats.get('tracks')} feature tracks; "
            f"{stats.get('verified_pairs')} of {stats.get('candidate_pairs')} candidate pairs "
            f"verified; {stats.get('rejected_geometry')} rejected by reprojection/angle, "
            f"{stats.get('removed_off_surface')} off the surface, {stats.get('removed_tool')} "
            f"on the tool.", note=True))
        for line in stats.get("warnings") or []:  # cameras not linked, groups that disagree
            sec.add(rh.paragraph(f"{line[:1].upper()}{line[1:]}.", note=True))
    if not log.report.get("robot", True):
        sec.add(rh.paragraph(
            "No robot kinematics in this log (topics.tool_pose = \"\"): tool removal is off, "
            "so points on the tool are kept and may be labelled as tissue.", note=True))
    return sec


def _quality(data: RunData, frames: FrameFigures, metrics: Metrics,
             pngs: Figures) -> rh.Section:
    """Per frame: what the data support (shares observed / unknown), the median σ and the
    residual against the noise, with the frames not to trust named in plain words, and the
    run's verdict (measured calibration with ground truth, else the residuals against σ)."""
    noise = metrics.noise or {}
    jitter = [v for v in (noise.get("tracker_jitter_mm") or {}).values() if v is not None]
    jitter_deg = [v for v in (noise.get("tracker_jitter_deg") or {}).values() if v is not None]
    bodies = data.log.report.get("tracker_bodies", [])
    sec = rh.Section("quality", "Quality (no ground truth needed)")
    sec.add(rh.table(("measured noise (1σ per axis)", "value"), [
        ("pixel noise at frame 0 (template residuals per degree of freedom)",
         rh.number(noise.get("pixel_px"), "px")),
        ("of which localisation (each camera's median residual taken out)",
         rh.number(noise.get("localisation_px"), "px")),
        ("largest systematic offset of a camera's views (the median residual: a calibration "
         "error, or the frame-0 pose error of a camera on its own tracker)",
         _largest_offset(noise.get("calibration_offset_px") or {})),
        ("tracker position jitter (median over cameras)",
         rh.number(float(np.median(jitter)) if jitter else None, "mm")),
        ("tracker rotation jitter (median over cameras)",
         rh.number(float(np.median(jitter_deg)) if jitter_deg else None, "°")),
        ("tracking noise (each tracked patch's Cramér-Rao bound plus what the frame's "
         "re-triangulated residuals show beyond the model; median over frames)",
         rh.number(noise.get("tracking_px"), "px")),
        ("cameras sharing one tracked body (pose error rigid for the group)",
         "; ".join(", ".join(g) for g in bodies) or "none"),
    ]))
    sec.add(*_place(pngs, "quality",
                    "Left: share of template points observed in the frame, labelled unknown "
                    "(σ above classify.max_sigma_mm and no motion beyond it: far from data, or "
                    "measured too loosely) "
                    "and rejected as outliers. Right: median uncertainty σ "
                    "of the labelled points, and the median registration residual in units of "
                    "the target's σ (about 1 when the fit is as good as the noise allows)."))
    warnings = grouped_warnings([(q.frame, w) for q in frames.quality for w in q.warnings])
    if warnings:
        sec.add(rh.paragraph("Frames not to trust: " + "; ".join(warnings) + "."))
    else:
        sec.add(rh.paragraph(
            f"No frame is flagged: each has at least {MIN_OBSERVED:.0%} of the template "
            f"observed, at most {MAX_UNKNOWN:.0%} of its points unknown, a median residual "
            f"under {MAX_RESIDUAL_RATIO:g}σ and a converged solve.", note=True))
    if metrics.verdict is not None:
        v = metrics.verdict
        basis = ("Against ground truth" if v.basis == "ground truth"
                 else "Without ground truth")
        sec.add(rh.paragraph(f"{basis}: {v.text[0].lower()}{v.text[1:]}", note=v.fits))
        if v.basis == "ground truth":  # what the residuals alone would have said
            residuals = verdict(*pooled_within_2sigma(frames.quality))
            sec.add(rh.paragraph(f"Residuals alone: {residuals.text}", note=True))
    return sec


def _labels(config: Config, metrics: Metrics, pngs: Figures) -> rh.Section:
    """Points per class and per reprojection status over time."""
    c = config.classify
    sensitivity = floor_words(metrics.summary["classify"].get("deform_floor_mm"), c.deform_mm)
    return rh.Section("labels", "Labels over time").add(
        *_place(pngs, "class-counts",
                f"Static: registered displacement below {c.static_mm:g} mm; deforming: "
                f"neighbourhood ({c.neighbourhood_mm:g} mm) {c.measure} at or above "
                f"{c.deform_mm:g} mm; shifting otherwise. {sensitivity}"),
        *_place(pngs, "deform-floor", "Each labelled point's deformation floor per frame "
                "(boxes: quartiles, whiskers: 5–95 %)."),
        *_place(pngs, "status-counts",
                "Intra-camera inliers (frame-0 position still reprojects: static evidence), "
                "inter-camera inliers (re-triangulated: dynamic), outliers, and points not "
                "visible."))


def _clouds(views: list[CloudView], pngs: Figures) -> rh.Section:
    """The rendered frames, in frame order."""
    return rh.Section("clouds", "Labelled clouds").add(
        *(block for v in views for block in _place(pngs, cloud_key(v.frame), _cloud_caption(v))))


def _registration(pngs: Figures) -> rh.Section:
    """Displacement and residual distributions per frame."""
    return rh.Section("registration", "Registration").add(
        *_place(pngs, "displacement",
                "Registered displacement ‖T_i p_i − p_i‖ per frame (boxes: quartiles, "
                "whiskers: 5–95 %)."),
        *_place(pngs, "residual",
                "Distance of each point with a target (intra/inter-camera inlier) to its "
                "target after registration."))


def _timing(run: dict[str, Any], pngs: Figures) -> rh.Section:
    """Wall time per stage and per frame (run: run.json)."""
    early = run.get("stages", {}).get("classify", {}).get("classified_with_register")
    note = (f" {early} frames were classified as they were registered: their time counts "
            "under register." if early else "")
    return rh.Section("timing", "Timing").add(*_place(
        pngs, "timing", "Wall time of each stage (left) and of target-cloud building and "
                        "non-rigid registration per frame (right)." + note))


def _cloud_caption(view: CloudView) -> str:
    if view.image is None:
        return f"Frame {view.frame}: registered cloud."
    return (f"Frame {view.frame}: registered cloud coloured by class, projected into camera "
            f"{view.camera}'s image (left; points behind the tool hidden) and in 3D (right).")


def _largest_offset(offsets: dict[str, list[float | None]]) -> str:
    """'0.18 px (right)': the longest of the cameras' median residual vectors px, or '–'."""
    lengths = {c: float(np.hypot(float(v[0]), float(v[1]))) for c, v in offsets.items()
               if len(v) == 2 and v[0] is not None and v[1] is not None}
    if not lengths:
        return "–"
    camera = max(lengths, key=lengths.__getitem__)
    return f"{rh.number(lengths[camera], 'px')} ({camera})"


def _evaluation(ev: dict[str, Any], pngs: Figures) -> rh.Section:
    """Scores against ground truth: template, registration and label errors."""
    sec = rh.Section("evaluation", "Evaluation against ground truth")
    tpl = ev["template"]
    items = [("template error (median)", _fmt_mm(tpl["error"].get("median_mm")), ""),
             ("template error (p95)", _fmt_mm(tpl["error"].get("p95_mm")), "")]
    if tpl.get("on_tool") is not None:
        items.append(("template points on the tool", str(tpl["on_tool"]["count"]),
                      "good" if tpl["on_tool"]["count"] == 0 else "bad"))
    reg = ev.get("registration")
    if reg:
        o = reg["overall"]
        items.append(("registration error (p95)", _fmt_mm(o.get("p95_mm")), ""))
        if o.get("within_1mm") is not None:
            items.append(("within 1 mm", f"{o['within_1mm']:.1%}",
                          "good" if o["within_1mm"] >= 0.95 else "bad"))
    sec.add(rh.tiles(items))
    sec.add(rh.paragraph(
        "Each template point is mapped to the nearest point of the true surface at frame 0 and "
        "that material point is followed through the frames; its true label is that of the "
        "nearest true vertex.", note=True))
    sec.add(*_place(pngs, "template-error",
                    "Distance of every template point to the true frame-0 surface."))
    if reg and reg["per_frame"]:
        sec.add(*_place(pngs, "error-over-time",
                        "Registration error: registered position vs. the followed material "
                        "point, all template points."))
        sec.add(*_place(pngs, "error-histograms",
                        "Distribution of the registration error in each frame (dashed: 1 mm)."))
        sec.add(rh.table(("frame", "median mm", "p95 mm", "max mm", "within 1 mm"),
                         [(r["frame"], r.get("median_mm"), r.get("p95_mm"), r.get("max_mm"),
                           None if r.get("within_1mm") is None else f"{r['within_1mm']:.1%}")
                          for r in reg["per_frame"]]))
    labels = ev.get("labels")
    if labels and labels.get("overall"):
        o = labels["overall"]
        score_rows = [(name, s["precision"], s["recall"], s["f1"], s["support"])
                      for name, s in o["per_class"].items()]
        score_rows.append(("macro-F1", None, None, o["macro_f1"], None))
        sec.add(rh.grid(*_place(pngs, "confusion",
                                "Rows: truth; columns: predicted (unknown = no label)."),
                        rh.table(("class", "precision", "recall", "F1", "support"), score_rows)))
        sec.add(*_place(pngs, "f1-over-time",
                        "F1 per class and frame (gaps: the class is absent in that frame's "
                        "truth)."))
    return sec


def _place(pngs: Figures, name: str, caption: str) -> list[str]:
    """Figure `name` with its caption, if it was drawn (else nothing)."""
    return [rh.figure(pngs[name], caption)] if name in pngs else []


def _fmt_mm(value: Any) -> str:
    return "–" if value is None else f"{value:.2f} mm"
