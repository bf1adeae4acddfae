"""Contact and indentation benchmark (issue 17): the goals per simulator seed, tuning and
acceptance seeds reported apart.

    .venv/bin/python benchmarks/deformation.py [--tuning 201 202 203] [--acceptance 204 205 206]
        [--variants default press-release hover] [--variant-seeds 201 204] [--frames 12]
        [--sample] [--workdir /tmp/surgrecon-deformation] [--fresh] [--set section.key=value ...]

For every (variant, seed): `surgrecon simulate LOG --variant V --seed S --frames F` (LOG.mcap
and LOG.gt.npz; reused when present), `surgrecon run LOG -o RUN` (resumes a finished run at
no cost), then `surgrecon measure RUN` and `surgrecon evaluate RUN` again, so that the table
always shows the measures of the code and settings of now, and RUN/metrics/evaluation.json's
`deformation` part is read. The default variant runs on the tuning and the acceptance seeds;
press-release (the tool lets go and lifts off: a release to detect) and hover (breathing
alone under a tool hovering 1 mm above: no contact) on --variant-seeds, the first counted
as tuning, the others as acceptance. --sample adds the shipped sample (its ground truth
predates the recorded tool poses: the ingested ones are used).

Goals (core/evaluate/deformation_scoring.py): contact onset and release within 1 frame; indentation
depth at the tip, frames in contact, median error <= 0.3 mm or <= 10 % of the true depth;
deformed area within 20 % (median relative error); out of contact (breathing alone) no
contact and the depth under the tip within 2 sigma; overhead of the measures <= 5 % of the
run (the measure stage and the report's two deformation figures against the sum of the
stages' wall times, evaluate left out: a real run has no ground truth; the stages' times
are those recorded last, so a busy machine makes them noisy). A goal holds for a set when
it holds on every run of it.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

GOALS = ("contact_events", "indentation", "area", "breathing")


def surgrecon() -> str:
    beside = Path(sys.executable).with_name("surgrecon")
    found = str(beside) if beside.exists() else shutil.which("surgrecon")
    if found is None:
        sys.exit("surgrecon is not installed (run `make install`, then .venv/bin/python ...)")
    return found


def call(argv: list[str], log: Path) -> None:
    proc = subprocess.run(argv, capture_output=True, text=True)
    with log.open("a") as f:
        f.write(f"$ {' '.join(argv)}\n{proc.stdout}{proc.stderr}(exit {proc.returncode})\n")
    if proc.returncode != 0:
        lines = (proc.stderr or proc.stdout).strip().splitlines() or ["failed"]
        raise RuntimeError(lines[-1])


def figure_seconds(run: Path) -> float:
    """Wall time of drawing the report's deformation figures of a run (in this process)."""
    from surgrecon_cli.config import load_config
    from surgrecon_cli.report.figures import deformation_tasks
    from surgrecon_cli.report.gather import gather

    data = gather(run)
    start = time.perf_counter()
    for task in deformation_tasks(data, load_config(run / "config.toml")):
        task.fn(*task.args)
    return time.perf_counter() - start


def run_one(name: str, variant: str, seed: int | None, args: argparse.Namespace,
            exe: str) -> dict[str, Any]:
    """Simulate (or take the sample), run, measure and evaluate one log; its table row."""
    work = args.workdir
    log_file = work / f"{name}.log"
    if seed is None:
        log, gt = Path("sample_data/sample.mcap"), Path("sample_data/sample.gt.npz")
    else:
        log = work / "logs" / f"{name}.mcap"
        gt = log.with_name(f"{name}.gt.npz")
        if args.fresh or not gt.exists():
            log.parent.mkdir(parents=True, exist_ok=True)
            call([exe, "simulate", str(log), "--variant", variant, "--seed", str(seed),
                  "--frames", str(args.frames), "-q"], log_file)
    run = work / "runs" / name
    sets = [a for s in args.set for a in ("--set", s)]
    if args.fresh and run.exists():
        shutil.rmtree(run)
    call([exe, "run", str(log), "-o", str(run), "-q", *sets], log_file)
    call([exe, "measure", str(run), "-q", *sets], log_file)
    call([exe, "evaluate", str(run), "--ground-truth", str(gt), "-q", *sets], log_file)
    evaluation = json.loads((run / "metrics" / "evaluation.json").read_text())
    stages = json.loads((run / "run.json").read_text())["stages"]
    seconds = {k: float(v.get("seconds") or 0.0) for k, v in stages.items() if k != "evaluate"}
    total = sum(seconds.values())  # a run without ground truth: no evaluate
    overhead = (seconds["measure"] + figure_seconds(run)) / total if total else None
    return {"name": name, "variant": variant, "seed": seed, "score": evaluation["deformation"],
            "overhead": overhead}


def _fmt(value: Any, spec: str) -> str:
    return "-" if value is None else format(value, spec)


def print_table(title: str, rows: list[dict[str, Any]]) -> None:
    print(f"\n{title}")
    head = (f"{'run':<20} {'onset':>7} {'release':>9} {'depth err mm':>13} {'(share)':>8} "
            f"{'area err':>9} {'free: fc':>9} {'|d|/σ':>6} {'overhead':>9}  goals")
    print(head)
    print("-" * len(head))
    for r in rows:
        s = r["score"]
        goals = " ".join(f"{g[:5]}:{'-' if s['goals'][g] is None else 'YN'[not s['goals'][g]]}"
                         for g in GOALS)
        onset = f"{_fmt(s['onset_frame'], 'd')}/{_fmt(s['true_onset_frame'], 'd')}"
        release = f"{_fmt(s['release_frame'], 'd')}/{_fmt(s['true_release_frame'], 'd')}"
        print(f"{r['name']:<20} {onset:>7} {release:>9} "
              f"{_fmt(s['indentation_error_mm']['median'], '.3f'):>13} "
              f"{_fmt(s['indentation_error_share']['median'], '.1%'):>8} "
              f"{_fmt(s['area_error_share']['median'], '.1%'):>9} "
              f"{s['out_of_contact']['false_contacts']:>9} "
              f"{_fmt(s['out_of_contact']['depth_over_sigma_max'], '.2f'):>6} "
              f"{_fmt(r['overhead'], '.1%'):>9}  {goals}")
    verdicts = []
    for g in GOALS:
        values = [r["score"]["goals"][g] for r in rows if r["score"]["goals"][g] is not None]
        verdicts.append(f"{g} {'PASS' if values and all(values) else 'FAIL' if values else '-'}")
    over = [r["overhead"] for r in rows if r["overhead"] is not None]
    verdicts.append(f"overhead {'PASS' if over and max(over) <= 0.05 else 'FAIL'} "
                    f"(max {_fmt(max(over) if over else None, '.1%')})")
    print("goals: " + "; ".join(verdicts))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tuning", nargs="*", type=int, default=[201, 202, 203])
    parser.add_argument("--acceptance", nargs="*", type=int, default=[204, 205, 206])
    parser.add_argument("--variants", nargs="*", default=["default", "press-release", "hover"])
    parser.add_argument("--variant-seeds", nargs="*", type=int, default=[201, 204])
    parser.add_argument("--frames", type=int, default=12)
    parser.add_argument("--sample", action="store_true")
    parser.add_argument("--workdir", type=Path, default=Path("/tmp/surgrecon-deformation"))
    parser.add_argument("--fresh", action="store_true")
    parser.add_argument("--set", action="append", default=[])
    args = parser.parse_args()
    args.workdir.mkdir(parents=True, exist_ok=True)
    exe = surgrecon()
    plan: dict[str, list[tuple[str, str, int | None]]] = {"tuning": [], "acceptance": []}
    for part, seeds in (("tuning", args.tuning), ("acceptance", args.acceptance)):
        if "default" in args.variants:
            plan[part] += [(f"default-s{s}", "default", s) for s in seeds]
    for i, seed in enumerate(args.variant_seeds):
        for variant in [v for v in args.variants if v != "default"]:
            part = "tuning" if i == 0 else "acceptance"
            plan[part].append((f"{variant}-s{seed}", variant, seed))
    if args.sample:
        plan["acceptance"].append(("sample", "default", None))
    results: dict[str, list[dict[str, Any]]] = {}
    for part, runs in plan.items():
        results[part] = []
        for name, variant, seed in runs:
            try:
                results[part].append(run_one(name, variant, seed, args, exe))
            except RuntimeError as exc:
                print(f"{name}: {exc}", file=sys.stderr)
        print_table(f"{part} seeds", results[part])
    (args.workdir / "deformation.json").write_text(json.dumps(results, indent=1))
    print(f"\n-> {args.workdir / 'deformation.json'}")


if __name__ == "__main__":
    main()
