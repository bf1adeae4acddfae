"""`surgrecon compare RUN...`: the key figures of several runs side by side, and the config
keys in which they differ.

Figures come from RUN/metrics/summary.json (written by report), RUN/metrics/evaluation.json
(evaluate) and the stage timings in RUN/run.json (a stage's own `seconds`, else the
pipeline's; "reused" for a stage a tagged run linked from the run it started from, left out
of the total); a figure a run does not have is shown as "-". The config is the one recorded
in run.json (RUN/config.toml if run.json has none); keys are compared as dotted
`section.key` names.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..errors import RunFolderError
from ..io.run.artefacts import read_json
from ..io.run.folder import RunFolder, config_value
from ..io.run.layout import RunLayout
from ..io.run.metrics import read_csv

_STAGES = ("ingest", "build-template", "register", "classify", "measure", "evaluate",
           "report")

# (row label, source, dotted path in it); sources: summary, evaluation, seconds
FIGURES: tuple[tuple[str, str, str], ...] = (
    ("frames", "summary", "frames"),
    ("template points", "summary", "template_points"),
    ("template error median (mm)", "evaluation", "template.error.median_mm"),
    ("template error p95 (mm)", "evaluation", "template.error.p95_mm"),
    ("registration error median (mm)", "evaluation", "registration.overall.median_mm"),
    ("registration error p95 (mm)", "evaluation", "registration.overall.p95_mm"),
    ("registration within 1 mm", "evaluation", "registration.overall.within_1mm"),
    ("macro F1", "evaluation", "labels.overall.macro_f1"),
    ("F1 static", "evaluation", "labels.overall.per_class.static.f1"),
    ("F1 shifting", "evaluation", "labels.overall.per_class.shifting.f1"),
    ("F1 deforming", "evaluation", "labels.overall.per_class.deforming.f1"),
    ("static fraction", "summary", "classes_frames_1_on.fractions.static"),
    ("shifting fraction", "summary", "classes_frames_1_on.fractions.shifting"),
    ("deforming fraction", "summary", "classes_frames_1_on.fractions.deforming"),
    ("unknown fraction", "summary", "classes_frames_1_on.fractions.unknown"),
    ("deformation floor (mm)", "summary", "classify.deform_floor_mm"),
    ("residual median (mm)", "summary", "residual_mm.median"),
    ("residual p95 (mm)", "summary", "residual_mm.p95"),
    ("displacement p95 (mm)", "summary", "displacement_mm.p95"),
    ("pixel noise (px)", "summary", "noise.pixel_px"),
    ("tracking noise (px)", "summary", "noise.tracking_px"),
    ("tracker jitter mean (mm)", "summary", "noise.tracker_jitter_mm"),
    ("tracker jitter mean (deg)", "summary", "noise.tracker_jitter_deg"),
    ("untrustworthy frames", "summary", "quality.untrustworthy_frames"),
    *((f"{stage} (s)", "seconds", stage) for stage in _STAGES),
    ("total (s)", "seconds", "total"),
)


@dataclass
class RunFigures:
    """One run's figures {row label: value or None}, flat config and per-frame rows."""

    path: Path
    label: str
    figures: dict[str, Any] = field(default_factory=dict)
    config: dict[str, Any] = field(default_factory=dict)
    frames: list[dict[str, Any]] = field(default_factory=list)


def flatten(config: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """{"a": {"b": 1}} -> {"a.b": 1} (lists stay values)."""
    out: dict[str, Any] = {}
    for key, value in config.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            out.update(flatten(value, f"{name}."))
        else:
            out[name] = value
    return out


def _figure(value: Any) -> Any:
    """A dict of per-camera values -> their mean; a list -> its length."""
    if isinstance(value, dict):
        numbers = [v for v in value.values() if isinstance(v, int | float)]
        return sum(numbers) / len(numbers) if numbers else None
    if isinstance(value, list):
        return len(value)
    return value


def load_run(path: Path, label: str | None = None) -> RunFigures:
    """The figures of one run folder; RunFolderError if it is not one."""
    layout = RunLayout(path)
    data = RunFolder(path).read()
    sources: dict[str, dict[str, Any]] = {"summary": {}, "evaluation": {}}
    if layout.summary_json.is_file():
        sources["summary"] = read_json(layout.summary_json, "report")
    if layout.evaluation_json.is_file():
        sources["evaluation"] = read_json(layout.evaluation_json, "evaluate")
    stages = data.get("stages", {})
    piped = data.get("pipeline", {}).get("seconds", {})  # the stages that time themselves
    seconds = {name: "reused" if stages.get(name, {}).get("reused_from")
               else stages.get(name, {}).get("seconds", piped.get(name)) for name in _STAGES}
    done = [s for s in seconds.values() if isinstance(s, int | float)]
    seconds["total"] = sum(done) if done else None
    sources["seconds"] = seconds
    run = RunFigures(Path(path), label or Path(path).name)
    for row, source, key in FIGURES:
        run.figures[row] = _figure(config_value(sources[source], key))
    config = data.get("config")
    if not config and layout.config_toml.is_file():
        try:
            config = tomllib.loads(layout.config_toml.read_text(encoding="utf-8"))
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
            raise RunFolderError(f"{layout.config_toml}: unreadable ({exc})") from exc
    run.config = flatten(config or {})
    if layout.frames_csv.is_file():
        run.frames = read_csv(layout.frames_csv)
    return run


def load_runs(paths: Sequence[Path]) -> list[RunFigures]:
    """Every run, labelled by its folder name (by the path given where two names clash)."""
    names = [Path(p).name for p in paths]
    return [load_run(p, names[i] if names.count(names[i]) == 1 else str(p))
            for i, p in enumerate(paths)]


def config_differences(runs: Sequence[RunFigures]) -> list[tuple[str, list[Any]]]:
    """(key, value per run) of every config key whose value is not the same in all runs
    (a key a run lacks counts as None)."""
    keys = sorted({k for run in runs for k in run.config})
    out = []
    for key in keys:
        values = [run.config.get(key) for run in runs]
        if any(v != values[0] for v in values[1:]):
            out.append((key, values))
    return out


def format_value(value: Any) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)


def _text_table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]
    lines = ["  ".join(c.ljust(w) if i == 0 else c.rjust(w)
                       for i, (c, w) in enumerate(zip(row, widths, strict=True)))
             for row in [header, *rows]]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)


def figure_rows(runs: Sequence[RunFigures]) -> list[list[str]]:
    """Rows of the figures table (label, one cell per run), leaving out figures no run has."""
    return [[row, *(format_value(run.figures.get(row)) for run in runs)]
            for row, _, _ in FIGURES if any(run.figures.get(row) is not None for run in runs)]


def format_comparison(runs: Sequence[RunFigures]) -> str:
    """The printed comparison: the figures table, then the differing config keys."""
    header = ["", *(run.label for run in runs)]
    text = _text_table(header, figure_rows(runs))
    diffs = config_differences(runs)
    if not diffs:
        return text + "\n\nconfig: the same in every run"
    rows = [[key, *(format_value(v) for v in values)] for key, values in diffs]
    return text + f"\n\nconfig keys that differ ({len(diffs)}):\n" + _text_table(
        ["key", *(run.label for run in runs)], rows)
