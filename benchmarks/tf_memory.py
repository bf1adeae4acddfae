"""TF memory benchmark: RSS per transform sample when a TF-heavy log is read into a TF tree.

    .venv/bin/python benchmarks/tf_memory.py /tmp/tf/tf1m.mcap --samples 1000000

Writes (once; `sim/tf_load.py`) a ROS 2 log of `/tf` messages, each with the 20 transforms
of a robot's link chain, then, in a child process, reads every transform
(`io.logs.transforms.read_transforms`) and builds the tree (`core.sync.tf_tree.build_tf_tree`)
as ingest does, keeping both alive. Reported: the child's RSS after its imports, its peak
RSS (the kernel's high-water mark, VmHWM) and its RSS at the end, and the growth per sample
in bytes. `--measure-only` skips writing (e.g. to measure another checkout's code on the same
log: `PYTHONPATH=/path/to/checkout`).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

_CHILD = """
import json, sys
from pathlib import Path

def status(key):
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1]) * 1024
    raise KeyError(key)

from surgrecon_cli.core.sync.tf_tree import build_tf_tree
from surgrecon_cli.io.logs.transforms import read_transforms
base = status("VmRSS")
log = read_transforms(Path(sys.argv[1]))
tree = build_tf_tree(log.samples)
print(json.dumps({"samples": len(log.samples), "edges": len(tree.edges), "base": base,
                  "peak": status("VmHWM"), "end": status("VmRSS")}))
"""


def measure(log: Path) -> dict[str, float]:
    """Read `log`'s TF in a child process: samples, edges, RSS (bytes) after the imports
    ("base"), at its peak and at the end, and the growth per sample ("peak_per_sample",
    "end_per_sample", bytes)."""
    out = subprocess.run([sys.executable, "-c", _CHILD, str(log)], check=True,
                         capture_output=True, text=True).stdout
    result: dict[str, float] = json.loads(out.strip().splitlines()[-1])
    n = max(result["samples"], 1)
    result["peak_per_sample"] = (result["peak"] - result["base"]) / n
    result["end_per_sample"] = (result["end"] - result["base"]) / n
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("log", type=Path)
    parser.add_argument("--samples", type=int, default=1_000_000)
    parser.add_argument("--measure-only", action="store_true")
    parser.add_argument("--json", action="store_true", help="print the figures as JSON")
    args = parser.parse_args()
    if not args.measure_only:
        from surgrecon_cli.sim.tf_load import write_tf_log

        args.log.parent.mkdir(parents=True, exist_ok=True)
        write_tf_log(args.log, args.samples)
    r = measure(args.log)
    if args.json:
        print(json.dumps(r))
        return
    print(f"{r['samples']:.0f} TF samples on {r['edges']:.0f} edges: RSS after imports "
          f"{r['base'] / 1e6:.0f} MB, peak {r['peak'] / 1e6:.0f} MB, end {r['end'] / 1e6:.0f} MB; "
          f"growth {r['peak_per_sample']:.0f} bytes/sample at the peak, "
          f"{r['end_per_sample']:.0f} bytes/sample kept")


if __name__ == "__main__":
    main()
