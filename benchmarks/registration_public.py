"""Public colourless shapes (issue 28): `register_pair` beside the peers, side by side.

Shapes (files from the peers' public repositories; give their folders):
- probreg (github.com/neka-nat/probreg, examples/): `face` (face-x.txt -> face-y.txt, 23,728
  points, taken as mm) and `bunny` (bunny-x.txt -> bunny-y.txt, 8,171 points, scaled to a
  0.2 m diagonal); the truth of source point i is target point i (the files share their
  order).
- Fast_RNRR (github.com/Juyong/Fast_RNRR, data/noise/): `jump_d03`, `jump_d07`, `jump_s005`,
  `jump_s05` (10,002 vertices, taken as m): source.obj -> target.obj, the same mesh in
  another pose with dense (d) or sparse (s) noise; truth of source vertex i is target vertex
  i (noise included, the same for every method); init/landmark.txt are the pairs the peers
  started from, passed to ours as landmarks. Fast_RNRR's own results and RPTS / NICP's (as
  its authors ran them) are read from results/. Its `partial_overlap` set ships only the
  targets (the sources are in the MIT dataset it names), so it is not measured here.
BCPD (`--bcpd`) runs on every shape with `registration_peers.run_bcpd`'s settings.

    PYTHONPATH=$PWD .venv/bin/python benchmarks/registration_public.py \
        --probreg PROBREG/examples --fast-rnrr FAST_RNRR/data/noise --bcpd /path/to/bcpd

Errors: median / p95 of |registered_i - truth_i| as % of the source's bounding-box diagonal;
time: CPU seconds in process (ours) or of the subprocess (BCPD), one thread.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from registration_peers import PeerError, read_obj_vertices, run_bcpd  # noqa: E402

from surgrecon_cli.registration import register_pair  # noqa: E402

BUNNY_DIAGONAL_M = 0.2  # ours: the bunny's files are in arbitrary units


@dataclass(frozen=True)
class Shape:
    """A public pair: source / target / truth (N, 3) m, landmarks (L, 2) or None, and the
    peers' stored results {name: (N, 3) m}."""

    name: str
    source: np.ndarray
    target: np.ndarray
    truth: np.ndarray
    landmarks: np.ndarray | None
    stored: dict[str, np.ndarray]


def read_ply_vertices(path: Path) -> np.ndarray:
    """x y z of an ASCII PLY's vertices (N, 3)."""
    lines = path.read_text().splitlines()
    n = next(int(ln.split()[-1]) for ln in lines if ln.startswith("element vertex"))
    start = lines.index("end_header") + 1
    return np.asarray([ln.split()[:3] for ln in lines[start:start + n]], float)


def probreg_shapes(folder: Path) -> list[Shape]:
    out = []
    for name, scale in (("face", 1e-3), ("bunny", 0.0)):
        x = np.loadtxt(folder / f"{name}-x.txt")
        y = np.loadtxt(folder / f"{name}-y.txt")
        if scale == 0.0:
            scale = BUNNY_DIAGONAL_M / float(np.linalg.norm(x.max(0) - x.min(0)))
        out.append(Shape(name, x * scale, y * scale, y * scale, None, {}))
    return out


def rnrr_shapes(folder: Path) -> list[Shape]:
    out = []
    for sub in sorted(p for p in folder.glob("jump_*") if p.is_dir()):
        src = read_obj_vertices(sub / "data" / "source.obj")
        tgt = read_obj_vertices(sub / "data" / "target.obj")
        lm = np.loadtxt(sub / "init" / "landmark.txt", dtype=np.int64, ndmin=2)
        stored = {}
        for method, label in (("ours", "Fast_RNRR"), ("RPTS", "RPTS"), ("NICP", "NICP")):
            files = sorted((sub / "results" / method).glob("*.ply"))
            if files:
                stored[label] = read_ply_vertices(files[0])
        out.append(Shape(sub.name, src, tgt, tgt, lm, stored))
    return out


def score(registered: np.ndarray, shape: Shape) -> tuple[float, float]:
    diag = float(np.linalg.norm(shape.source.max(0) - shape.source.min(0)))
    e = np.linalg.norm(registered - shape.truth, axis=1) / diag * 100
    return float(np.median(e)), float(np.percentile(e, 95))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--probreg", type=Path, help="probreg's examples/ folder")
    ap.add_argument("--fast-rnrr", type=Path, help="Fast_RNRR's data/noise/ folder")
    ap.add_argument("--bcpd", help="BCPD binary")
    ap.add_argument("--only", nargs="*", help="shape names to run")
    ap.add_argument("--cap", type=float, default=600.0)
    args = ap.parse_args()
    shapes: list[Shape] = []
    if args.probreg:
        shapes += probreg_shapes(args.probreg)
    if args.fast_rnrr:
        shapes += rnrr_shapes(args.fast_rnrr)
    if args.only:
        shapes = [s for s in shapes if s.name in args.only]
    print("| shape | n | nothing | ours | best peer | ours / best | peers (median % of "
          "diagonal) | ours CPU s | BCPD CPU s |")
    print("| --- | ---: | ---: | --- | --- | ---: | --- | ---: | ---: |")
    for shape in shapes:
        t0 = time.process_time()
        result = register_pair(shape.source, shape.target, landmarks=shape.landmarks)
        ours_s = time.process_time() - t0
        ours = score(result.registered, shape)
        peers = {name: score(reg, shape) for name, reg in shape.stored.items()}
        bcpd_s = float("nan")
        if args.bcpd:
            try:
                reg, bcpd_s = run_bcpd(args.bcpd, shape.source, shape.target, None, None,
                                       args.cap)
                peers["BCPD"] = score(reg, shape)
            except PeerError as exc:
                print(f"  BCPD on {shape.name}: {exc}", file=sys.stderr)
        nothing = score(shape.source, shape)
        best = min(peers.items(), key=lambda kv: kv[1][0]) if peers else ("-", (np.nan, 0))
        listed = ", ".join(f"{k} {v[0]:.3f}" for k, v in peers.items())
        print(f"| {shape.name} | {len(shape.source)} | {nothing[0]:.3f} | {ours[0]:.3f} / "
              f"{ours[1]:.3f} | {best[0]} {best[1][0]:.3f} | {ours[0] / best[1][0]:.2f} | "
              f"{listed} | {ours_s:.2f} | {bcpd_s:.2f} |", flush=True)


if __name__ == "__main__":
    main()
