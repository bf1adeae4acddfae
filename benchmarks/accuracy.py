"""Accuracy benchmark: the whole pipeline on simulator variants, scored against their truth.

    .venv/bin/python benchmarks/accuracy.py [--variants default stereo ...] [--seeds 101 ...]
        [--frames 12] [--width 640 --height 480] [--workdir /tmp/surgrecon-accuracy]
        [--jobs 1] [--fresh] [--config F.toml] [--set section.key=value ...]

For every (variant, seed): `surgrecon simulate LOG --variant V --seed S` (LOG.mcap and
LOG.gt.npz), `surgrecon run LOG -o RUN`, `surgrecon evaluate RUN --ground-truth LOG.gt.npz`,
then RUN/metrics/evaluation.json is read. Prints one table (a row per run), per variant the
mean and minimum macro-F1, and the goals with PASS / FAIL (a goal holds when it holds on
every seed; the worst seed's value is shown). The table is also written to
WORKDIR/accuracy.csv and WORKDIR/accuracy.json. Logs and run folders are reused when they
exist (`surgrecon run` resumes a finished run at no cost); --fresh regenerates them. A run
that fails shows its one-line error in its row; the others go on.

The default seeds 101-105 are the acceptance seeds. "deform share" is the share of the
labelled points (label not unknown) that the pipeline calls deforming: the truth of the rigid
variant has none. Metrics that evaluation.json does not have (yet) print as "-".
--config and --set go to `surgrecon run` and `surgrecon evaluate` (a run folder per
configuration); the simulated truth always uses the default label rule (SPEC section 6).
"""

from __future__ import annotations

import argparse
import csv
import hashlib
import json
import math
import shutil
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

from surgrecon_cli.io.run.layout import RunLayout

DEFAULT_VARIANTS = ("default", "stereo", "stereo-plus", "noisy", "rigid", "sweep")
DEFAULT_SEEDS = (101, 102, 103, 104, 105)
# Extra `surgrecon run` arguments a variant needs (its topics, ...): none so far, every
# variant writes the default topics.
RUN_ARGS: dict[str, list[str]] = {}

# (key, header, format): the table's columns after variant and seed.
COLUMNS = (
    ("macro_f1", "macroF1", "{:.3f}"),
    ("f1_static", "F1 st", "{:.3f}"),
    ("f1_shifting", "F1 sh", "{:.3f}"),
    ("f1_deforming", "F1 de", "{:.3f}"),
    ("precision_deforming", "P de", "{:.3f}"),
    ("recall_deforming", "R de", "{:.3f}"),
    ("reg_median_mm", "reg med", "{:.3f}"),
    ("reg_p95_mm", "reg p95", "{:.3f}"),
    ("reg_labelled_median_mm", "lab med", "{:.3f}"),
    ("reg_labelled_p95_mm", "lab p95", "{:.3f}"),
    ("deforming_share", "deform%", "{:.1%}"),
    ("calibration_2sigma", "calib2σ", "{:.1%}"),
    ("unknown_fraction", "unknown", "{:.1%}"),
    ("unsupported_moved", "unsupp", "{:.0f}"),
    ("seconds", "time s", "{:.0f}"),  # simulate + run + evaluate, as when first made
)


def surgrecon_executable() -> str:
    """The `surgrecon` script of the interpreter running this benchmark (the project venv)."""
    beside = Path(sys.executable).with_name("surgrecon")
    if beside.exists():
        return str(beside)
    found = shutil.which("surgrecon")
    if found is None:
        sys.exit("surgrecon is not installed (run `make install`, then .venv/bin/python ...)")
    return found


# ---- reading evaluation.json defensively -------------------------------------------------
def lookup(data: Any, *paths: str) -> Any:
    """The first value found along any of the dotted paths, else None."""
    for path in paths:
        node = data
        for key in path.split("."):
            node = node.get(key) if isinstance(node, dict) else None
            if node is None:
                break
        if node is not None:
            return node
    return None


def number(value: Any, *keys: str) -> float | None:
    """A finite float from a number, or from the first of `keys` in a dict; else None."""
    if isinstance(value, dict):
        value = next((value[k] for k in keys if k in value), None)
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    return float(value) if math.isfinite(value) else None


def fraction(value: Any, *keys: str) -> float | None:
    """A fraction in 0..1 (a value above 1 is taken for a percentage)."""
    x = number(value, *keys)
    return x / 100.0 if x is not None and x > 1.0 else x


def deforming_share(overall: Any) -> float | None:
    """Predicted deforming / predicted anything but unknown, from the confusion matrix."""
    confusion = lookup(overall, "confusion")
    cols = lookup(overall, "confusion_axes.cols") or ["static", "shifting", "deforming", "unknown"]
    try:
        totals = [sum(float(row[c]) for row in confusion) for c in range(len(cols))]
        labelled = sum(t for name, t in zip(cols, totals, strict=True) if name != "unknown")
        deforming = totals[list(cols).index("deforming")]
    except (TypeError, ValueError, IndexError, KeyError):
        return None
    return deforming / labelled if labelled > 0 else None


def metrics(evaluation: dict) -> dict[str, float | None]:
    """The table's numbers from one evaluation.json."""
    overall = lookup(evaluation, "labels.overall") or {}
    per_class = overall.get("per_class", {}) if isinstance(overall, dict) else {}
    row: dict[str, float | None] = {
        "macro_f1": number(lookup(overall, "macro_f1")),
        "precision_deforming": number(lookup(per_class, "deforming.precision")),
        "recall_deforming": number(lookup(per_class, "deforming.recall")),
        "reg_median_mm": number(lookup(evaluation, "registration.overall.median_mm")),
        "reg_p95_mm": number(lookup(evaluation, "registration.overall.p95_mm")),
        "reg_labelled_median_mm": number(
            lookup(evaluation, "registration.labelled.median_mm", "registration.labelled.median")
        ),
        "reg_labelled_p95_mm": number(
            lookup(evaluation, "registration.labelled.p95_mm", "registration.labelled.p95")
        ),
        "deforming_share": deforming_share(overall),
        "calibration_2sigma": fraction(
            lookup(evaluation, "labels.calibration_2sigma", "labels.overall.calibration_2sigma"),
            "fraction", "value", "within",
        ),
        "unknown_fraction": fraction(
            lookup(evaluation, "labels.unknown_fraction", "labels.overall.unknown_fraction"),
            "fraction", "value",
        ),
        "unsupported_moved": number(
            lookup(evaluation, "registration.unsupported_moved", "labels.unsupported_moved"),
            "count", "value",
        ),
    }
    for name in ("static", "shifting", "deforming"):
        row[f"f1_{name}"] = number(lookup(per_class, f"{name}.f1"))
    return row


# ---- one (variant, seed) ---------------------------------------------------------------------
def one_line(text: str) -> str:
    """The error line of a failed command (its last `error:` line, else its last line)."""
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    errors = [line for line in lines if line.lower().startswith(("error", "internal error"))]
    line = (errors or lines or ["failed without output"])[-1]
    return line if len(line) <= 300 else line[:297] + "..."


class StepError(Exception):
    """A command of one (variant, seed) failed: which step, and its one-line error."""

    def __init__(self, step: str, message: str):
        super().__init__(f"{step}: {message}")


def step(name: str, argv: list[str], log_file: Path) -> float:
    """Run one command, appending its output to `log_file`; seconds taken."""
    start = time.perf_counter()
    proc = subprocess.run(argv, capture_output=True, text=True)
    seconds = time.perf_counter() - start
    with log_file.open("a") as f:
        f.write(f"$ {' '.join(argv)}\n{proc.stdout}{proc.stderr}(exit {proc.returncode}, "
                f"{seconds:.1f} s)\n\n")
    if proc.returncode != 0:
        raise StepError(name, one_line(proc.stderr or proc.stdout))
    return seconds


def _stored_seconds(path: Path, fallback: float = 0.0) -> float:
    """Seconds a step took when its output was made (saved beside it), else `fallback`."""
    try:
        return float(json.loads(path.read_text()))
    except (OSError, ValueError, TypeError):
        return fallback


def run_one(variant: str, seed: int, args: argparse.Namespace, exe: str) -> dict[str, Any]:
    """Simulate, run and evaluate one (variant, seed); the table row."""
    row: dict[str, Any] = {"variant": variant, "seed": seed, "error": "", "reused": False}
    stem = f"{variant}-s{seed}-f{args.frames}-{args.width}x{args.height}"
    logs, runs = args.workdir / "logs", args.workdir / "runs"
    log = logs / f"{stem}.mcap"
    gt = logs / f"{stem}.gt.npz"
    run_args = ["--config", str(args.config)] if args.config else []
    for override in args.set:
        run_args += ["--set", override]
    run_args += RUN_ARGS.get(variant, [])
    suffix = ""
    if run_args:  # a run folder per pipeline configuration
        key = json.dumps([run_args, args.config.read_text() if args.config else ""])
        suffix = "-" + hashlib.sha256(key.encode()).hexdigest()[:8]
    run_dir = runs / f"{stem}{suffix}"
    out_log = args.workdir / "logs" / f"{stem}{suffix}.txt"
    row["run_dir"] = str(run_dir)
    timings = {"simulate": 0.0, "run": 0.0, "evaluate": 0.0}
    try:
        logs.mkdir(parents=True, exist_ok=True)
        runs.mkdir(parents=True, exist_ok=True)
        if args.fresh:
            for path in (log, gt, out_log, logs / f"{stem}.seconds.json",
                         runs / f"{run_dir.name}.seconds.json"):
                path.unlink(missing_ok=True)
            shutil.rmtree(run_dir, ignore_errors=True)
        sim_time = logs / f"{stem}.seconds.json"
        run_time = runs / f"{run_dir.name}.seconds.json"
        if not (log.exists() and gt.exists()):
            shutil.rmtree(run_dir, ignore_errors=True)  # a new log: its old run is stale
            run_time.unlink(missing_ok=True)
            timings["simulate"] = step("simulate", [
                exe, "simulate", str(log), "--variant", variant, "--seed", str(seed),
                "--frames", str(args.frames), "--width", str(args.width),
                "--height", str(args.height), "-q"], out_log)
            sim_time.write_text(json.dumps(timings["simulate"]))
        else:
            timings["simulate"] = _stored_seconds(sim_time)
            row["reused"] = True
        if args.rerun:
            shutil.rmtree(run_dir, ignore_errors=True)
            run_time.unlink(missing_ok=True)
        fresh_run = not RunLayout(run_dir).run_json.exists()
        timings["run"] = step("run", [exe, "run", str(log), "-o", str(run_dir), "-q",
                                      *run_args], out_log)
        if fresh_run:
            run_time.write_text(json.dumps(timings["run"]))
        else:  # resumed: report what the run took when it was made (when known)
            timings["run"] = _stored_seconds(run_time, timings["run"])
            row["reused"] = True
        timings["evaluate"] = step("evaluate", [
            exe, "evaluate", str(run_dir), "--ground-truth", str(gt), "-q", *run_args], out_log)
        evaluation_path = RunLayout(run_dir).evaluation_json
        try:
            evaluation = json.loads(evaluation_path.read_text())
        except (OSError, ValueError) as exc:
            raise StepError("read", f"{evaluation_path}: {exc}") from exc
        row.update(metrics(evaluation))
    except StepError as exc:
        row["error"] = str(exc)
    except OSError as exc:
        row["error"] = f"{type(exc).__name__}: {exc}"
    row.update({f"{k}_s": round(v, 1) for k, v in timings.items()})
    row["seconds"] = round(sum(timings.values()), 1)
    return row


# ---- goals -------------------------------------------------------------------------------------
# (variants it applies to or None for all, description, metric, low, high)
GOALS = (
    (("default",), "macro-F1 >= 0.92", "macro_f1", 0.92, None),
    (("default",), "deforming precision >= 0.85", "precision_deforming", 0.85, None),
    (("default",), "deforming recall >= 0.90", "recall_deforming", 0.90, None),
    (("stereo", "noisy"), "macro-F1 >= 0.88", "macro_f1", 0.88, None),
    (("rigid",), "deforming share <= 1 %", "deforming_share", None, 0.01),
    (None, "registration median <= 0.2 mm", "reg_median_mm", None, 0.2),
    (None, "registration p95 <= 0.8 mm", "reg_p95_mm", None, 0.8),
    (None, "calibration (2 sigma) 85-99 %", "calibration_2sigma", 0.85, 0.99),
    (None, "unsupported moved points = 0", "unsupported_moved", None, 0.0),
)


def check_goals(rows: list[dict[str, Any]], variants: list[str]) -> list[dict[str, Any]]:
    """One result per (goal, variant): PASS when every seed meets it, FAIL when a seed
    misses it or failed to run, N/A when the metric is missing."""
    results = []
    for applies, text, key, low, high in GOALS:
        for variant in variants:
            if applies is not None and variant not in applies:
                continue
            mine = [r for r in rows if r["variant"] == variant]
            values = [r.get(key) for r in mine if not r["error"]]
            failed_runs = sum(1 for r in mine if r["error"])
            present = [v for v in values if v is not None]

            def badness(v: float, low=low, high=high) -> float:
                """How far v is past its bound (> 0: missed; the seed nearest to missing a
                met goal has the largest)."""
                return max((low - v) if low is not None else -math.inf,
                           (v - high) if high is not None else -math.inf)

            worst = max(present, key=badness) if present else None
            if failed_runs:
                status = "FAIL"
            elif not present or len(present) < len(values):
                status = "N/A"
            else:
                status = "PASS" if all(badness(v) <= 0 for v in present) else "FAIL"
            results.append({"variant": variant, "goal": text, "metric": key, "worst": worst,
                            "mean": sum(present) / len(present) if present else None,
                            "seeds": len(mine), "failed_runs": failed_runs, "status": status})
    return results


# ---- output --------------------------------------------------------------------------------------
def cell(value: Any, fmt: str) -> str:
    return "-" if value is None else fmt.format(value)


def print_table(rows: list[dict[str, Any]]) -> None:
    headers = ["variant", "seed", *(h for _, h, _ in COLUMNS)]
    body = [[r["variant"], str(r["seed"]), *(cell(r.get(k), f) for k, _, f in COLUMNS)]
            for r in rows]
    widths = [max(len(h), *(len(b[i]) for b in body)) for i, h in enumerate(headers)]
    print("  ".join(h.rjust(w) if i > 1 else h.ljust(w) for i, (h, w) in
                    enumerate(zip(headers, widths, strict=True))))
    for r, b in zip(rows, body, strict=True):
        line = "  ".join(c.rjust(w) if i > 1 else c.ljust(w) for i, (c, w) in
                         enumerate(zip(b, widths, strict=True)))
        print(line + (f"  ERROR {r['error']}" if r["error"] else ""))


def summarise(rows: list[dict[str, Any]], variants: list[str]) -> list[dict[str, Any]]:
    out = []
    for variant in variants:
        mine = [r for r in rows if r["variant"] == variant]
        f1 = [r["macro_f1"] for r in mine if not r["error"] and r.get("macro_f1") is not None]
        out.append({"variant": variant, "runs": len(mine), "ok": len(f1),
                    "macro_f1_mean": sum(f1) / len(f1) if f1 else None,
                    "macro_f1_min": min(f1) if f1 else None,
                    "seconds_mean": sum(r["seconds"] for r in mine) / len(mine) if mine else None})
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="\n\n".join(__doc__.split("\n\n")[1:]))
    parser.add_argument("--variants", nargs="+", default=list(DEFAULT_VARIANTS),
                        metavar="NAME", help="simulator variants (default: %(default)s)")
    parser.add_argument("--seeds", nargs="+", type=int, default=list(DEFAULT_SEEDS),
                        metavar="S", help="seeds (default: the acceptance seeds %(default)s)")
    parser.add_argument("--frames", type=int, default=12, help="frames per log (default 12)")
    parser.add_argument("--width", type=int, default=640, help="image width (default 640)")
    parser.add_argument("--height", type=int, default=480, help="image height (default 480)")
    parser.add_argument("--workdir", type=Path, default=Path("/tmp/surgrecon-accuracy"),
                        help="logs, runs and the tables (default %(default)s)")
    parser.add_argument("--jobs", type=int, default=1, help="(variant, seed) runs in parallel")
    parser.add_argument("--fresh", action="store_true",
                        help="regenerate logs and runs even when they exist")
    parser.add_argument("--rerun", action="store_true",
                        help="keep the simulated logs, run the pipeline again (after a code "
                        "change)")
    parser.add_argument("--config", type=Path, help="config TOML passed to surgrecon run")
    parser.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                        help="passed to surgrecon run (repeatable)")
    args = parser.parse_args(argv)

    from surgrecon_cli.sim.variants import VARIANTS

    unknown = [v for v in args.variants if v not in VARIANTS]
    if unknown:
        parser.error(f"unknown variant(s) {', '.join(unknown)}; known: {', '.join(VARIANTS)}")
    if args.frames < 2 or args.jobs < 1:
        parser.error("--frames must be >= 2 and --jobs >= 1")
    if args.config is not None and not args.config.is_file():
        parser.error(f"--config {args.config}: no such file")
    args.workdir.mkdir(parents=True, exist_ok=True)
    exe = surgrecon_executable()
    jobs = [(v, s) for v in args.variants for s in args.seeds]
    print(f"{len(jobs)} runs ({len(args.variants)} variants x {len(args.seeds)} seeds), "
          f"{args.frames} frames {args.width}x{args.height}, {args.jobs} in parallel, "
          f"in {args.workdir}", flush=True)
    start = time.perf_counter()

    def work(job: tuple[str, int]) -> dict[str, Any]:
        row = run_one(*job, args, exe)
        status = f"ERROR {row['error']}" if row["error"] else (
            f"macro-F1 {cell(row.get('macro_f1'), '{:.3f}')}")
        print(f"  {job[0]} seed {job[1]}: {status} ({row['seconds']:.0f} s)", flush=True)
        return row

    with ThreadPoolExecutor(max_workers=args.jobs) as pool:
        rows = list(pool.map(work, jobs))
    print()
    print_table(rows)
    summary = summarise(rows, args.variants)
    print("\nmacro-F1 per variant (over the seeds that ran):")
    for s in summary:
        print(f"  {s['variant']:<12} mean {cell(s['macro_f1_mean'], '{:.3f}')}  "
              f"min {cell(s['macro_f1_min'], '{:.3f}')}  ({s['ok']}/{s['runs']} runs, "
              f"{cell(s['seconds_mean'], '{:.0f}')} s per run)")
    goals = check_goals(rows, args.variants)
    fmt = {k: f for k, _, f in COLUMNS}
    print("\ngoals (PASS = met on every seed; worst seed shown):")
    width = max(len(g["goal"]) for g in goals)
    for g in goals:
        print(f"  {g['status']:<4}  {g['variant']:<12} {g['goal']:<{width}}  worst "
              f"{cell(g['worst'], fmt[g['metric']])}  mean {cell(g['mean'], fmt[g['metric']])}"
              + (f"  ({g['failed_runs']} runs failed)" if g["failed_runs"] else ""))
    keys = ["variant", "seed", *(k for k, _, _ in COLUMNS), "simulate_s", "run_s", "evaluate_s",
            "reused", "error", "run_dir"]
    with (args.workdir / "accuracy.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=keys, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)
    (args.workdir / "accuracy.json").write_text(json.dumps(
        {"frames": args.frames, "width": args.width, "height": args.height,
         "variants": args.variants, "seeds": args.seeds, "set": args.set,
         "config": str(args.config) if args.config else None,
         "rows": rows, "summary": summary, "goals": goals}, indent=1))
    print(f"\n{args.workdir / 'accuracy.csv'}, {args.workdir / 'accuracy.json'} "
          f"({time.perf_counter() - start:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
