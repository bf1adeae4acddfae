"""Registration benchmark (issue 14): ours beside BCPD and Fast_RNRR on seeded pair families.

    export PYTHONPATH=$PWD
    nice -n 10 .venv/bin/python benchmarks/registration.py [--quick] [--families F ...]
        [--seeds 100 101 ...] [--sizes N ...] [--bcpd PATH] [--fast-rnrr PATH]
        [--set key=value ...] [--variant key=value[,key=value] ...] [--peers pycpd ...]

Pairs: sim/pairs_catalog.py (coloured tissue with independent resampling, strays and a cut
side; colourless scanned blob / torus / body / limb, partial and noisy scans; a 90 degree +
0.8 scale rotation). Default seeds are the acceptance seeds 100-104 (tuning seeds are 0-4).
Per family, size and seed it prints, for doing nothing (the source as it is), ours and each
peer: median / p95 error (mm) against the true moved source, the median error along the true
surface normal and along the surface (normals: local PCA of the truth), the median as % of
the bounding-box diagonal, the Spearman rank correlation between the per-point `residuals`
and the true error (ours only), the CPU time and its ratio to ours on the same pair.
Then a summary per family (means over seeds) and the goals of issue 14, met or not.

Ours: `surgrecon_cli.registration.register(src, tgt, src_rgb, tgt_rgb, config)` in process,
defaults plus `--set` overrides of RegistrationConfig, timed (CPU time) after one warm-up
call; that is `register_pair`, what `register-pair` runs (`--before` adds the shared
`register` that the frame pipeline runs, without the colour-stray decision). Families
stray_colour / stray_colour_partial:
tuned on seeds 0-4, accepted on 100-104; their goals and colour decisions are printed last.
Peers (binaries from --bcpd / SURGRECON_BCPD and --fast-rnrr / SURGRECON_FAST_RNRR; "not
available" without them) run as subprocesses, see benchmarks/registration_peers.py for their
settings; their CPU time includes their process start-up and file I/O (nothing subtracted).
Everything runs on one thread (OMP/OPENBLAS/MKL_NUM_THREADS=1 unless set otherwise).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # before numpy is imported: ours on one thread too

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections import defaultdict  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from registration_metrics import Errors, errors, pca_normals, worst_region_excess  # noqa: E402
from registration_peers import (  # noqa: E402
    PeerError,
    run_bcpd,
    run_fast_rnrr,
    run_python_peer,
)
from registration_stray import estimate_ratio, stray_goals  # noqa: E402

from surgrecon_cli.config import RegistrationConfig  # noqa: E402
from surgrecon_cli.registration import register, register_pair  # noqa: E402
from surgrecon_cli.sim.pairs import Pair  # noqa: E402
from surgrecon_cli.sim.pairs_catalog import ACCEPTANCE_SEEDS, FAMILIES, make_pair  # noqa: E402

SHAPE_FAMILIES = [f for f, fam in FAMILIES.items() if not fam.coloured and f != "rotation"]
QUICK_FAMILIES = ["tissue", "tissue_partial", "blob", "body", "rotation"]


def parse_overrides(items: list[str]) -> dict[str, object]:
    """key=value strings -> RegistrationConfig field values, typed like the defaults."""
    defaults = RegistrationConfig()
    names = {f.name for f in dataclasses.fields(RegistrationConfig)}
    out: dict[str, object] = {}
    for item in items:
        key, _, raw = item.partition("=")
        if key not in names:
            raise SystemExit(f"--set: RegistrationConfig has no key {key!r}")
        kind = type(getattr(defaults, key))
        out[key] = raw.lower() in ("1", "true", "yes") if kind is bool else kind(raw)
    return out


def run_ours(pair: Pair, cfg: RegistrationConfig, entry=register_pair):
    """(registered (N, 3) m, residuals (N,) m, wall s, the result) of one in-process call of
    `entry` (register_pair: what `register-pair` runs; register: the shared frame call)."""
    t0 = time.process_time()  # CPU time: the machine is shared
    res = entry(pair.source, pair.target, pair.source_rgb, pair.target_rgb, cfg)
    return res.registered, res.residuals, time.process_time() - t0, res


def fmt_row(cells: list[str]) -> str:
    return "| " + " | ".join(cells) + " |"


def row(family: str, n: int, seed: int, method: str, e: Errors | None, wall: float | None,
        ours_wall: float | None, note: str = "") -> str:
    if e is None:
        return fmt_row([family, str(n), str(seed), method, note] + [""] * 7)
    ratio = "" if wall is None or not ours_wall else f"{wall / ours_wall:.1f}"
    rho = "" if np.isnan(e.spearman) else f"{e.spearman:.2f}"
    return fmt_row([family, str(n), str(seed), method, f"{e.median:.3f}", f"{e.p95:.3f}",
                    f"{e.normal:.3f}", f"{e.tangential:.3f}", f"{e.percent_diag:.2f}", rho,
                    "" if wall is None else f"{wall:.2f}", ratio])


HEADER = ["family", "n", "seed", "method", "median mm", "p95 mm", "normal mm",
          "tangential mm", "% diag", "Spearman", "cpu s", "time / ours"]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--families", nargs="+", choices=list(FAMILIES), default=None)
    ap.add_argument("--seeds", type=int, nargs="+", default=list(ACCEPTANCE_SEEDS))
    ap.add_argument("--sizes", type=int, nargs="+", default=None,
                    help="source sizes for every family (default: each family's own)")
    ap.add_argument("--quick", action="store_true",
                    help=f"first seed only, families {' '.join(QUICK_FAMILIES)}, sizes <= 5000")
    ap.add_argument("--bcpd", default=os.environ.get("SURGRECON_BCPD"))
    ap.add_argument("--fast-rnrr", default=os.environ.get("SURGRECON_FAST_RNRR"))
    ap.add_argument("--bcpd-colour-mm", type=float, default=20.0,
                    help="BCPD colour channels: mm per RGB unit (chosen on tuning seed 0)")
    ap.add_argument("--peers", nargs="*", default=[],
                    choices=["pycpd", "probreg-cpd", "probreg-bcpd"],
                    help="optional Python peers (the `bench` extra)")
    ap.add_argument("--set", dest="overrides", action="append", default=[],
                    metavar="KEY=VALUE", help="RegistrationConfig override for ours")
    ap.add_argument("--variant", action="append", default=[], metavar="K=V[,K=V]",
                    help="an extra row of ours with these overrides on top of --set")
    ap.add_argument("--before", action="store_true",
                    help="also a row 'before': the shared register() (what the frame pipeline "
                    "runs), without register_pair's colour-stray decision")
    ap.add_argument("--cap", type=float, default=300.0, help="time cap per peer run (s)")
    args = ap.parse_args(argv)

    families = args.families or (QUICK_FAMILIES if args.quick else list(FAMILIES))
    seeds = args.seeds[:1] if args.quick else args.seeds
    base = parse_overrides(args.overrides)
    configs = {"ours": RegistrationConfig(**base)}  # type: ignore[arg-type]
    for v in args.variant:
        configs[f"ours[{v}]"] = RegistrationConfig(**{**base, **parse_overrides(v.split(","))})
    warm = make_pair("tissue", 500, 0)
    if args.before:  # the shared `register` at the same config
        configs["before"] = configs["ours"]
    for cfg in configs.values():
        run_ours(warm, cfg)  # imports, caches
    load = os.getloadavg()
    print(f"# load average {load[0]:.1f} / {load[1]:.1f} on {os.cpu_count()} cores; "
          f"threads {os.environ['OMP_NUM_THREADS']}; overrides {base or 'none'}")
    print(f"# BCPD: {args.bcpd or 'not available'}; Fast_RNRR: {args.fast_rnrr or 'not available'}")
    print(fmt_row(HEADER))
    print(fmt_row(["---"] * 4 + ["---:"] * 8))
    sys.stdout.flush()
    # results[(family, n)][method] -> list of (seed, Errors, wall, returned the source as is)
    results: dict[tuple[str, int], dict[str, list]] = defaultdict(lambda: defaultdict(list))
    excess: dict[int, float] = {}
    decisions: dict[tuple, list[float]] = defaultdict(list)  # colour weight mm per seed
    estimates: dict[tuple, list[float]] = defaultdict(list)  # true / estimated median error
    t_start = time.perf_counter()
    for family in families:
        sizes = args.sizes or FAMILIES[family].sizes
        sizes = [s for s in sizes if s <= 5000] if args.quick else sizes
        for n in sizes:
            for seed in seeds:
                pair = make_pair(family, n, seed)
                normals = pca_normals(pair.truth)
                store = results[(family, n)]

                def emit(method: str, reg: np.ndarray, wall: float | None, ours_wall: float | None,
                         residuals: np.ndarray | None = None, *, p: Pair = pair, nrm: np.ndarray =
                         normals, s: int = seed, st: dict = store, nn: int = n,
                         fam: str = family) -> Errors:
                    e = errors(reg, p.truth, nrm, p.diagonal_m, residuals)
                    still = np.abs(reg - p.source).max() < 1e-3 * p.diagonal_m  # < 0.1 % moved
                    st[method].append((s, e, wall, still and method != "nothing"))
                    label = method + (" (returned the source as is: < 0.1 % of the diagonal moved)"
                                      if still and method != "nothing" else "")
                    print(row(fam, nn, s, label, e, wall, ours_wall))
                    return e

                nothing = emit("nothing", pair.source, None, None)
                t_ours = None
                for label, cfg in configs.items():
                    reg, resid, wall, res = run_ours(
                        pair, cfg, register if label == "before" else register_pair)
                    e = emit(label, reg, wall, wall if label == "ours" else t_ours, resid)
                    decisions[(family, n, label)].append(res.stats[0]["colour_weight_mm"])
                    estimates[(family, n, label)].append(estimate_ratio(e, res, pair.source))
                    if label == "ours":
                        t_ours = wall
                        if family.endswith("_partial"):
                            excess[(family, seed)] = worst_region_excess(pair.source, e.per_point,
                                                               nothing.per_point, 5e-3)
                peers = []
                if args.bcpd:
                    peers.append(("bcpd" + ("+colour" if pair.source_rgb is not None else ""),
                                  lambda p=pair: run_bcpd(args.bcpd, p.source, p.target,
                                                          p.source_rgb, p.target_rgb, args.cap,
                                                          args.bcpd_colour_mm)))
                else:
                    print(row(family, n, seed, "bcpd", None, None, None, "not available"))
                if args.fast_rnrr:
                    peers.append(("fast_rnrr", lambda p=pair, f=family: run_fast_rnrr(
                        args.fast_rnrr, p.source, p.target, f.startswith("tissue"), args.cap)))
                else:
                    print(row(family, n, seed, "fast_rnrr", None, None, None, "not available"))
                for name in args.peers:
                    peers.append((name, lambda p=pair, nm=name: run_python_peer(
                        nm, p.source, p.target, args.cap)))
                for name, fn in peers:
                    try:
                        reg, wall = fn()
                    except (PeerError, OSError, ValueError) as exc:
                        print(row(family, n, seed, name, None, None, None, f"failed: {exc}"))
                        continue
                    emit(name, reg, wall, t_ours)
                sys.stdout.flush()
    print(f"\n# total benchmark wall time {time.perf_counter() - t_start:.0f} s")
    summarise(results)
    goals(results, excess)
    stray_goals(results, excess, decisions, estimates)
    return 0


def _mean(rows: list, attr: str) -> float:
    return float(np.mean([getattr(e, attr) for _, e, *_ in rows]))


def summarise(results: dict) -> None:
    """Means over seeds per family, size and method."""
    print("\n## Means over seeds\n")
    print(fmt_row(["family", "n", "method", "median mm", "p95 mm", "normal mm",
                   "tangential mm", "% diag", "Spearman", "cpu s", "time / ours"]))
    print(fmt_row(["---"] * 3 + ["---:"] * 8))
    for (family, n), methods in results.items():
        ours_wall = np.mean([w for _, _, w, _ in methods["ours"]]) if "ours" in methods else None
        for method, rows in methods.items():
            walls = [w for _, _, w, _ in rows if w is not None]
            wall = float(np.mean(walls)) if walls else None
            rho = _mean(rows, "spearman")
            still = sum(r[3] for r in rows)
            label = method + (f" ({still}/{len(rows)} seeds: the source returned as is)"
                              if still else "")
            print(fmt_row([family, str(n), label, f"{_mean(rows, 'median'):.3f}",
                           f"{_mean(rows, 'p95'):.3f}", f"{_mean(rows, 'normal'):.3f}",
                           f"{_mean(rows, 'tangential'):.3f}",
                           f"{_mean(rows, 'percent_diag'):.2f}",
                           "" if np.isnan(rho) else f"{rho:.2f}",
                           "" if wall is None else f"{wall:.2f}",
                           "" if wall is None or not ours_wall else f"{wall / ours_wall:.1f}"]))


def goals(results: dict, excess: dict[int, float]) -> None:
    """The goals table of issue 14 with the measured figures (worst seed unless said)."""
    out: list[tuple[str, str, str, bool | None]] = []

    def ours(family: str, n: int = 5000) -> list | None:
        return results.get((family, n), {}).get("ours")

    def verdict(name: str, goal: str, ok: bool | None, value: str) -> None:
        out.append((name, goal, value, ok))

    for family, med_goal, p95_goal in (("tissue", 0.2, 0.8), ("tissue_partial", 0.4, 2.0)):
        rows = ours(family)
        if not rows:
            verdict(f"{family} 5k, defaults", f"median <= {med_goal}, p95 <= {p95_goal}", None, "")
            continue
        med = max(e.median for _, e, *_ in rows)
        p95 = max(e.p95 for _, e, *_ in rows)
        ok = med <= med_goal and p95 <= p95_goal
        value = f"worst seed {med:.3f} / {p95:.3f} mm"
        if family == "tissue_partial":
            worst = max(v for (f, _), v in excess.items() if f == family)
            ok = ok and worst <= 0.2
            value += f"; worst 5 mm cell: ours - nothing = {worst:+.2f} mm"
            med_goal_text = f"median <= {med_goal}, p95 <= {p95_goal}, no 5 mm cell worse " \
                            "than nothing by > 0.2 mm (the noise)"
        else:
            med_goal_text = f"median <= {med_goal}, p95 <= {p95_goal}"
        verdict(f"{family} 5k, defaults", med_goal_text, ok, value)
    for family in SHAPE_FAMILIES:
        methods = results.get((family, 5000), {})
        peer = [(_mean(methods[m], "median"), m) for m in ("bcpd", "fast_rnrr") if m in methods]
        if "ours" not in methods or not peer:
            verdict(family, "within 1.2x of the best of BCPD / Fast_RNRR", None,
                    "not measured" if "ours" not in methods else "no peer result")
            continue
        best, who = min(peer)
        mine = _mean(methods["ours"], "median")
        verdict(family, "mean median within 1.2x of the best of BCPD / Fast_RNRR",
                mine <= 1.2 * best, f"ours {mine:.3f} mm vs {who} {best:.3f} mm "
                f"({mine / best:.2f}x)")
    rows = ours("rotation")
    verdict("rotation 90 deg + scale 0.8", "median <= 2 % of the diagonal",
            None if not rows else max(e.percent_diag for _, e, *_ in rows) <= 2.0,
            "" if not rows else f"worst seed {max(e.percent_diag for _, e, *_ in rows):.2f} %")
    rhos = [(e.spearman, f) for (f, _), m in results.items() for _, e, *_ in m.get("ours", [])
            if not np.isnan(e.spearman)]
    if rhos:
        low, where = min(rhos)
        verdict("residual vs true error, Spearman", ">= 0.5", low >= 0.5,
                f"lowest {low:.2f} ({where}); median {np.median([r for r, _ in rhos]):.2f}")
    for n, cap in ((5000, 0.2), (20000, 0.6)):
        rows = ours("tissue", n)
        bcpd = results.get(("tissue", n), {}).get("bcpd+colour")
        if not rows:
            verdict(f"tissue {n // 1000}k in-process time", f"<= {cap} s", None, "not measured")
            continue
        wall = float(np.median([w for _, _, w, _ in rows]))
        ok = wall <= cap
        value = f"median {wall:.3f} s"
        if bcpd:
            ratio = float(np.median([b[2] / o[2] for b, o in zip(bcpd, rows, strict=True)]))
            ok = ok and ratio >= 10
            value += f", BCPD+colour / ours {ratio:.1f}x"
        verdict(f"tissue {n // 1000}k in-process time", f"<= {cap} s and >= 10x BCPD+colour",
                ok, value)
    print("\n## Goals of issue 14\n")
    print(fmt_row(["figure", "goal", "measured", "status"]))
    print(fmt_row(["---"] * 4))
    for name, goal, value, ok in out:
        status = "not measured" if ok is None else ("met" if ok else "NOT MET")
        print(fmt_row([name, goal, value, status]))


if __name__ == "__main__":
    sys.exit(main())
