"""Hour-long logs (issue 27, item 4): one register worker registering >= 10,000 frames.

    .venv/bin/python benchmarks/register_long.py [--steps 10000] [--frames 20] [--cameras 3]
        [--variant default] [--size 320x256] [--seed 7] [--block 500]
        [--workdir /tmp/surgrecon-register-long]

An hour of a 30 Hz stereo endoscope (108,000 frames):

    .venv/bin/python benchmarks/register_long.py --steps 108000 --variant stereo --cameras 2 \
        --block 6000

A small simulated log (`surgrecon simulate --variant V --frames F --cameras C`, ingested,
its template built; reused when present in WORKDIR) is registered by one process, on one
thread, as a register worker does it: `stages.register.register_frame(RUN, k, config)` for
k = 1, 2, ..., F-1, 1, 2, ... until `--steps` frames are done (each call reads its base
from the run folder, keeps its process caches, and writes RUN/registration/k.npz). Printed
per block of `--block` frames: CPU seconds a frame and the process's resident set (RSS,
from /proc/self/status) at the block's end; then the first and last blocks side by side.
Memory that grows with the number of frames registered shows as RSS rising block by block.
"""

from __future__ import annotations

import argparse
import subprocess
import time
from pathlib import Path

import cv2
from long_log import surgrecon_executable
from threadpoolctl import threadpool_limits

from surgrecon_cli.config import Config
from surgrecon_cli.io.run.layout import RunLayout
from surgrecon_cli.stages.register import register_frame


def rss_mb() -> float:
    """This process's resident set (MB)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def prepare(workdir: Path, variant: str, frames: int, cameras: int, size: str,
            seed: int) -> Path:
    """The simulated, ingested run with its template (made once)."""
    width, height = size.split("x")
    name = f"{variant}-f{frames}c{cameras}-{size}-s{seed}"
    log, run = workdir / f"{name}.mcap", workdir / name
    exe = surgrecon_executable()
    if not log.is_file():
        subprocess.run([exe, "simulate", str(log), "--variant", variant, "--frames",
                        str(frames), "--cameras", str(cameras), "--width", width,
                        "--height", height, "--seed", str(seed), "-q"],
                       check=True, stdout=subprocess.DEVNULL)
    if not RunLayout(run).template_ply.is_file():
        subprocess.run([exe, "ingest", str(log), "-o", str(run), "--force", "-q"], check=True)
        subprocess.run([exe, "build-template", str(run), "-q"], check=True)
    return run


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=10_000)
    parser.add_argument("--frames", type=int, default=20)
    parser.add_argument("--cameras", type=int, default=3)
    parser.add_argument("--variant", default="default",
                        help="simulator preset (surgrecon simulate --variant)")
    parser.add_argument("--size", default="320x256")
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--block", type=int, default=500)
    parser.add_argument("--workdir", type=Path, default=Path("/tmp/surgrecon-register-long"))
    args = parser.parse_args()
    args.workdir.mkdir(parents=True, exist_ok=True)
    run = prepare(args.workdir, args.variant, args.frames, args.cameras, args.size, args.seed)
    cv2.setNumThreads(1)
    threadpool_limits(limits=1)
    config = Config()
    print(f"{run}: {args.steps} frames registered in one process (frames 1..{args.frames - 1}"
          f" replayed), blocks of {args.block}")
    print(f"{'frames':>8} {'cpu s/frame':>11} {'wall s/frame':>12} {'RSS MB':>8}", flush=True)
    rows = []
    done = 0
    while done < args.steps:
        cpu, wall = time.process_time(), time.perf_counter()
        count = min(args.block, args.steps - done)
        for i in range(done, done + count):
            out = register_frame(run, 1 + i % (args.frames - 1), config)
            if "failed" in out:
                raise SystemExit(f"frame {out['frame']} failed: {out['failed']}")
        done += count
        rows.append((done, (time.process_time() - cpu) / count,
                     (time.perf_counter() - wall) / count, rss_mb()))
        print(f"{rows[-1][0]:>8} {rows[-1][1]:>11.4f} {rows[-1][2]:>12.4f} "
              f"{rows[-1][3]:>8.1f}", flush=True)
    first, last = rows[0], rows[-1]
    print(f"\nstart (frames 1-{first[0]}): {first[1]:.4f} s/frame CPU, RSS {first[3]:.1f} MB; "
          f"end (frames {last[0] - args.block + 1}-{last[0]}): {last[1]:.4f} s/frame CPU, "
          f"RSS {last[3]:.1f} MB; RSS change {last[3] - first[3]:+.1f} MB over "
          f"{last[0] - first[0]} frames")


if __name__ == "__main__":
    main()
