"""What damaged or altered a run, in plain sentences: shown in a box at the top of the
report and listed in summary.json (`caveats`). Pure; reads only the run.json dict and the
ingest report.

Sources (recorded by the stages in run.json):
- ingest `truncated`: the log was damaged and `--allow-truncated` used the data before it;
- ingest `salvaged`: the log was damaged after its data (index, summary): read by streaming;
- ingest `replaced`: `--force` replaced the run of another log, or wrote into a folder that
  was not a run folder;
- register `frames_failed`: frames that could not be registered (their points unknown);
- the ingest report's `part`: only a part of the log was ingested (ingest.start_s,
  duration_s, every);
- the ingest report's `warnings`: what ingest warned about on the terminal (a missing robot,
  lost messages, unit or calibration doubts).
"""

from __future__ import annotations

from typing import Any

_LISTED = 10  # failed frames named one by one, beyond that only counted


def run_caveats(run: dict[str, Any], ingest_report: dict[str, Any]) -> list[str]:
    """The caveats of a run (run.json as a dict, the ingest report), in pipeline order."""
    stages = run.get("stages", {})
    ingest, register = stages.get("ingest", {}), stages.get("register", {})
    out = []
    damage = ingest.get("truncated") or ingest_report.get("truncated")
    if damage:
        dropped = ingest_report.get("frames_dropped_after_damage")
        frames = ingest.get("frames")
        kept = f"{frames} frames kept" if frames is not None else "the frames before it kept"
        extra = f", {dropped} incomplete frames dropped" if dropped else ""
        out.append(f"Damaged log read with --allow-truncated: {damage}. Only the data before "
                   f"the damage was used ({kept}{extra}); the rest of the recording is missing "
                   "from every result.")
    if ingest.get("salvaged"):
        out.append(f"Damaged log salvaged: {ingest['salvaged']}; every message was still read "
                   "(by streaming, without the log's index), so the results are complete, "
                   "but the file should be re-copied or repaired.")
    part = ingest_report.get("part")
    if part:
        window = (f"{part['duration_s']:g} s" if part["duration_s"] else "to the end")
        out.append(f"A part of the log: {ingest_report.get('frames')} of its "
                   f"{ingest_report.get('frames_in_log')} frames (from {part['start_s']:g} s "
                   f"after its first, {window}, every {part['every']}; ingest.start_s, "
                   "duration_s, every).")
    if ingest.get("replaced"):
        out.append(f"--force: {ingest['replaced']}.")
    warned = ingest_report.get("warnings") or []
    for text in warned[:_LISTED]:
        out.append(f"Ingest warned: {text.rstrip('.')}.")
    if len(warned) > _LISTED:
        out.append(f"Ingest warned {len(warned) - _LISTED} more times (each shown on the "
                   "terminal during ingest).")
    failed = register.get("frames_failed") or {}
    if failed:
        keys = sorted(failed, key=int)
        named = "; ".join(f"frame {k}: {failed[k]}" for k in keys[:_LISTED])
        more = f"; and {len(keys) - _LISTED} more" if len(keys) > _LISTED else ""
        out.append(f"{len(keys)} frame{'s' if len(keys) > 1 else ''} could not be registered "
                   f"({named}{more}); their points are unknown and their figures are "
                   "left out.")
    return out
