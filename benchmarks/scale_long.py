"""Long logs (issue 15, item 4), the parts of `benchmarks/scale.py` that grow with the log:

1. Timed pieces, per frame, at T = 20, 2,000 and 100,000 frames (synthetic run-folder
   files, in this process): ingest store access (the old way: frames.npz loaded again for
   every frame; now: loaded once per process, then a cached look-up), the progress record
   (old: run.json rewritten with the list of finished frames and fsynced; now: one line
   appended, run.json counts at most once a second), classify's label writing and the
   report's per-frame accumulation (time a frame; memory held per frame, by tracemalloc).
   Access and progress are timed at 100k frames too; memory at 100k is extrapolated:
   the peak at 2,000 frames + the bytes held a frame (slope from 1,000 to 2,000) x 98k.
2. Whole runs: `surgrecon run` (serial, 1 worker) on replayed logs (benchmarks/long_log.py:
   8 rendered frames replayed, small images) of 20 and `--long-frames` frames, in a child
   process: register / classify / report seconds per frame and the whole run's peak RSS.
3. Drift: `surgrecon run` on a simulated log of `--drift-frames` frames with ground truth;
   median registration error (mm, against the simulator's truth) of the last 20 frames
   against the first 20.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np
from long_log import _LAUNCHER, surgrecon_executable, write_long_log

from surgrecon_cli.core.classify.labels import SHIFTING, STATIC
from surgrecon_cli.io.run.artefacts import FrameRegistration
from surgrecon_cli.io.run.atomic import write_json, write_npz
from surgrecon_cli.io.run.folder import FrameProgress, RunFolder
from surgrecon_cli.io.run.ingest_store import _load_ingested, load_ingested
from surgrecon_cli.io.run.layout import RunLayout
from surgrecon_cli.report.frames import FrameAccumulator
from surgrecon_cli.sim.random_frames import write_random_classified
from surgrecon_cli.stages.classify import write_labels_streaming

POINTS = 2200  # template points (the sample's order of magnitude)
CAMERAS = 6
LENGTHS = (20, 2000)
EXTRAPOLATE = 100_000


def _ingest_folder(root: Path, n_frames: int) -> Path:
    """A synthetic RUN/ingest of n_frames frames (frames.npz and cameras.json)."""
    ingest = root / "ingest"
    ingest.mkdir(parents=True)
    model = {"K": [[500, 0, 160], [0, 500, 128], [0, 0, 1]], "dist": [0] * 5, "width": 320,
             "height": 256, "model": "plumb_bob"}
    write_json(RunLayout.ingest_cameras(ingest), {"cameras": [str(c) for c in range(CAMERAS)],
                                                  "models": [model] * CAMERAS, "report": {}})
    paths = np.array([[RunLayout.image_relpath(c, k, "jpg") for c in range(CAMERAS)]
                      for k in range(n_frames)])
    write_npz(RunLayout.ingest_frames(ingest), stamps_ns=np.arange(n_frames, dtype=np.int64),
              image_stamps_ns=np.zeros((n_frames, CAMERAS), np.int64),
              poses=np.tile(np.eye(4), (n_frames, CAMERAS, 1, 1)),
              usable=np.ones((n_frames, CAMERAS), bool),
              tool_poses=np.tile(np.eye(4), (n_frames, 1, 1)), joint_names=np.array(["j"]),
              joint_positions=np.zeros((n_frames, 1)), image_paths=paths)
    return ingest


def _per_call(fn, repeat: int) -> float:
    start = time.perf_counter()
    for _ in range(repeat):
        fn()
    return (time.perf_counter() - start) / repeat


def ingest_access(work: Path, n_frames: int) -> dict[str, float]:
    """Seconds a frame to get a frame's ingest data: old (reload all), now (cached look-up),
    and the one load per process now."""
    ingest = _ingest_folder(work / f"ingest{n_frames}", n_frames)
    stamp = (os.stat(ingest),)  # any key not used before: a cold load

    def cold() -> None:
        _load_ingested.__wrapped__(str(ingest), stamp).usable_poses(n_frames - 1)

    once = _per_call(cold, 3 if n_frames > 10_000 else 10)
    load_ingested(ingest)
    warm = _per_call(lambda: load_ingested(ingest).usable_poses(n_frames - 1), 200)
    return {"old": once, "now": warm, "load_once": once}


def progress_write(work: Path, n_frames: int) -> dict[str, float]:
    """Seconds a frame to record a finished frame at frame T: old (run.json with the list
    of T frames, fsynced), now (one appended line; run.json counts at most once a second,
    so their cost a frame is that write over the frames a second)."""
    run = RunFolder(work / f"progress{n_frames}")
    run.write({"stages": {}})
    old = _per_call(lambda: run.mark_stage("register", "running",
                                           frames_done=list(range(1, n_frames))), 5)
    progress = FrameProgress(work / f"progress{n_frames}" / "progress.jsonl")
    progress.restart({k: "" for k in range(1, n_frames)})
    counts = _per_call(lambda: run.mark_stage("register", "running", frames_done=n_frames), 5)
    now = _per_call(lambda: progress.append(n_frames), 200)
    return {"old": old, "now": now, "run_json_counts": counts}


def _traced(fn) -> tuple[float, int]:
    """Wall seconds of fn() and its peak traced allocation (bytes)."""
    tracemalloc.start()
    try:
        start = time.perf_counter()
        fn()
        return time.perf_counter() - start, tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def classify_labels(work: Path, n_frames: int) -> dict[str, float]:
    """classify's label writing (hysteresis passes, labels.npz by rows): seconds a frame
    and peak bytes held."""
    layout = RunLayout(work / f"classify{n_frames}")
    write_random_classified(layout, n_frames, POINTS, np.random.default_rng(1))
    seconds, peak = _traced(lambda: write_labels_streaming(layout, n_frames, POINTS, 3))
    return {"seconds": seconds / n_frames, "peak": peak}


def report_accumulation(n_frames: int) -> dict[str, float]:
    """The report's per-frame reduction (report/frames.py) of synthetic registered frames:
    seconds a frame and peak bytes held."""
    rng = np.random.default_rng(2)
    template = rng.random((POINTS, 3))
    n = POINTS
    reg = FrameRegistration(
        transforms=np.tile(np.eye(3, 4, dtype=np.float32), (n, 1, 1)),
        registered=(template + 1e-3 * rng.standard_normal((n, 3))).astype(np.float32),
        target=template.astype(np.float32), status=np.zeros(n, np.uint8),
        views=np.full(n, 2, np.uint8), residual=np.full(n, 1e-4, np.float32),
        sigma=np.full(n, 1e-4, np.float32), target_sigma=np.full(n, 1e-4, np.float32),
        target_covariance=np.zeros((n, 3, 3), np.float32),
        target_pose_covariance=np.zeros((n, 3, 3), np.float32),
        support_mm=np.ones(n, np.float32), pixels=np.zeros((n, CAMERAS, 2), np.float32),
        tracking_px=0.1, base=0, converged=True, failed=False, error="", seconds_target=0.1,
        seconds_register=0.1, new_points=0, contact_points=0)
    labels = rng.choice([STATIC, SHIFTING], n).astype(np.uint8)

    def run() -> None:
        acc = FrameAccumulator(template, n_frames, classified=True)
        for k in range(n_frames):
            acc.add(k, reg if k else None, labels)
        acc.result()

    seconds, peak = _traced(run)
    return {"seconds": seconds / n_frames, "peak": peak}


def pieces_table(work: Path) -> None:
    """Per-frame cost and memory of the pieces that grew with the log, at 20 and 2,000
    frames, extrapolated to 100k."""
    rows = []
    for name, fn in (("ingest store access", lambda t: ingest_access(work, t)),
                     ("progress write", lambda t: progress_write(work, t))):
        at = {t: fn(t) for t in (*LENGTHS, EXTRAPOLATE)}
        rows.append((f"{name}, old", *(at[t]["old"] * 1e3 for t in (*LENGTHS, EXTRAPOLATE)),
                     "measured"))
        rows.append((f"{name}, now", *(at[t]["now"] * 1e3 for t in (*LENGTHS, EXTRAPOLATE)),
                     "measured"))
        extra, what = (("load_once", "  (now: the one load a process)")
                       if "load_once" in at[LENGTHS[0]]
                       else ("run_json_counts", "  (now: run.json counts, at most 1 Hz)"))
        rows.append((what,
                     *(at[t][extra] * 1e3 for t in (*LENGTHS, EXTRAPOLATE)), "measured"))
    print("\nper-frame cost of the pieces that used to grow with the log (ms a frame; "
          f"{POINTS} points, {CAMERAS} cameras)")
    print(f"{'piece':<46} {'T=20':>9} {'T=2000':>9} {'T=100k':>9}")
    for name, a, b, c, how in rows:
        print(f"{name:<46} {a:>9.3f} {b:>9.3f} {c:>9.3f}  {how}")
    mem = {}
    slope_from = 1000  # both past report/frames.SAMPLED_FRAMES: the slope is what grows
    for name, fn in (("classify label writing", lambda t: classify_labels(work, t)),
                     ("report per-frame accumulation", report_accumulation)):
        mem[name] = {t: fn(t) for t in (*LENGTHS, slope_from)}
    print(f"\nmemory held and time a frame (tracemalloc peak; {POINTS} points); bytes a frame "
          f"from {slope_from} to {LENGTHS[1]} frames; 100k extrapolated: "
          f"peak({LENGTHS[1]}) + (100k - {LENGTHS[1]}) x bytes a frame")
    print(f"{'piece':<32} {'ms/frame 20':>11} {'ms/frame 2000':>13} {'peak MB 20':>10} "
          f"{'peak MB 2000':>12} {'bytes/frame':>11} {'peak MB 100k':>12}")
    for name, at in mem.items():
        a, b = at[LENGTHS[0]], at[LENGTHS[1]]
        per = (b["peak"] - at[slope_from]["peak"]) / (LENGTHS[1] - slope_from)
        print(f"{name:<32} {a['seconds'] * 1e3:>11.3f} {b['seconds'] * 1e3:>13.3f} "
              f"{a['peak'] / 1e6:>10.2f} {b['peak'] / 1e6:>12.2f} {per:>11.0f} "
              f"{(b['peak'] + per * (EXTRAPOLATE - LENGTHS[1])) / 1e6:>12.1f}")


def measured_run(log: Path, run_dir: Path, extra: tuple[str, ...] = ()) -> dict:
    """`surgrecon run LOG -o RUN -q` (serial) in a child process: wall s, peak RSS MiB and
    run.json."""
    shutil.rmtree(run_dir, ignore_errors=True)
    cmd = [surgrecon_executable(), "run", str(log), "-o", str(run_dir), "-q",
           "--executor", "serial", *extra]
    done = subprocess.run([sys.executable, "-S", "-c", _LAUNCHER, *cmd], capture_output=True,
                          text=True, check=False)
    result = json.loads(done.stdout.strip().splitlines()[-1])
    if result["rc"] != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed: {done.stderr[-2000:]}")
    return {"wall": result["seconds"], "rss_mb": result["maxrss_kib"] / 1024,
            "run": json.loads((run_dir / "run.json").read_text())}


def runs_table(work: Path, long_frames: int) -> None:
    """Whole runs on replayed logs of 20 and `long_frames` frames (4 cameras, 320x256)."""
    out = {}
    for n in (LENGTHS[0], long_frames):
        log = work / f"replay{n}.mcap"
        print(f"writing a replayed log of {n} frames (4 cameras, 320x256) ...", flush=True)
        write_long_log(log, minutes=(n - 0.5) / 10 / 60, target_bytes=0, frame_rate=10.0,
                       cameras=4, width=320, height=256)
        print(f"running it ({n} frames) ...", flush=True)
        out[n] = measured_run(log, work / f"run-replay{n}")
    print("\nwhole run, serial, 4 cameras 320x256 (replayed log; per frame = stage s / "
          "frames)")
    print(f"{'frames':>7} {'wall s':>8} {'register s/fr':>13} {'classify s/fr':>13} "
          f"{'measure s/fr':>12} {'report s/fr':>11} {'peak RSS MB':>11}")
    for m in out.values():
        sec = m["run"]["pipeline"]["seconds"]
        frames = m["run"]["ingest"]["frames"]
        print(f"{frames:>7} {m['wall']:>8.1f} {sec['register'] / frames:>13.4f} "
              f"{sec['classify'] / frames:>13.4f} {sec['measure'] / frames:>12.4f} "
              f"{sec['report'] / frames:>11.4f} {m['rss_mb']:>11.0f}")
    a, b = out[LENGTHS[0]], out[long_frames]
    ratio = (b["run"]["pipeline"]["seconds"]["register"] / b["run"]["ingest"]["frames"]) / (
        a["run"]["pipeline"]["seconds"]["register"] / a["run"]["ingest"]["frames"])
    print(f"register per frame {long_frames} vs 20 frames: {ratio:.2f}x; peak RSS "
          f"{b['rss_mb'] / a['rss_mb']:.2f}x (goal within 15 %); {long_frames}-frame run peak "
          f"RSS {b['rss_mb']:.0f} MB (goal <= 1536)")


def drift_table(work: Path, frames: int) -> None:
    """Median registration error of the last 20 frames against the first 20 (simulated
    log, 4 cameras 320x256, its ground truth)."""
    log = work / f"drift{frames}.mcap"
    print(f"simulating {frames} frames (4 cameras, 320x256) ...", flush=True)
    subprocess.run([surgrecon_executable(), "simulate", str(log), "--frames", str(frames),
                    "--cameras", "4", "--width", "320", "--height", "256", "-q"], check=True,
                   stdout=subprocess.DEVNULL)
    m = measured_run(log, work / "run-drift")
    ev = json.loads((work / "run-drift" / "metrics" / "evaluation.json").read_text())
    per = {r["frame"]: r.get("median_mm") for r in ev["registration"]["per_frame"]}
    first = [per[k] for k in range(1, 21) if per.get(k) is not None]
    last = [per[k] for k in range(frames - 20, frames) if per.get(k) is not None]
    a, b = float(np.median(first)), float(np.median(last))
    print(f"\ndrift, {frames} frames: registration error (median mm against the truth) "
          f"frames 1-20 {a:.3f}, frames {frames - 20}-{frames - 1} {b:.3f}: "
          f"{b / a:.2f}x (goal <= 1.20x); run {m['wall']:.0f} s, peak RSS {m['rss_mb']:.0f} MB")


def long_tables(workdir: Path | None, long_frames: int, drift_frames: int,
                pieces_only: bool) -> None:
    work = Path(tempfile.mkdtemp(prefix="surgrecon-long-", dir=workdir))
    try:
        pieces_table(work)
        if not pieces_only:
            runs_table(work, long_frames)
            drift_table(work, drift_frames)
    finally:
        shutil.rmtree(work, ignore_errors=True)
