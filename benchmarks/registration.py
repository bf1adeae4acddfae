"""Registration benchmark: surgrecon vs pycpd / probreg (CPD, BCPD) on synthetic dome pairs.

    .venv/bin/pip install -e .[bench]        # pycpd, probreg (benchmark only)
    .venv/bin/python benchmarks/registration.py [--sizes 2000 5000 10000 50000] [--cap 60]

Pairs: a bumpy dome ~50 mm across (metres), a breathing-like smooth shift plus a 5 mm Gaussian
indentation, 0.2 mm noise; variants with 20 % gross outliers (extra target points 1-5 mm off
the surface), with colour (texture), and with 30 % of the target removed (partial overlap).
The target holds the same material points as the source (shuffled), so the error of a
registered point is its distance to its true moved position. Every method runs on the same
pairs, each in a forked worker process (terminated and reported "capped" past the time cap);
wall and process-CPU time and the worker's peak RSS (which includes the parent's ~imports
and data, inherited by fork) are reported. The peers see geometry only. All numbers are ours.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import queue as queue_mod
import resource
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from surgrecon_cli.sim.pairs import MM, dome, texture, warp


# ----------------------------------------------------------------------------- data
@dataclass(frozen=True)
class Pair:
    source: np.ndarray
    target: np.ndarray
    source_rgb: np.ndarray | None
    target_rgb: np.ndarray | None
    truth: np.ndarray  # (N, 3) true moved source points


def make_pair(n: int, *, outliers: float = 0.0, colour: bool = False, partial: float = 0.0,
              noise_mm: float = 0.2, seed: int = 0) -> Pair:
    rng = np.random.default_rng(seed)
    src = dome(n, rng)
    truth = warp(src)
    tgt = truth + rng.normal(0, noise_mm * MM, truth.shape)
    rgb = texture(src)
    trgb = np.clip(rgb + rng.normal(0, 0.02, rgb.shape), 0, 1)
    if partial > 0:  # remove a contiguous side of the target
        keep = tgt[:, 0] > np.quantile(tgt[:, 0], partial)
        tgt, trgb = tgt[keep], trgb[keep]
    if outliers > 0:
        k = round(outliers * len(tgt))
        base = tgt[rng.integers(0, len(tgt), k)]
        d = rng.normal(size=(k, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        tgt = np.r_[tgt, base + d * rng.uniform(1, 5, (k, 1)) * MM]
        trgb = np.r_[trgb, rng.uniform(0, 1, (k, 3))]
    order = rng.permutation(len(tgt))
    return Pair(src, tgt[order], rgb if colour else None, trgb[order] if colour else None, truth)


# ----------------------------------------------------------------------------- methods
def run_ours(pair: Pair, **overrides: object) -> np.ndarray:
    from surgrecon_cli.config import RegistrationConfig
    from surgrecon_cli.registration import register

    cfg = replace(RegistrationConfig(), **overrides)
    return register(pair.source, pair.target, pair.source_rgb, pair.target_rgb, cfg).registered


def run_pycpd(pair: Pair) -> np.ndarray:
    from pycpd import DeformableRegistration

    # pycpd registers Y (moving) onto X (fixed); its default w=0 assumes no outliers
    reg = DeformableRegistration(X=pair.target / MM, Y=pair.source / MM, alpha=2.0, beta=2.0,
                                 w=0.1, max_iterations=100, tolerance=1e-5)
    ty, _ = reg.register()
    return np.asarray(ty) * MM


def run_probreg(pair: Pair, method: str) -> np.ndarray:
    from probreg import bcpd, cpd

    src, tgt = pair.source / MM, pair.target / MM
    if method == "cpd":
        res = cpd.registration_cpd(src, tgt, tf_type_name="nonrigid", w=0.1, maxiter=100,
                                   tol=1e-5, beta=2.0, lmd=2.0)
        return np.asarray(res.transformation.transform(src)) * MM
    tf = bcpd.registration_bcpd(src, tgt, w=0.1, maxiter=100, tol=1e-5)
    return np.asarray(tf.transform(src)) * MM


def timed(fn: Callable[[], np.ndarray], cap: float) -> tuple[np.ndarray | None, float, str]:
    """Run fn in a forked worker process; (result, seconds, status: 'ok'/'capped'/error).

    A run past `cap` seconds is terminated, so a slow peer cannot eat the CPU of later runs.
    """
    ctx = mp.get_context("fork")
    queue = ctx.Queue()

    def work() -> None:
        t0 = time.perf_counter()
        try:
            res = fn()
            queue.put(("ok", res, time.perf_counter() - t0))
        except Exception as exc:
            queue.put((type(exc).__name__, None, time.perf_counter() - t0))

    proc = ctx.Process(target=work, daemon=True)
    proc.start()
    try:
        status, res, secs = queue.get(timeout=cap)
    except queue_mod.Empty:
        proc.terminate()
        proc.join()
        return None, cap, "capped"
    proc.join()
    return res, secs, status


def measured(fn: Callable[[], np.ndarray]) -> tuple[np.ndarray, float, float, float]:
    """(result, wall s, process CPU s, peak RSS MB of this process); call in a fresh worker."""
    t0, c0 = time.perf_counter(), time.process_time()
    res = fn()
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    return res, wall, cpu, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def errors_mm(reg: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    e = np.linalg.norm(reg - truth, axis=1) / MM
    return float(np.median(e)), float(np.percentile(e, 95))


# ----------------------------------------------------------------------------- main
CASES = {
    "clean": {},
    "outliers20": {"outliers": 0.2},
    "colour+outliers20": {"outliers": 0.2, "colour": True},
    "partial30": {"partial": 0.3},
    "colour+partial30": {"partial": 0.3, "colour": True},
}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[2000, 5000, 10000, 50000])
    ap.add_argument("--cases", nargs="+", default=list(CASES), choices=list(CASES))
    ap.add_argument("--peers", nargs="*", default=["pycpd", "cpd", "bcpd"])
    ap.add_argument("--peer-max-points", type=int, default=5000,
                    help="peers are not run above this size (reported capped)")
    ap.add_argument("--peer-cases", nargs="+", default=["clean", "outliers20", "partial30"],
                    choices=list(CASES), help="cases the peers run (geometry only)")
    ap.add_argument("--cap", type=float, default=60.0, help="time cap per peer run (s)")
    ap.add_argument("--mu-study", action="store_true", help="also time growing mu (x2/iter)")
    args = ap.parse_args(argv)

    peers: dict[str, Callable[[Pair], np.ndarray]] = {
        "pycpd": run_pycpd,
        "cpd": lambda p: run_probreg(p, "cpd"),
        "bcpd": lambda p: run_probreg(p, "bcpd"),
    }
    print("| size | case | method | median mm | p95 mm | wall s | cpu s | ours/peer wall "
          "| peak RSS MB |")
    print("| ---: | --- | --- | ---: | ---: | ---: | ---: | ---: | ---: |")
    sys.stdout.flush()
    for n in args.sizes:
        for case in args.cases:
            pair = make_pair(n, **CASES[case])  # type: ignore[arg-type]
            run_ours(make_pair(500, **CASES[case]))  # warm-up: imports, caches
            variants = [("ours", {})]
            if args.mu_study:
                variants.append(("ours, mu x2/iter", {"mu_growth": 2.0, "mu": 0.25}))
            t_ours = np.nan
            for label, overrides in variants:
                out, _, status = timed(
                    lambda p=pair, o=overrides: measured(lambda: run_ours(p, **o)), 600.0)
                if out is None:
                    print(f"| {n} | {case} | {label} | {status} | | | | | |")
                    continue
                reg, wall, cpu, rss = out
                t_ours = wall if label == "ours" else t_ours
                med, p95 = errors_mm(reg, pair.truth)
                print(f"| {n} | {case} | {label} | {med:.3f} | {p95:.3f} | {wall:.3f} | {cpu:.3f} "
                      f"| | {rss:.0f} |")
            for name in args.peers if case in args.peer_cases else ():
                if n > args.peer_max_points:
                    print(f"| {n} | {case} | {name} | not run (size > {args.peer_max_points}) "
                          "| | | | | |")
                    continue
                out, secs, status = timed(
                    lambda f=peers[name], p=pair: measured(lambda: f(p)), args.cap)
                if status == "capped":
                    print(f"| {n} | {case} | {name} | capped | | > {args.cap:.0f} | | "
                          f"< {t_ours / args.cap:.4f} | |")
                    continue
                if out is None:
                    print(f"| {n} | {case} | {name} | failed: {status} | | {secs:.1f} | | | |")
                    continue
                res, wall, cpu, rss = out
                med, p95 = errors_mm(res, pair.truth)
                print(f"| {n} | {case} | {name} | {med:.3f} | {p95:.3f} | {wall:.2f} | {cpu:.2f} "
                      f"| {t_ours / wall:.4f} | {rss:.0f} |")
            sys.stdout.flush()
    return 0


if __name__ == "__main__":
    sys.exit(main())
