"""Sample I/O timings: the goals that used to be timed assertions in the tests (a test
asserts behaviour; wall-clock time is measured here).

    .venv/bin/python benchmarks/sample_io.py [--run RUN] [--repeats 5]

- `info` on the shipped sample (an indexed log, read from its summary and message indexes):
  goal < 2 s.
- `surgrecon export RUN --mcap` of a run of the sample: goal <= 5 s and <= 1.5 x the log.
  Without --run, `surgrecon run sample_data/sample.mcap` makes one in a temporary folder
  first (about a minute on 2 cores).

Prints the median and the spread of `--repeats` timings of each, against its goal.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

from surgrecon_cli.cli.main import main
from surgrecon_cli.info import scan_log

SAMPLE = Path(__file__).resolve().parents[1] / "sample_data" / "sample.mcap"


def timings(action: Callable[[], object], repeats: int) -> list[float]:
    """Wall seconds of `repeats` calls of `action`."""
    out = []
    for _ in range(repeats):
        start = time.perf_counter()
        action()
        out.append(time.perf_counter() - start)
    return out


def report(name: str, seconds: list[float], goal_s: float, extra: str = "") -> None:
    median = statistics.median(seconds)
    print(f"{name}: median {median:.2f} s (min {min(seconds):.2f}, max {max(seconds):.2f}, "
          f"{len(seconds)} runs); goal {goal_s:g} s {'met' if median <= goal_s else 'MISSED'}"
          + (f"; {extra}" if extra else ""))


def main_() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", type=Path, help="a finished run of the sample to export")
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    report("info on the sample", timings(lambda: scan_log(SAMPLE), args.repeats), 2.0)
    with tempfile.TemporaryDirectory() as tmp:
        run = args.run
        if run is None:
            run = Path(tmp) / "run"
            assert main(["run", str(SAMPLE), "-o", str(run), "-q"]) == 0
        out = Path(tmp) / "export.mcap"

        def export() -> None:
            assert main(["export", str(run), "--mcap", str(out), "--force", "-q"]) == 0

        seconds = timings(export, args.repeats)
        ratio = out.stat().st_size / SAMPLE.stat().st_size
        report("export --mcap of the sample run", seconds, 5.0,
               f"{ratio:.2f} x the log (goal <= 1.5)")


if __name__ == "__main__":
    main_()
