"""Scale benchmark (issue 6): ingest of a long log, and the whole pipeline on 1 and 2
workers with each executor.

    .venv/bin/python benchmarks/scale.py [--frames 60] [--repeat 3] [--long-gb 2.1] [--skip-long]
    .venv/bin/python benchmarks/scale.py --only-long-logs [--long-frames 2000] [--drift-frames 500]

1. Long log: `benchmarks/long_log.py` writes a >= 2 GB synthetic log (6 cameras; rendered
   images reused with new stamps), `surgrecon ingest` runs on it in a child process, and
   its peak RSS (goal <= 1 GB), wall time and throughput are printed.
2. Pipeline: a simulated log of `--frames` frames (6 cameras, 640x480, as the shipped
   sample) goes through `surgrecon run` from scratch — ingest to report, imports and
   worker start-up included — with serial, processes and Dask LocalCluster executors on 1
   and 2 workers, each `--repeat` times (rounds interleave the executors). Printed, for the
   run of median wall time: wall time, frames per second, the register and classify stage
   times, speedups against serial and against the same executor on 1 worker (goal: >= 1.7x
   for 2 workers on 2 cores), and whether the clouds are byte-identical to serial's.
3. Long logs (issue 15): per-frame cost and memory of the pieces that grew with the log at
   20 / 2,000 / 100k frames, whole serial runs of 20 and --long-frames replayed frames
   (per-frame stage time, peak RSS) and registration drift over --drift-frames simulated
   frames (benchmarks/scale_long.py; --pieces-only: the timed pieces alone).
Big files go to --workdir (default a temporary folder), deleted at the end.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

from long_log import measure_ingest, surgrecon_executable, write_long_log
from scale_long import long_tables

SURGRECON = surgrecon_executable()
CONFIGS = (("serial", 1), ("processes", 1), ("processes", 2), ("dask", 1), ("dask", 2))


def clouds_digest(run_dir: Path) -> str:
    """SHA-256 over every labelled cloud of a run (byte-identical outputs <=> same digest)."""
    digest = hashlib.sha256()
    for ply in sorted((run_dir / "clouds").glob("*.ply")):
        digest.update(ply.read_bytes())
    return digest.hexdigest()


def time_run(log: Path, run_dir: Path, executor: str, workers: int) -> dict:
    """`surgrecon run` from scratch in a child process: wall s and the stage times."""
    shutil.rmtree(run_dir, ignore_errors=True)
    start = time.perf_counter()
    subprocess.run([SURGRECON, "run", str(log), "-o", str(run_dir), "-q",
                    "--executor", executor, "--workers", str(workers)],
                   check=True, stdout=subprocess.DEVNULL)
    wall = time.perf_counter() - start
    run = json.loads((run_dir / "run.json").read_text())
    return {"wall": wall, "frames": run["ingest"]["frames"],
            "stages": run["pipeline"]["seconds"], "digest": clouds_digest(run_dir)}


def median_run(runs: list[dict]) -> dict:
    """The run of median wall time (its stage times and digest with it); every run must
    have produced the same clouds."""
    ordered = sorted(runs, key=lambda run: run["wall"])
    median = dict(ordered[len(ordered) // 2])
    if len({run["digest"] for run in runs}) > 1:
        median["digest"] = "differs between repeats"
    return median


def pipeline_table(work: Path, frames: int, repeat: int) -> None:
    log = work / f"scale{frames}.mcap"
    print(f"simulating {frames} frames (6 cameras, 640x480) ...", flush=True)
    subprocess.run([SURGRECON, "simulate", str(log), "--frames", str(frames), "-q"],
                   check=True, stdout=subprocess.DEVNULL)
    runs: dict[tuple[str, int], list[dict]] = {config: [] for config in CONFIGS}
    for round_ in range(repeat):  # rounds interleave the configs, so drift hits all alike
        for executor, workers in CONFIGS:
            run = time_run(log, work / f"run-{executor}-{workers}", executor, workers)
            runs[executor, workers].append(run)
            print(f"  round {round_ + 1}/{repeat} {executor} x{workers}: {run['wall']:.1f} s",
                  flush=True)
    rows = {config: median_run(done) for config, done in runs.items()}
    serial = rows["serial", 1]
    print(f"\nwhole pipeline, {serial['frames']} frames x 6 cameras (imports and worker "
          f"start-up included; median of {repeat} runs)")
    print(f"{'executor':<10} {'workers':>7} {'wall s':>7} {'frames/s':>8} {'register s':>10} "
          f"{'classify s':>10} {'vs serial':>9} {'vs 1 worker':>11} {'same clouds':>11}")
    for (executor, workers), row in rows.items():
        one = rows[executor, 1]
        print(f"{executor:<10} {workers:>7} {row['wall']:>7.1f} "
              f"{row['frames'] / row['wall']:>8.2f} {row['stages']['register']:>10.1f} "
              f"{row['stages']['classify']:>10.1f} {serial['wall'] / row['wall']:>8.2f}x "
              f"{one['wall'] / row['wall']:>10.2f}x "
              f"{'yes' if row['digest'] == serial['digest'] else 'NO':>11}")


def long_log_table(work: Path, gigabytes: float) -> None:
    log = work / "long.mcap"
    print(f"writing a {gigabytes:.1f} GB log ...", flush=True)
    write_long_log(log, target_bytes=int(gigabytes * 1e9))
    m = measure_ingest(log, work / "run-long")
    print(f"\ningest of a long log: {m['log_gb']:.2f} GB, {m['frames']} frames: peak RSS "
          f"{m['peak_rss_mb']:.0f} MB (goal <= 1024), {m['seconds']:.0f} s "
          f"({m['log_gb'] * 1000 / m['seconds']:.0f} MB/s)")
    log.unlink()
    shutil.rmtree(work / "run-long", ignore_errors=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, default=60, help="frames of the pipeline log")
    parser.add_argument("--long-gb", type=float, default=2.1, help="size of the long log")
    parser.add_argument("--repeat", type=int, default=3,
                        help="runs per executor; the table shows the median")
    parser.add_argument("--skip-long", action="store_true", help="skip the long-log ingest")
    parser.add_argument("--workdir", type=Path, help="where the logs and runs go")
    parser.add_argument("--long-frames", type=int, default=2000,
                        help="frames of the long replayed run (long logs)")
    parser.add_argument("--drift-frames", type=int, default=500,
                        help="frames of the simulated drift run (long logs)")
    parser.add_argument("--only-long-logs", action="store_true",
                        help="only the long-log tables (3.)")
    parser.add_argument("--pieces-only", action="store_true",
                        help="long logs: only the timed pieces, no whole runs")
    args = parser.parse_args()
    if args.only_long_logs or args.pieces_only:
        long_tables(args.workdir, args.long_frames, args.drift_frames, args.pieces_only)
        return
    work = Path(tempfile.mkdtemp(prefix="surgrecon-scale-", dir=args.workdir))
    try:
        if not args.skip_long:
            long_log_table(work, args.long_gb)
        pipeline_table(work, args.frames, args.repeat)
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
