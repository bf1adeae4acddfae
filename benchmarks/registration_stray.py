"""Goals of issue 28 for benchmarks/registration.py: the stray-colour families, the colour
decision per family and size, and how far the summary's error estimate is below the truth.

Figures per method come from the benchmark's results: (family, n) -> method -> rows of
(seed, Errors, wall s, returned as is). Seeds are reported as run (the caller says which
are tuning and which acceptance seeds).
"""

from __future__ import annotations

import numpy as np
from registration_metrics import Errors

from surgrecon_cli.core.registration.pair import error_estimate_mm

GOALS = {2000: (0.5, 1.5), 5000: (0.2, 0.8), 20000: (0.1, 0.6)}  # median, p95 mm
PARTIAL_MEDIAN = 0.4
CELL_ALLOWANCE = 0.2  # mm: the target's noise; a cell within it is "not worse"
TIME_CAP_S, BCPD_FACTOR = 0.3, 5.0
ESTIMATE_FACTOR = 10.0


def estimate_ratio(e: Errors, result: object, source: np.ndarray) -> float:
    """True median error / the summary's estimated median error (inf for a 0 estimate)."""
    est = error_estimate_mm(result, source)[0]  # type: ignore[arg-type]
    return float("inf") if not est > 0 else e.median / est


def _row(cells: list[str]) -> str:
    return "| " + " | ".join(cells) + " |"


def stray_goals(results: dict, excess: dict, decisions: dict, estimates: dict) -> None:
    """Print the goals table of issue 28 (worst seed and median over seeds)."""
    out: list[list[str]] = []

    def put(name: str, goal: str, value: str, ok: bool | None) -> None:
        out.append([name, goal, value, "not measured" if ok is None else
                    ("met" if ok else "NOT MET")])

    for n, (g_med, g_p95) in GOALS.items():
        rows = results.get(("stray_colour", n), {}).get("ours")
        nothing = results.get(("stray_colour", n), {}).get("nothing")
        if not rows:
            put(f"stray_colour {n // 1000}k", f"median <= {g_med}, p95 <= {g_p95}", "", None)
            continue
        med = [e.median for _, e, *_ in rows]
        p95 = [e.p95 for _, e, *_ in rows]
        base = f"; nothing {np.median([e.median for _, e, *_ in nothing]):.2f}" if nothing else ""
        put(f"stray_colour {n // 1000}k", f"median <= {g_med}, p95 <= {g_p95}",
            f"median over seeds {np.median(med):.3f} / {np.median(p95):.3f}; worst seed "
            f"{max(med):.3f} / {max(p95):.3f}{base}", max(med) <= g_med and max(p95) <= g_p95)
    rows = results.get(("stray_colour_partial", 5000), {}).get("ours")
    if rows:
        med = max(e.median for _, e, *_ in rows)
        cells = [v for (f, _), v in excess.items() if f == "stray_colour_partial"]
        worst = max(cells) if cells else float("nan")
        put("stray_colour_partial 5k", f"median <= {PARTIAL_MEDIAN}; no 5 mm cell worse than "
            f"nothing by > {CELL_ALLOWANCE} mm", f"worst seed {med:.3f}; worst cell ours - "
            f"nothing {worst:+.2f} mm", med <= PARTIAL_MEDIAN and worst <= CELL_ALLOWANCE)
    rows = results.get(("stray_colour", 5000), {}).get("ours")
    bcpd = results.get(("stray_colour", 5000), {}).get("bcpd+colour")
    if rows:
        wall = float(np.median([w for _, _, w, _ in rows]))
        value, ok = f"median {wall:.3f} s CPU", wall <= TIME_CAP_S
        if bcpd:
            ratio = float(np.median([b[2] / o[2] for b, o in zip(bcpd, rows, strict=True)]))
            value += f", BCPD+colour / ours {ratio:.1f}x"
            ok = ok and ratio >= BCPD_FACTOR
        put("stray_colour 5k time (CPU, one thread)",
            f"<= {TIME_CAP_S} s, >= {BCPD_FACTOR:.0f}x faster than BCPD+colour", value, ok)
    for (family, n, label), ratios in sorted(estimates.items()):
        if label != "ours":
            continue
        worst = max(ratios)
        put(f"estimate {family} {n // 1000}k", f"true / estimated median < {ESTIMATE_FACTOR:.0f}",
            f"worst seed {worst:.1f}x", worst < ESTIMATE_FACTOR)
    print("\n## Goals of issue 28\n")
    print(_row(["figure", "goal", "measured (mm unless said)", "status"]))
    print(_row(["---"] * 4))
    for cells in out:
        print(_row(cells))
    print("\n## Colour decision (mm per RGB unit per seed; 0 = colour not used)\n")
    print(_row(["family", "n", "method", "weights"]))
    print(_row(["---"] * 4))
    for (family, n, label), weights in sorted(decisions.items()):
        print(_row([family, str(n), label, " ".join(f"{w:.0f}" for w in weights)]))
