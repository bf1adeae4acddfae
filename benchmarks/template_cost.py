"""Template cost benchmark (issue 15, item 3): the frame-0 template of a simulated 6-camera
log with every candidate pair matched against pair sequencing, at 640x480 and 1920x1080.

    .venv/bin/python benchmarks/template_cost.py [--seeds 21 22] [--sizes 640x480 1920x1080]
        [--baseline /path/to/other/checkout] [--workdir DIR]

Per size and seed, `surgrecon simulate --cameras 6 --frames 2` and `surgrecon ingest` make
a run; then each mode builds the template (`core.template.build.build_template`, the stage's
call) in a fresh child process, which prints: template points, error against the
simulator's true frame-0 surface (median / p95 mm, as `surgrecon evaluate` maps them),
camera pairs matched across epipolar bands, camera-to-template matchings, wall and CPU
seconds of the build, and the child's peak RSS (ru_maxrss; the caller stays small so the
fork does not inflate it). Modes: `all-pairs` (template.match_all_pairs = true) and
`sequenced` (the default); `--baseline DIR` adds `before`, the same child run on another
source tree (e.g. a checkout of main before this change), which has no sequencing.
Goals (issue 15): 6 cameras 1920x1080 template <= 5 s and <= 1 GB; sequenced <= half the
pairs of all-pairs with the template error within 10 %. Timings on a loaded machine are
noisy: compare the ratios of one run.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from long_log import surgrecon_executable

HERE = Path(__file__).resolve()
SOURCE = HERE.parents[1]
MODES = ("all-pairs", "sequenced")


def child(run_dir: Path, gt_path: Path, mode: str) -> None:
    """Build the template of frame 0 of an ingested run in this process; print one JSON line."""
    import dataclasses
    import resource
    import time

    import numpy as np

    from surgrecon_cli.config import Config
    from surgrecon_cli.core.evaluate.scoring import map_to_surface
    from surgrecon_cli.core.noise.model import noise_from_report
    from surgrecon_cli.core.template.build import build_template
    from surgrecon_cli.io.logs.ground_truth import load_ground_truth
    from surgrecon_cli.io.run.ingest_store import load_ingested

    config = Config()
    if mode != "before":
        config = dataclasses.replace(config, template=dataclasses.replace(
            config.template, match_all_pairs=mode == "all-pairs"))
    log = load_ingested(run_dir / "ingest")
    images, poses = log.frame_images(0), log.usable_poses(0)
    noise = noise_from_report(log.report, log.cameras, pixel_px=0.0)
    wall, cpu = time.perf_counter(), time.process_time()
    try:
        from surgrecon_cli.core.template.build import BuildOptions, TemplateFrame
    except ImportError:  # a `--baseline` source tree from before these were grouped
        result = build_template(images, list(log.models), poses, log.tool_poses[0],
                                config.template, config.tool, noise=noise)
    else:
        result = build_template(TemplateFrame(images, poses, log.tool_poses[0]),
                                list(log.models), config.template, config.tool,
                                BuildOptions(noise=noise))
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    gt = load_ground_truth(gt_path)
    error_mm = map_to_surface(result.points, gt.vertices[0], gt.faces).distance * 1e3
    stats = result.stats
    print(json.dumps({
        "points": len(result.points), "median_mm": float(np.median(error_mm)),
        "p95_mm": float(np.percentile(error_mm, 95)),
        "pairs": stats.get("pairs_matched", stats["candidate_pairs"]),
        "to_template": stats.get("matched_to_template", 0), "wall_s": wall, "cpu_s": cpu,
        "rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6}))


def measure(run_dir: Path, gt: Path, mode: str, source: Path) -> dict:
    """One template build in a child process with `source` first on the path."""
    env = dict(os.environ, PYTHONPATH=str(source))
    out = subprocess.run([sys.executable, str(HERE), "--child", str(run_dir), str(gt), mode],
                         env=env, check=True, capture_output=True, text=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def prepare(workdir: Path, size: str, seed: int, exe: str) -> tuple[Path, Path]:
    """Simulated log (6 cameras, 2 frames) and its ingested run, made once per size/seed."""
    width, height = size.split("x")
    stem = workdir / f"sim_{size}_{seed}"
    log, gt, run = stem.with_suffix(".mcap"), stem.with_suffix(".gt.npz"), workdir / stem.name
    if not (log.exists() and gt.exists()):
        subprocess.run([exe, "simulate", str(log), "--cameras", "6", "--frames", "2",
                        "--seed", str(seed), "--width", width, "--height", height, "-q"],
                       check=True, stdout=subprocess.DEVNULL)
    if not (run / "ingest").exists():
        subprocess.run([exe, "ingest", str(log), "-o", str(run), "-q", "--force"], check=True,
                       stdout=subprocess.DEVNULL)
    return run, gt


def print_rows(rows: list[dict]) -> None:
    """The table, and per size/seed sequenced / all-pairs ratios."""
    head = (f"{'size':>9} {'seed':>4} {'mode':>9} {'points':>6} {'med mm':>7} {'p95 mm':>7} "
            f"{'pairs':>5} {'to tpl':>6} {'wall s':>7} {'cpu s':>6} {'RSS GB':>6}")
    print(head)
    for r in rows:
        print(f"{r['size']:>9} {r['seed']:>4} {r['mode']:>9} {r['points']:>6} "
              f"{r['median_mm']:>7.3f} {r['p95_mm']:>7.3f} {r['pairs']:>5} "
              f"{r['to_template']:>6} {r['wall_s']:>7.2f} {r['cpu_s']:>6.2f} {r['rss_gb']:>6.2f}")
    print("\nsequenced / all-pairs (goal: pairs <= 0.5, error <= 1.10)")
    for r in rows:
        if r["mode"] != "sequenced":
            continue
        base = next(a for a in rows if a["mode"] == "all-pairs" and a["size"] == r["size"]
                    and a["seed"] == r["seed"])
        print(f"{r['size']:>9} {r['seed']:>4}  pairs {r['pairs'] / base['pairs']:.2f}  "
              f"points {r['points'] / base['points']:.2f}  "
              f"median {r['median_mm'] / base['median_mm']:.2f}  "
              f"p95 {r['p95_mm'] / base['p95_mm']:.2f}  cpu {r['cpu_s'] / base['cpu_s']:.2f}  "
              f"wall {r['wall_s'] / base['wall_s']:.2f}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[21, 22])
    parser.add_argument("--sizes", nargs="+", default=["640x480", "1920x1080"])
    parser.add_argument("--baseline", type=Path, help="another source tree, run as `before`")
    parser.add_argument("--workdir", type=Path, help="keep logs and runs here (reused)")
    parser.add_argument("--child", nargs=3, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        child(Path(args.child[0]), Path(args.child[1]), args.child[2])
        return 0
    exe = surgrecon_executable()
    with tempfile.TemporaryDirectory() as tmp:
        workdir = args.workdir or Path(tmp)
        workdir.mkdir(parents=True, exist_ok=True)
        rows = []
        for size in args.sizes:
            for seed in args.seeds:
                run, gt = prepare(workdir, size, seed, exe)
                modes = [(m, SOURCE) for m in MODES]
                if args.baseline:
                    modes.insert(0, ("before", args.baseline.resolve()))
                for mode, source in modes:
                    row = measure(run, gt, mode, source)
                    rows.append(dict(row, size=size, seed=seed, mode=mode))
                    print(json.dumps(rows[-1]), flush=True)
        print()
        print_rows(rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
