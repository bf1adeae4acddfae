r"""Hour-long logs (issue 27): one register worker registering 100,000 frames, its memory.

    .venv/bin/python benchmarks/register_long.py [--steps 10000] [--frames 20] [--cameras 3]
        [--variant default] [--size 320x256] [--seed 7] [--block 500]
        [--workdir /tmp/surgrecon-register-long] [--tracemalloc DEPTH] [--top 15]

The 100,000-frame run of docs/frame-step-cost.md ("Long runs"): a 2-camera stereo
endoscope at 96x80 (28 template points). On a shared machine give it a core by raising its
scheduling autogroup once started (plain `nice` does not help against other sessions'
autogroups):

    .venv/bin/python benchmarks/register_long.py --steps 100000 --variant stereo \
        --cameras 2 --size 96x80 --block 2500 | tee benchmarks/results/register_long_100k.txt &
    echo -20 > /proc/<PID>/autogroup

An hour of a 30 Hz stereo endoscope at 320x256 (108,000 frames, ~0.15 s of CPU a frame):

    .venv/bin/python benchmarks/register_long.py --steps 108000 --variant stereo --cameras 2 \
        --block 6000

A small simulated log (`surgrecon simulate --variant V --frames F --cameras C`, ingested,
its template built; reused when present in WORKDIR) is registered by one process, on one
thread, as a register worker does it: `stages.register.register_frame(RUN, k, config)` for
k = 1, 2, ..., F-1, 1, 2, ... until `--steps` frames are done (each call reads its base
from the run folder, keeps its process caches, and writes RUN/registration/k.npz). Printed
per block of `--block` frames, at the block's end: CPU and wall seconds a frame; the
resident set (RSS), its peak (VmHWM) and its anonymous and file-backed parts (RssAnon,
RssFile; /proc/self/status); the C heap from glibc's mallinfo2 (all arenas: `heap MB`
obtained from the kernel, `in use` of it, `mmap MB` in blocks malloc mmapped; NaN without
glibc >= 2.33); Python's allocated blocks (sys.getallocatedblocks) and the objects the
garbage collector tracks; with --tracemalloc, the traced Python/numpy size (slow: ~20x the
CPU a frame). Then, after the first block, the frames after which the C heap (obtained +
mmapped, read after every frame, ~4 us) passed its high-water mark; with --tracemalloc the
allocation sites that grew most between the first block's end and the end
(`Snapshot.compare_to` by traceback); and the first and last blocks side by side (also
when interrupted by SIGINT or SIGTERM: the blocks done so far).

Reading it: memory that grows with the frames registered shows as RSS rising block by
block. If `in use` and the Python columns are flat while `heap MB` steps, the heap was
extended and kept (glibc keeps up to 64 MB of free heap top, `executors.heap.adapted_heap`)
for a transient or a block that found no free hole of its size: look for the allocation
behind it, not for a container that grows. Python-level growth shows in `py blocks`,
`gc objs` and `traced` (they also rise and fall with garbage waiting for the collector's
oldest generation, every ~15,000 frames here).

Sizes: the stereo variant's 2 cameras build a template from 96x80 up (21 points at 96x80,
35 at 128x96, 88 at 192x160, 337 at 320x256); at 80x64 build-template fails (5 verified
matches of the 15 needed to link the pair). The default variant's ring cameras 0 and 1 at
192x160 share too little of a view (1 verified match of 15): 2 cameras are --variant stereo.
"""

from __future__ import annotations

import argparse
import ctypes
import ctypes.util
import gc
import linecache
import signal
import subprocess
import sys
import time
import tracemalloc
from pathlib import Path
from typing import NamedTuple

import cv2
from long_log import surgrecon_executable
from threadpoolctl import threadpool_limits

from surgrecon_cli.config import Config
from surgrecon_cli.io.run.layout import RunLayout
from surgrecon_cli.stages.register import register_frame


def rss_mb(field: str = "VmRSS") -> float:
    """A size in /proc/self/status, MB: the resident set (VmRSS), its peak (VmHWM), its
    anonymous (RssAnon) or file-backed (RssFile) part."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(f"{field}:"):
            return int(line.split()[1]) / 1024
    return float("nan")


class _Mallinfo2(ctypes.Structure):
    """glibc's `struct mallinfo2` (malloc.h, glibc >= 2.33): byte counts over all arenas."""

    _fields_ = [(name, ctypes.c_size_t) for name in (
        "arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks",
        "fordblks", "keepcost")]


def _mallinfo2() -> ctypes._CFuncPtr | None:  # type: ignore[name-defined]
    """glibc's mallinfo2, or None (not glibc, or older than 2.33)."""
    try:
        function = ctypes.CDLL(ctypes.util.find_library("c")).mallinfo2
    except (OSError, AttributeError, TypeError):
        return None
    function.restype = _Mallinfo2
    function.argtypes = []
    return function


MALLINFO2 = _mallinfo2()


def c_heap_mb() -> tuple[float, float, float]:
    """The C heap (glibc malloc, all arenas), MB: obtained from the kernel by brk/arenas
    (`arena`), of it in use (`uordblks`), and mmapped blocks (`hblkhd`); NaN without
    glibc's mallinfo2."""
    if MALLINFO2 is None:
        return float("nan"), float("nan"), float("nan")
    info = MALLINFO2()
    return info.arena / 2**20, info.uordblks / 2**20, info.hblkhd / 2**20


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


class Row(NamedTuple):
    """One block's figures at its end."""

    frames: int  # frames done
    cpu: float  # CPU s/frame over the block
    wall: float  # wall s/frame over the block
    rss: float  # resident set, MB
    peak: float  # its peak (VmHWM), MB
    anon: float  # of the resident set: anonymous memory (RssAnon: heaps, mmapped blocks), MB
    file: float  # of it: file-backed pages (RssFile: the libraries' code and data), MB
    heap: float  # C heap obtained from the kernel (glibc mallinfo2 `arena`), MB
    in_use: float  # of it in use (`uordblks`), MB
    mmapped: float  # blocks mmapped by malloc (`hblkhd`), MB
    py_blocks: int  # Python's allocated memory blocks (sys.getallocatedblocks)
    gc_objects: int  # objects tracked by the garbage collector
    traced: float  # tracemalloc's traced size, MB (NaN when not tracing)


COLUMNS = (f"{'frames':>8} {'cpu s/frame':>11} {'wall s/frame':>12} {'RSS MB':>8} "
           f"{'peak MB':>8} {'anon MB':>8} {'file MB':>8} {'heap MB':>8} {'in use':>8} "
           f"{'mmap MB':>8} {'py blocks':>10} {'gc objs':>8} {'traced':>8} {'wall min':>8}")


def measure(frames: int, cpu: float, wall: float) -> Row:
    """The figures at a block's end (`Row`)."""
    traced = tracemalloc.get_traced_memory()[0] / 2**20 if tracemalloc.is_tracing() else \
        float("nan")
    return Row(frames, cpu, wall, rss_mb(), rss_mb("VmHWM"), rss_mb("RssAnon"),
               rss_mb("RssFile"), *c_heap_mb(), sys.getallocatedblocks(),
               len(gc.get_objects()), traced)


def print_row(row: Row, minutes: float) -> None:
    """A block's row as printed (COLUMNS)."""
    print(f"{row.frames:>8} {row.cpu:>11.4f} {row.wall:>12.4f} {row.rss:>8.1f} "
          f"{row.peak:>8.1f} {row.anon:>8.1f} {row.file:>8.1f} {row.heap:>8.1f} "
          f"{row.in_use:>8.1f} {row.mmapped:>8.1f} {row.py_blocks:>10} {row.gc_objects:>8} "
          f"{row.traced:>8.2f} {minutes:>8.1f}", flush=True)


def print_growth(start: tracemalloc.Snapshot, end: tracemalloc.Snapshot, top: int) -> None:
    """The `top` allocation sites (by traceback) whose traced size grew most between the
    two snapshots."""
    ignore = (tracemalloc.Filter(False, tracemalloc.__file__),
              tracemalloc.Filter(False, linecache.__file__))
    stats = end.filter_traces(ignore).compare_to(start.filter_traces(ignore), "traceback")
    print(f"\ntracemalloc: the {top} sites that grew most (traceback, innermost last)")
    for stat in stats[:top]:
        print(f"{stat.size_diff / 1024:+9.1f} KiB {stat.count_diff:+7d} blocks "
              f"(now {stat.size / 1024:.1f} KiB in {stat.count})")
        for line in stat.traceback.format()[-12:]:
            print(f"    {line}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=10_000)
    parser.add_argument("--frames", type=int, default=20)
    parser.add_argument("--cameras", type=int, default=3)
    parser.add_argument("--variant", default="default",
                        help="simulator preset (surgrecon simulate --variant)")
    parser.add_argument("--size", default="320x256")
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--block", type=int, default=500)
    parser.add_argument("--workdir", type=Path, default=Path("/tmp/surgrecon-register-long"))
    parser.add_argument("--tracemalloc", type=int, default=0, metavar="DEPTH",
                        help="trace Python allocations (tracebacks of DEPTH frames; slow): the "
                             "traced size per block, and the sites that grew most between the "
                             "end of the first block and the end")
    parser.add_argument("--top", type=int, default=15,
                        help="allocation sites printed with --tracemalloc")
    args = parser.parse_args()
    args.workdir.mkdir(parents=True, exist_ok=True)
    run = prepare(args.workdir, args.variant, args.frames, args.cameras, args.size, args.seed)
    cv2.setNumThreads(1)
    threadpool_limits(limits=1)
    config = Config()
    print(f"{run}: {args.steps} frames registered in one process (frames 1..{args.frames - 1}"
          f" replayed), blocks of {args.block}")
    print(COLUMNS, flush=True)
    if args.tracemalloc:
        tracemalloc.start(args.tracemalloc)
    rows: list[Row] = []
    # the frames after which the C heap (obtained + mmapped) exceeded its high-water mark:
    # (frames done, before: obtained, in use, mmapped MB, after: the same)
    growth: list[tuple[int, float, float, float, float, float, float]] = []
    top = c_heap_mb()
    first_snapshot: tracemalloc.Snapshot | None = None
    done, at, started = 0, 0, time.perf_counter()
    # SIGINT (also when started in the background) and SIGTERM stop at the next frame
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    try:
        while done < args.steps:
            cpu, wall = time.process_time(), time.perf_counter()
            count = min(args.block, args.steps - done)
            for i in range(done, done + count):
                out = register_frame(run, 1 + i % (args.frames - 1), config)
                if "failed" in out:
                    raise SystemExit(f"frame {out['frame']} failed: {out['failed']}")
                at = i + 1
                heap = c_heap_mb()
                if heap[0] + heap[2] > top[0] + top[2]:  # the C heap grew past its high
                    if rows:  # water mark (after the first block: past the warm-up)
                        growth.append((at, *top, *heap))
                    top = heap
            done += count
            rows.append(measure(done, (time.process_time() - cpu) / count,
                                (time.perf_counter() - wall) / count))
            if args.tracemalloc and first_snapshot is None:
                first_snapshot = tracemalloc.take_snapshot()
            print_row(rows[-1], (time.perf_counter() - started) / 60)
    except KeyboardInterrupt:
        print(f"\ninterrupted after {at} frames ({len(rows)} whole blocks, {done} frames), "
              f"{(time.perf_counter() - started) / 60:.1f} min; RSS {rss_mb():.1f} MB, peak "
              f"{rss_mb('VmHWM'):.1f} MB")
    if growth:
        print(f"\nthe C heap (obtained + mmapped) grew past its high-water mark after "
              f"{len(growth)} frames past the first block: frames done, MB obtained / in use / "
              f"mmapped before -> after")
        for at_frame, *mb in growth:
            print(f"{at_frame:>8}  {mb[0]:.2f} / {mb[1]:.2f} / {mb[2]:.2f} -> {mb[3]:.2f} / "
                  f"{mb[4]:.2f} / {mb[5]:.2f}")
    if first_snapshot is not None and len(rows) > 1:
        print_growth(first_snapshot, tracemalloc.take_snapshot(), args.top)
    if not rows:
        return
    first, last = rows[0], rows[-1]
    size = last.frames - (rows[-2].frames if len(rows) > 1 else 0)

    def span(name: str) -> str:
        values = [getattr(r, name) for r in rows]
        return f"{min(values):.1f}-{max(values):.1f}"
    print(f"\nstart (frames 1-{first.frames}): {first.cpu:.4f} s/frame CPU, RSS {first.rss:.1f} "
          f"MB, heap {first.heap:.1f} MB ({first.in_use:.1f} in use); end (frames "
          f"{last.frames - size + 1}-{last.frames}): {last.cpu:.4f} s/frame CPU, RSS "
          f"{last.rss:.1f} MB, heap {last.heap:.1f} MB ({last.in_use:.1f} in use); RSS change "
          f"{last.rss - first.rss:+.1f} MB over {last.frames - first.frames} frames; at the "
          f"blocks' ends RSS {span('rss')} MB (anon {span('anon')}, file {span('file')}), C heap "
          f"{span('heap')} MB ({span('in_use')} in use), Python blocks {span('py_blocks')}, gc "
          f"objects {span('gc_objects')}; peak RSS {last.peak:.1f} MB")


if __name__ == "__main__":
    main()
