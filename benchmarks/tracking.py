"""Tracking benchmark: real camera motion without a tracker (issue 24, items 2-3).

    .venv/bin/python benchmarks/tracking.py [--seeds 301 302] [--frames 12]
        [--variant rig-sweep] [--workdir /tmp/surgrecon-tracking] [--surgrecon EXE]
        [--set section.key=value ...]

For every seed: `surgrecon simulate --variant rig-sweep` (an untracked stereo endoscope
sweeping 2-4 deg a frame over still tissue: the scene moves rigidly in the rig frame, the
truth is that rigid motion), `surgrecon run`, `surgrecon evaluate`; then per frame:
- tracked: share of the template points visible in >= 2 cameras at their true position
  (in front, inside the image) that the tracker found in >= 2 cameras; target: ... that
  also passed the reprojection check (intra or inter: a target for the registration);
- labelled: share of points with a label (not unknown); deforming: share of the labelled
  points called deforming (the truth has none);
- p95: 95th percentile (mm) of the labelled points' distance from their true position,
  i.e. from the scene's rigid motion.
Goals (issue 24): tracked >= 80 %, deforming <= 5 %, labelled >= 50 % of point-frames,
p95 <= 2 mm. `--surgrecon` runs another installation (e.g. main's, for "before").

`--runs RUN ...` tabulates finished runs of a real rigid scene instead (e.g. the SurgT
clip through `surgrecon convert`): without ground truth, "visible" uses the registered
positions and the reference is the best rigid motion of the template onto the labelled
registered points (robust fit, 1 mm inliers), so p95 is the labelled points' departure
from one rigid motion.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import numpy as np

from surgrecon_cli.core.classify.labels import DEFORMING, INTER, INTRA, UNKNOWN
from surgrecon_cli.core.evaluate.scoring import map_to_surface
from surgrecon_cli.core.geometry.cameras import in_image, project
from surgrecon_cli.core.registration.rigid_fit import robust_rigid
from surgrecon_cli.io.logs.ground_truth import load_ground_truth
from surgrecon_cli.io.run.artefacts import read_labels, read_registration, read_template
from surgrecon_cli.io.run.ingest_store import load_ingested
from surgrecon_cli.io.run.layout import RunLayout


def run(argv: list[str]) -> None:
    proc = subprocess.run(argv, capture_output=True, text=True)
    if proc.returncode != 0:
        sys.exit(f"{' '.join(argv)} failed: {proc.stderr.strip().splitlines()[-1:]}")


def frame_table(run_dir: Path, gt_path: Path | None) -> list[dict[str, float]]:
    """Per frame k >= 1: tracked, labelled, deforming shares and the labelled p95 (mm)
    against the truth (gt_path) or, without it, against the best rigid motion."""
    layout = RunLayout(run_dir)
    log = load_ingested(layout.ingest_dir)
    template = read_template(layout).points
    n = len(template)
    gt = None if gt_path is None else load_ground_truth(gt_path)
    mapping = None if gt is None else map_to_surface(template, gt.vertices[0], gt.faces)
    labels = read_labels(layout, (log.n_frames, n)).labels
    rows = []
    for k in range(1, log.n_frames):
        reg = read_registration(layout, k, n)
        lab = labels[k] != UNKNOWN
        if gt is not None and mapping is not None:
            true = mapping.follow(gt.vertices[k], gt.faces)
        else:
            fit = lab & np.isfinite(reg.registered).all(1)
            R, t, _ = robust_rigid(template[fit], reg.registered[fit], 1e-3)
            true = template @ R.T + t
        poses = log.usable_poses(k)
        seen = np.zeros(n, int)
        for c, model in enumerate(log.models):
            if np.isfinite(poses[c]).all():
                uv, z = project(true, poses[c], model)
                seen += (z > 0) & in_image(uv, model, 8.0)
        visible = seen >= 2
        has = (reg.status == INTRA) | (reg.status == INTER)
        found = np.isfinite(reg.pixels).all(2).sum(1) >= 2
        error = np.linalg.norm(reg.registered - true, axis=1)[lab] * 1e3
        rows.append({
            "frame": k,
            "visible": int(visible.sum()),
            "tracked": float((found & visible).sum() / max(visible.sum(), 1)),
            "target": float((has & visible).sum() / max(visible.sum(), 1)),
            "labelled": float(lab.mean()),
            "deforming": float((labels[k] == DEFORMING).sum() / max(lab.sum(), 1)),
            "p95_mm": float(np.percentile(error, 95)) if len(error) else float("nan"),
            "errors": error,
        })
    return rows


def print_rows(name: str, rows: list[dict]) -> None:
    """The per-frame lines of one run and its summary line."""
    for r in rows:
        print(f"{name:>5} {r['frame']:>5} {r['visible']:>7} {r['tracked']:>7.1%} "
              f"{r['target']:>7.1%} {r['labelled']:>8.1%} {r['deforming']:>6.1%} "
              f"{r['p95_mm']:>7.2f}")
    errors = np.concatenate([r["errors"] for r in rows])
    labelled = np.array([r["labelled"] for r in rows])
    deforming = np.array([r["deforming"] for r in rows]) @ labelled / max(labelled.sum(), 1e-9)
    tracked = [r["tracked"] for r in rows]
    target = np.mean([r["target"] for r in rows])
    p95 = np.percentile(errors, 95) if len(errors) else float("nan")
    print(f"{name:>5}   all {'':>7} {np.mean(tracked):>7.1%} {target:>7.1%} "
          f"{labelled.mean():>8.1%} {deforming:>6.1%} {p95:>7.2f}   "
          f"(min tracked {min(tracked):.1%})")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[301, 302])
    parser.add_argument("--frames", type=int, default=12)
    parser.add_argument("--variant", default="rig-sweep")
    parser.add_argument("--workdir", type=Path, default=Path("/tmp/surgrecon-tracking"))
    parser.add_argument("--surgrecon", default=str(Path(sys.executable).with_name("surgrecon")))
    parser.add_argument("--set", action="append", default=[], dest="overrides")
    parser.add_argument("--runs", type=Path, nargs="+", default=[],
                        help="finished runs of a real rigid scene to tabulate (no truth)")
    args = parser.parse_args()
    args.workdir.mkdir(parents=True, exist_ok=True)
    sets = [a for o in args.overrides for a in ("--set", o)]
    own = str(Path(sys.executable).with_name("surgrecon"))  # the variant is this branch's
    print(f"{'seed':>5} {'frame':>5} {'visible':>7} {'tracked':>7} {'target':>7} {'labelled':>8} "
          f"{'deform':>6} {'p95 mm':>7}")
    for run_dir in args.runs:
        print_rows(run_dir.name, frame_table(run_dir, None))
    for seed in args.seeds if not args.runs else ():
        log = args.workdir / f"{args.variant}-{seed}.mcap"
        run_dir = args.workdir / f"run-{args.variant}-{seed}"
        if not log.exists():
            run([own, "simulate", str(log), "--variant", args.variant, "--seed",
                 str(seed), "--frames", str(args.frames)])
        gt = log.with_name(log.name.removesuffix(".mcap") + ".gt.npz")
        run([args.surgrecon, "run", str(log), "-o", str(run_dir), *sets])
        run([args.surgrecon, "evaluate", str(run_dir), "--ground-truth", str(gt)])
        print_rows(str(seed), frame_table(run_dir, gt))


if __name__ == "__main__":
    main()
