"""Report layer 4: the page's section on tool-tissue contact and indentation (the measure
stage's series and summary, the figures already drawn, the scores against the simulator's
truth). Pure."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from ..config import Config
from ..core.measure.indentation import NOT_MEASURED, tool_known
from . import html as rh
from .gather import RunData


def contact_section(data: RunData, config: Config, pngs: Mapping[str, bytes]) -> rh.Section:
    """Tiles, the two figures, the definitions, the per-frame table and the scores."""
    sec = rh.Section("contact", "Tool–tissue contact and indentation")
    if data.deformation is None:
        return sec
    series, summary = data.deformation, data.deformation_summary or {}
    d = config.deformation
    known = tool_known(data.log.tool_poses)
    onset, release = summary.get("onset_frame"), summary.get("release_frame")
    items = [("contact", NOT_MEASURED if not known.any() else "none" if onset is None else
              f"frames {onset}–{release - 1 if release is not None else series.n_frames - 1}",
              ""),
             ("deepest indentation", _mm(summary.get("max_indentation_mm"),
                                         summary.get("max_indentation_sigma_mm")), ""),
             ("largest deformed area", rh.number(summary.get("max_area_mm2"), "mm²"), ""),
             ("largest indented volume", rh.number(summary.get("max_volume_mm3"), "mm³"), "")]
    if d.youngs_modulus_kpa > 0:
        items.append(("force proxy (model)", rh.number(summary.get("max_force_n"), "N"), ""))
    if not known.any():
        items = [(name, NOT_MEASURED, "") for name, _value, _mood in items]
    sec.add(rh.tiles(items))
    if not known.all():
        sec.add(rh.paragraph(
            f"Contact is not measured in {int((~known).sum())} of {len(known)} frames: the "
            "tool pose is unknown there (no robot kinematics in the log, or a gap in its "
            "stream). That is not the same as no contact.", note=bool(known.any())))
    if "deformation-over-time" in pngs:
        sec.add(rh.figure(pngs["deformation-over-time"],
                          "Left: depth of the tissue under the tool tip along the tool axis, "
                          "measured as the displacement left after removing the rigid motion "
                          "of the ring around each point (so breathing does not count), ±2σ; "
                          "beside it how far the tip is below the frame-0 surface by the "
                          "robot's kinematics. Right: area of the deformed region. Shaded: "
                          "frames in contact." + (" Crosses: simulator truth."
                                                  if data.evaluation else "")))
    if "deformation-map" in pngs:
        sec.add(rh.figure(pngs["deformation-map"],
                          f"Frame {summary.get('deepest_frame')}, the deepest indentation: "
                          "each template point at its frame-0 position (top view) coloured "
                          "by its compensated displacement into the tissue; ringed: the "
                          f"deformed region (at least {d.threshold_mm:g} mm, connected to "
                          "the contact point); the star: the tool tip, grey: its shaft. "
                          "Breathing that moves a region rigidly leaves no colour; where "
                          "its edge shears the tissue (no rigid motion fits there), it "
                          "shows."))
    sec.add(rh.paragraph(
        f"Contact: the tool (a capsule of the shaft radius) comes within the tolerance of the "
        f"registered surface: {d.contact_sigmas:g}σ of the frame's points (the median), at least "
        f"{d.contact_floor_mm:g} mm; once in contact, a release needs the clearance beyond "
        f"{d.contact_sigmas:g}σ of that point extrapolated as far as the nearest point is from "
        "the data (the tissue under the tool is hidden). "
        f"Ring: template points {d.ring_inner_mm:g}–"
        f"{d.ring_outer_mm:g} mm from each point at frame 0. Area and volume are integrated over "
        f"a triangulation of the frame-0 template; gaps wider than {d.max_edge_mm:g} mm count "
        "no area.", note=True))
    if d.youngs_modulus_kpa > 0:
        sec.add(rh.paragraph(
            "The force is a model output, not a measurement: Hertzian contact of a rigid "
            f"sphere of the shaft radius ({config.tool.shaft_radius_m * 1e3:g} mm) on an "
            f"elastic half-space, E = {d.youngs_modulus_kpa:g} kPa, ν = {d.poisson_ratio:g} "
            "(valid for indentations much smaller than the radius).", note=True))
    rows = [(r["frame"], "yes" if r["contact"] else "", r["clearance_mm"], r["tolerance_mm"],
             r["indentation_mm"], r["penetration_mm"], r["area_mm2"], r["volume_mm3"],
             r["force_n"]) if k else (r["frame"], NOT_MEASURED, *[None] * 7)
            for r, k in zip(series.rows(), known, strict=True)]
    sec.add(rh.table(("frame", "contact", "clearance mm", "tolerance mm", "indentation mm",
                      "penetration mm", "area mm²", "volume mm³", "force N (model)"), rows))
    extra = summary.get("extra_tools") or []
    if extra:
        sec.add(rh.paragraph("The table above is the `[tool]`'s; each `[[tools]]` tool is "
                             "measured the same way, at its working end (per frame: "
                             "metrics/deformation_tools.csv):", note=True))
        sec.add(rh.table(("tool", "pose topic", "frames in contact", "deepest indentation",
                          "largest area", "largest volume", "smallest clearance"),
                         [(t.get("name", ""), t.get("pose", ""),
                           _contact_frames(t, series.n_frames),
                           rh.number(t.get("max_indentation_mm"), "mm"),
                           rh.number(t.get("max_area_mm2"), "mm²"),
                           rh.number(t.get("max_volume_mm3"), "mm³"),
                           rh.number(t.get("min_clearance_mm"), "mm")) for t in extra]))
    scores = (data.evaluation or {}).get("deformation")
    if scores:
        sec.add(_scores(scores))
    return sec


def _scores(s: dict[str, Any]) -> str:
    """The goals against the simulator's truth, one row each."""
    goals = s.get("goals", {})

    def verdict(name: str) -> str:
        value = goals.get(name)
        if isinstance(value, str):
            return value
        return "–" if value is None else ("met" if value else "missed")

    depth, share = s["indentation_error_mm"], s["indentation_error_share"]
    free = s["out_of_contact"]
    rows = [
        ("contact onset / release (frame)",
         f"{s['onset_frame']} / {s['release_frame']} (truth {s['true_onset_frame']} / "
         f"{s['true_release_frame']})", "within 1 frame", verdict("contact_events")),
        ("indentation error, frames in contact (median)",
         f"{rh.number(depth['median'], 'mm')} ({_share(share['median'])})",
         "≤ 0.3 mm or ≤ 10 %", verdict("indentation")),
        ("deformed area error (median)", _share(s["area_error_share"]["median"]), "≤ 20 %",
         verdict("area")),
        ("out of contact: false contacts, |depth| / σ (max)",
         f"{free['false_contacts']}, {rh.number(free['depth_over_sigma_max'])}",
         "0, ≤ 2", verdict("breathing")),
    ]
    if goals and all(v == NOT_MEASURED for v in goals.values()):
        rows = [(name, NOT_MEASURED, goal, "") for name, _, goal, _ in rows]
    return rh.table(("against ground truth", "measured", "goal", ""), rows)


def _mm(value: Any, sigma: Any) -> str:
    text = rh.number(value, "mm")
    return text if sigma is None or text == "–" else f"{text} ± {sigma:.2g}"


def _share(value: Any) -> str:
    return "–" if value is None else f"{value:.1%}"


def _contact_frames(tool: Mapping[str, Any], n_frames: int) -> str:
    """How many frames a tool touches, from its onset to its last frame in contact."""
    frames, onset, release = (tool.get("contact_frames") or [], tool.get("onset_frame"),
                              tool.get("release_frame"))
    if onset is None:
        return "none"
    return f"{len(frames)} (frames {onset}–{(release or n_frames) - 1})"
