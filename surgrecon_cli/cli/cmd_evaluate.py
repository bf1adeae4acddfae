"""`surgrecon evaluate RUN --ground-truth GT.npz`: score a run against ground truth."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from .common import common_options, locks_run_folder, progress


@click.command("evaluate")
@click.argument("run_dir", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("--ground-truth", "gt_path", type=click.Path(dir_okay=False, path_type=Path),
              help="Ground truth (NAME.gt.npz from `surgrecon simulate`); default: the one "
                   "beside the run's input log.")
@common_options
@locks_run_folder()
def evaluate_cmd(run_dir: Path, gt_path: Path | None, config: Any, quiet: bool) -> None:
    """Score a run against the simulator's ground truth.

    Template points are mapped to the nearest point of the true frame-0 surface and that
    material point is followed through the frames. Reports the template error, template
    points on the tool, the registration error per frame and overall (mm), per-class
    precision / recall / F1 of the labels and the contact and indentation measures (the same
    definitions on the true surface). Scores whatever stages are done. Writes
    RUN/metrics/evaluation.json.

    \b
    Example:
      surgrecon evaluate runs/sample --ground-truth sample_data/sample.gt.npz
    """
    from ..io.run.layout import RunLayout
    from ..stages.evaluate import run_evaluate

    gt_path = gt_path or _default_gt(run_dir)
    with progress(quiet)(desc="evaluate", unit="frame") as bar:
        def on_step(done: int, total: int) -> None:
            bar.total = total
            bar.update(done - bar.n)

        result = run_evaluate(run_dir, config, gt_path, on_step=on_step)
    click.echo(format_evaluation(result))
    click.echo(f"-> {RunLayout(run_dir).evaluation_json}")


def _default_gt(run_dir: Path) -> Path:
    from ..errors import InputError
    from ..io.logs.ground_truth import gt_path_beside
    from ..io.run.folder import RunFolder

    recorded = RunFolder(run_dir).read().get("input", {}).get("path")
    candidate = gt_path_beside(Path(recorded)) if recorded else None
    if candidate is None or not candidate.is_file():
        raise InputError(f"no ground truth given and none beside the run's input log "
                         f"({candidate or 'unknown'}); pass --ground-truth GT.npz")
    return candidate


def _mm(stats: dict[str, Any], key: str) -> str:
    value = stats.get(key)
    return "-" if value is None else f"{value:.2f}"


def format_evaluation(ev: dict[str, Any]) -> str:
    """The evaluation as a few readable lines (mm)."""
    lines = []
    tpl = ev["template"]
    err = tpl["error"]
    tool = tpl.get("on_tool")
    tool_text = "tool pose unknown" if tool is None else (
        f"{tool['count']} on the tool ({tool['fraction']:.1%})")
    lines.append(f"template: {tpl['points']} points; distance to the true surface median "
                 f"{_mm(err, 'median_mm')} mm, p95 {_mm(err, 'p95_mm')} mm, max "
                 f"{_mm(err, 'max_mm')} mm; {tool_text}")
    reg = ev.get("registration")
    if reg:
        o = reg["overall"]
        within = o.get("within_1mm")
        lines.append(f"registration error, {ev['frames'] - 1} frames x {tpl['points']} points: "
                     f"median {_mm(o, 'median_mm')} mm, p95 {_mm(o, 'p95_mm')} mm, max "
                     f"{_mm(o, 'max_mm')} mm"
                     + ("" if within is None else f"; {within:.1%} within 1 mm"))
    labels = ev.get("labels")
    per_label = {row["frame"]: row for row in (labels or {}).get("per_frame", [])}
    if reg:
        head = f"  {'frame':>5} {'median':>7} {'p95':>7} {'max':>7}"
        head += f" {'macro-F1':>9}" if labels else ""
        lines.append(head)
        for row in reg["per_frame"]:
            line = (f"  {row['frame']:>5} {_mm(row, 'median_mm'):>7} {_mm(row, 'p95_mm'):>7} "
                    f"{_mm(row, 'max_mm'):>7}")
            if labels:
                f1 = per_label.get(row["frame"], {}).get("macro_f1")
                line += f" {'-' if f1 is None else f'{f1:.3f}':>9}"
            lines.append(line)
    if labels and labels.get("overall"):
        o = labels["overall"]
        lines.append(f"labels, frames 1..{ev['frames'] - 1}: macro-F1 {o['macro_f1']:.3f}")
        lines.append(f"  {'class':<10} {'precision':>9} {'recall':>7} {'F1':>6} {'support':>8}")
        for name, s in o["per_class"].items():
            p, r = s["precision"], s["recall"]
            lines.append(f"  {name:<10} {'-' if p is None else f'{p:.3f}':>9} "
                         f"{'-' if r is None else f'{r:.3f}':>7} {s['f1']:>6.3f} "
                         f"{s['support']:>8}")
        axes = o["confusion_axes"]
        lines.append("  confusion (rows: truth, columns: predicted)")
        lines.append(f"  {'':<10}" + "".join(f"{c:>10}" for c in axes["cols"]))
        for name, row in zip(axes["rows"], o["confusion"], strict=True):
            lines.append(f"  {name:<10}" + "".join(f"{v:>10}" for v in row))
    deformation = ev.get("deformation")
    if deformation and all(isinstance(v, str) for v in deformation["goals"].values()):
        lines.append("contact and indentation: not measured (no tool pose in the log); "
                     "goals: " + ", ".join(f"{k} {v}" for k, v in deformation["goals"].items()))
    elif deformation:
        depth = deformation["indentation_error_mm"]["median"]
        area = deformation["area_error_share"]["median"]
        goals = ", ".join(f"{k} {_goal(v)}" for k, v in deformation["goals"].items())
        lines.append(f"contact onset/release {deformation['onset_frame']}/"
                     f"{deformation['release_frame']} (truth {deformation['true_onset_frame']}/"
                     f"{deformation['true_release_frame']}); indentation error median "
                     f"{'-' if depth is None else f'{depth:.2f}'} mm; area error median "
                     f"{'-' if area is None else f'{area:.1%}'}; goals: {goals}")
    return "\n".join(lines)


def _goal(value: bool | str | None) -> str:
    """A deformation goal: met, MISSED, "-" (nothing to judge) or why it was not judged."""
    if isinstance(value, str):
        return value
    return "-" if value is None else ("met" if value else "MISSED")
