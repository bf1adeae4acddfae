"""Per-frame cost of the register stage beside its floor on this machine (issues 15, 27).

    .venv/bin/python benchmarks/frame_cost.py [--cases 640x512:2 640x512:5 1280x1024:2]
        [--frames 6] [--seed 7] [--floor-levels 1] [--repeat 1]
        [--workdir /tmp/surgrecon-frame-cost] [--before SRC]

`--before SRC`: also measure the register stage of another surgrecon source tree (e.g. the
base commit: `git worktree add /tmp/base 1405d84`, then `--before /tmp/base`) on the same
run folders, in a child process with PYTHONPATH=SRC, printed as a "before" row above this
tree's "after" row, both against the same floor (this tree is measured in a child process
too, so that both start cold alike). `--repeat N`: each tree is measured N times,
interleaved, each tree first in every other turn, and the run with the smallest CPU total is
printed: on a shared machine, the least disturbed one.

For every case (size:cameras): `surgrecon simulate LOG --width W --height H --cameras C
--frames F --seed S`, `surgrecon ingest` and `surgrecon build-template` (reused when they
exist in WORKDIR), then on one thread (BLAS and OpenCV, as a worker):

- measured, in a child process per tree: `stages.register.register_frame` of frames
  1..F-1 in order (the register stage with 1 worker: the process caches warm as they are
  in a worker; "before" runs first, "after" then rewrites the frames), timed over frames
  2..F-1 (frame 1 pays the process's one-time set-up: imports, the registrar, the
  template's views), per frame: total,
  and its target part (tracking, reprojection check) and registration part as the frame
  step reports them; "rest" = total - both (loading inputs, decoding, writing).
- floor, in this process, the irreducible parts of one frame, timed on the same data:
  decoding the frame's C JPEG images; one pyramid build per image (cv2.buildOpticalFlowPyramid with
  derivatives, `--floor-levels` levels, default 1: the depth that tracks as well as 3,
  measured in issue 15); KLT forward and backward of the template points each camera
  saw, on prebuilt pyramids (calcOpticalFlowPyrLK on the images minus its own pyramid
  builds: OpenCV's Python binding does not accept a prebuilt pyramid); and, for the
  registration, one factorisation and one solve of the X-step system (graph and operators
  of core/registration) plus, per ADMM iteration the registration needed (counted by a
  `register` of the template to the frame's target), one solve and the mat-vecs with D,
  Dᵀ, B, Bᵀ.
- classify, after the register stage in the same child: `stages.classify.classify_one_frame`
  of frames 2..F-1 (frame 1 first, untimed), per frame, beside its floor: the spec's rule
  on the same registered positions, one unweighted rigid fit of every neighbourhood
  (`labels.rigid_fit_rms`). In `surgrecon run` the frames are classified on the register
  workers, so a frame's CPU is the register stage's plus this.

Times are process CPU seconds (robust to other load on the machine; wall time is printed
beside the total). Ratios = measured / floor, per part and in total; all figures are ours,
measured in one run, on a machine that may be loaded: compare ratios of one run.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial import cKDTree

from surgrecon_cli.config import Config
from surgrecon_cli.core.registration import graph, register
from surgrecon_cli.core.registration.admm import factorise
from surgrecon_cli.core.target.tracking import tracking_image
from surgrecon_cli.io.run.artefacts import read_observations, read_registration, read_template
from surgrecon_cli.io.run.ingest_store import load_ingested
from surgrecon_cli.io.run.layout import RunLayout

SURGRECON = [str(Path(sys.executable).with_name("surgrecon"))]


def cpu_seconds(fn: Callable[[], object], repeat: int = 3) -> float:
    """Smallest process CPU time (s) of `repeat` calls of fn (the least disturbed one)."""
    best = np.inf
    for _ in range(repeat):
        start = time.process_time()
        fn()
        best = min(best, time.process_time() - start)
    return float(best)


def prepare(workdir: Path, width: int, height: int, cameras: int, frames: int,
            seed: int) -> Path:
    """Simulated log, ingested, with its template: the run folder (reused if present)."""
    name = f"w{width}h{height}c{cameras}f{frames}s{seed}"
    log, run = workdir / f"{name}.mcap", workdir / name
    if not log.is_file():
        subprocess.run([*SURGRECON, "simulate", str(log), "--width", str(width), "--height",
                        str(height), "--cameras", str(cameras), "--frames", str(frames),
                        "--seed", str(seed), "-q"], check=True)
    if not RunLayout(run).template_ply.is_file():
        subprocess.run([*SURGRECON, "ingest", str(log), "-o", str(run), "--force", "-q"],
                       check=True)
        subprocess.run([*SURGRECON, "build-template", str(run), "-q"], check=True)
    return run


def measured(run: Path, frames: int, config: Config) -> dict[str, float]:
    """Per-frame CPU seconds of the register stage (1 worker) and its parts over frames
    2..frames-1 (frame 1 registered first, untimed: the process's warm-up); wall seconds."""
    from surgrecon_cli.stages.register import register_frame

    if frames < 3:
        raise SystemExit("--frames must be at least 3 (frame 1 warms up, 2.. are timed)")
    total = target = solve = 0.0
    wall = 0.0
    for k in range(1, frames):
        start, start_wall = time.process_time(), time.perf_counter()
        out = register_frame(run, k, config)
        if "failed" in out:
            raise SystemExit(f"{run}: frame {k} failed: {out['failed']}")
        if k == 1:
            continue
        total += time.process_time() - start
        wall += time.perf_counter() - start_wall
        target += out["seconds_target"]
        solve += out["seconds_register"]
    n = frames - 2
    wall_total = wall / n
    # The frame step reports wall seconds; scale them to CPU with the run's CPU/wall ratio.
    scale = (total / n) / wall_total
    parts = {"target": target / n * scale, "registration": solve / n * scale}
    from surgrecon_cli.stages.classify import classify_one_frame

    classify_one_frame(run, 1, config)  # the process's classify set-up, untimed
    start = time.process_time()
    for k in range(2, frames):
        classify_one_frame(run, k, config)
    return {"total": total / n, "wall": wall_total, **parts,
            "rest": total / n - parts["target"] - parts["registration"],
            "classify": (time.process_time() - start) / n}


def measured_by(code: Path | None, run: Path, frames: int) -> dict[str, float]:
    """`measured` in a child process on one thread, with PYTHONPATH=code (None: this tree)."""
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    env["PYTHONPATH"] = str((code or Path(__file__).resolve().parents[1]).absolute())
    out = subprocess.run([sys.executable, __file__, "--measure", str(run), "--frames",
                          str(frames)], env=env, check=True, capture_output=True, text=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def tracking_floor(run: Path, levels: int, window: int) -> dict[str, float]:
    """Per-frame CPU seconds of decoding, pyramids and KLT (frames 0 -> 1)."""
    layout = RunLayout(run)
    log = load_ingested(layout.ingest_dir)
    n = len(read_template(layout).points)
    obs = read_observations(layout, n)
    decode = pyramid = klt = 0.0
    win = (window, window)
    for c in range(len(log.cameras)):
        decode += cpu_seconds(lambda c=c: log.load_image(1, c))
        prev = tracking_image(log.load_image(0, c))
        cur = tracking_image(log.load_image(1, c))
        pts = obs.pixels[obs.camera == c].astype(np.float32).reshape(-1, 1, 2)
        with_deriv = cpu_seconds(lambda cur=cur: cv2.buildOpticalFlowPyramid(
            cur, win, levels, withDerivatives=True))
        plain = cpu_seconds(lambda cur=cur: cv2.buildOpticalFlowPyramid(
            cur, win, levels, withDerivatives=False))

        def both(prev=prev, cur=cur, pts=pts) -> None:
            params = dict(winSize=win, maxLevel=levels, flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
                          criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01))
            fwd, _, _ = cv2.calcOpticalFlowPyrLK(prev, cur, pts, pts.copy(), **params)
            cv2.calcOpticalFlowPyrLK(cur, prev, fwd, pts.copy(), **params)

        pyramid += with_deriv
        klt += max(cpu_seconds(both) - 2 * (with_deriv + plain), 0.0)
    return {"decode": decode, "pyramid": pyramid, "klt": klt}


def registration_floor(run: Path, frame: int, config: Config) -> dict[str, float]:
    """CPU seconds of one factorisation + solve, and of the ADMM iterations' solves and
    mat-vecs, for the registration of the template to `frame`'s target."""
    layout = RunLayout(run)
    template = read_template(layout)
    src = template.points
    reg = read_registration(layout, frame, len(src))
    has = np.isfinite(reg.target).all(1)
    cfg = config.registration
    iterations = [0]

    def count(_step: int, state: dict) -> None:
        iterations[0] += int(state.get("admm_iterations", 0))

    register(src, reg.target[has], template.rgb, template.rgb[has], cfg,
             target_ids=np.flatnonzero(has), weights=has.astype(float), callback=count)
    tree = cKDTree(src)
    norm = graph.normalisation(src, tree, cfg.max_nodes if cfg.max_nodes > 0 else len(src))
    q = norm.to_internal(src)
    per_point = cfg.max_nodes == 0 or len(src) <= cfg.max_nodes
    nodes = q if per_point else q[graph.sample_nodes(q, cfg.max_nodes)]
    node_tree = cKDTree(nodes)
    if per_point:
        idx, w = np.arange(len(q))[:, None], np.ones((len(q), 1))
    else:
        idx, w = graph.interpolation(q, nodes, node_tree, cfg.interp_neighbors)
    D = graph.data_operator(q, nodes, idx, w)[np.flatnonzero(has)]
    ea, eb = graph.neighbour_edges(nodes, node_tree, cfg.k_neighbors)
    B = graph.smoothness_operator(nodes, ea, eb)
    L = graph.linear_selector(len(nodes))
    mu2 = cfg.mu * len(src) / len(nodes)
    factor = factorise(D, B, L, cfg.beta, cfg.mu, mu2)
    X = np.random.default_rng(0).normal(size=(D.shape[1], 3))
    Dt, Bt = D.T.tocsr(), B.T.tocsr()
    setup = cpu_seconds(lambda: factorise(D, B, L, cfg.beta, cfg.mu, mu2).solve(X))
    per_iteration = cpu_seconds(lambda: (factor.solve(X), Dt @ (D @ X), Bt @ (B @ X)))
    return {"solve": setup, "admm": iterations[0] * per_iteration,
            "iterations": float(iterations[0])}


def classify_floor(run: Path, frames: int, config: Config) -> float:
    """Per-frame CPU seconds of the spec's rule on the registered positions of frames
    2..frames-1: one unweighted rigid fit of every template neighbourhood, the least work
    that asks whether each neighbourhood follows one rigid motion."""
    from surgrecon_cli.core.classify.labels import rigid_fit_rms
    from surgrecon_cli.stages.classify import template_and_neighbourhoods

    template, nb, _ = template_and_neighbourhoods(run, config)
    index, mask = nb.members()
    layout = RunLayout(run)
    positions = [read_registration(layout, k, len(template)).registered.astype(float)
                 for k in range(2, frames)]
    return sum(cpu_seconds(lambda p=p: rigid_fit_rms(template, p, index, mask))
               for p in positions) / len(positions)


def row(label: str, case: str, m: dict[str, float], t: dict[str, float],
        r: dict[str, float], c: float) -> str:
    """One table row: the measured parts of `m` beside the floors t (tracking), r (ADMM)
    and c (classify)."""
    f_target = t["decode"] + t["pyramid"] + t["klt"]
    f_reg = r["solve"] + r["admm"]
    floor = f_target + f_reg
    return (f"{case:>12} {label:>6} | {m['wall']:6.3f} {m['total']:6.3f} {floor:6.3f} "
            f"{m['total'] / floor:5.1f} | {m['target']:6.3f} {f_target:6.3f} "
            f"{m['target'] / f_target:5.1f} | {m['registration']:6.3f} {f_reg:6.3f} "
            f"{m['registration'] / f_reg:5.1f} {r['iterations']:5.0f} | "
            f"{m['rest']:5.3f} | {t['decode']:.3f} {t['pyramid']:.3f} {t['klt']:.3f} "
            f"{r['solve']:.3f} {r['admm']:.3f} | {m['classify']:6.3f} {c:6.3f} "
            f"{m['classify'] / c:5.1f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cases", nargs="+", default=["640x512:2", "640x512:5", "1280x1024:2"],
                        help="WIDTHxHEIGHT:CAMERAS")
    parser.add_argument("--frames", type=int, default=6,
                        help="frames of each simulated log (frames 2..F-1 are timed)")
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--floor-levels", type=int, default=1)
    parser.add_argument("--repeat", type=int, default=1,
                        help="measure each tree this many times (interleaved), keep the least "
                             "disturbed (smallest CPU total)")
    parser.add_argument("--workdir", type=Path, default=Path("/tmp/surgrecon-frame-cost"))
    parser.add_argument("--before", type=Path, help="surgrecon source tree measured as before")
    parser.add_argument("--measure", type=Path, help=argparse.SUPPRESS)  # child: one run
    args = parser.parse_args()
    config = Config()
    cv2.setNumThreads(1)
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1)
    if args.measure is not None:
        print(json.dumps(measured(args.measure, args.frames, config)))
        return
    args.workdir.mkdir(parents=True, exist_ok=True)
    head = (f"{'case':>12} {'code':>6} | {'wall s':>6} {'cpu s':>6} {'floor':>6} {'ratio':>5} | "
            f"{'target':>6} {'floor':>6} {'ratio':>5} | {'regist':>6} {'floor':>6} {'ratio':>5}"
            f" {'iters':>5} | {'rest':>5} | decode pyramid klt solve admm (floor, s) | "
            f"{'classify':>6} {'floor':>6} {'ratio':>5}")
    print(head)
    for case in args.cases:
        size, cameras = case.split(":")
        width, height = (int(v) for v in size.split("x"))
        try:
            run = prepare(args.workdir, width, height, int(cameras), args.frames, args.seed)
        except subprocess.CalledProcessError as exc:  # e.g. no template: say so, go on
            print(f"{case:>12} | not measured: {exc.cmd[1]} failed", flush=True)
            continue
        codes = ([("before", args.before)] if args.before else []) + [("after", None)]
        runs: dict[str, list[dict[str, float]]] = {label: [] for label, _ in codes}
        for turn in range(args.repeat):  # interleaved, so that both see the same load,
            for label, code in codes[::-1] if turn % 2 else codes:  # each first in turn
                runs[label].append(measured_by(code, run, args.frames))
        rows = [(label, min(runs[label], key=lambda m: m["total"])) for label, _ in codes]
        t = tracking_floor(run, args.floor_levels, config.target.klt_window_px)
        r = registration_floor(run, args.frames - 1, config)
        c = classify_floor(run, args.frames, config)
        for label, m in rows:
            print(row(label, case, m, t, r, c), flush=True)


if __name__ == "__main__":
    main()
