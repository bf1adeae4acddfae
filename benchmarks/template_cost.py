"""Template cost benchmark (issues 15 and 27): the frame-0 template of a simulated 6-camera
log, at 640x480 and 1920x1080, in modes of the template config, beside another source tree.

    .venv/bin/python benchmarks/template_cost.py [--seeds 21 22] [--sizes 640x480 1920x1080]
        [--modes default detect_width_px=1280 match_all_pairs=false] [--baseline main]
        [--real] [--workdir DIR]

Per size and seed, `surgrecon simulate --cameras 6 --frames 2` and `surgrecon ingest` make
a run; then each mode builds the template (`core.template.build.build_template`, the stage's
call, inside `kept_heap` as the stage does) in a fresh child process limited to one thread
(as a worker runs it: `executors.single_threaded`), which prints: template points, error
against the simulator's true frame-0 surface (median / p95 mm, as `surgrecon evaluate` maps
them), camera pairs matched across epipolar bands, camera-to-template matchings, CPU
seconds of feature detection, matching and the rest, wall and CPU seconds of the build, the
child's peak RSS (ru_maxrss; the caller stays small so the fork does not inflate it) and a
digest of the template points. A mode is `default` or comma-separated overrides of
`[template]` keys (`detect_width_px=1280,match_all_pairs=false`). `--baseline REF` adds
`before`: the default mode run on another source tree (a directory, or a git revision of
this repository exported to a temporary directory), for the ratios of one run.
`--real` adds the real SurgT stereo pair (tests/data/surgt, frame 0, each eye resized to
the size, intrinsics scaled; no truth, so no error): its feature and matching costs are
realistic, and `6-cam s` estimates a 6-camera template from them (6 images, 15 pairs).
Goals (issue 27): 6 cameras 1920x1080 template <= 5 s CPU and <= 1 GB, the template at
defaults unchanged, a mode that changes it within 5 % of the default's error. Timings on a
loaded machine are noisy: compare the ratios of one run.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from long_log import surgrecon_executable

HERE = Path(__file__).resolve()
SOURCE = HERE.parents[1]
MODES = ("default", "match_all_pairs=false")
STEPS = ("features", "matches", "points")


def overrides(mode: str) -> dict:
    """`[template]` key -> value of a mode (`default`: none), typed like the config's."""
    from surgrecon_cli.config import Config

    if mode in ("default", "before"):
        return {}
    cfg, out = Config().template, {}
    for item in mode.split(","):
        key, value = item.split("=")
        kind = type(getattr(cfg, key))
        out[key] = value.lower() in ("1", "true", "yes") if kind is bool else kind(value)
    return out


def real_inputs(size: str) -> tuple:
    """Frame 0 of the SurgT clip, each eye resized to `size`: frame, models, poses."""
    import cv2
    import numpy as np
    from convert_surgt import SURGT, decoded_frames

    from surgrecon_cli.core.geometry.cameras import CameraModel
    from surgrecon_cli.core.geometry.poses import invert_pose, nearest_rotation

    width, height = (int(v) for v in size.split("x"))
    frame = decoded_frames(1)[0]
    fs = cv2.FileStorage(str(SURGT / "calibration.yaml"), cv2.FILE_STORAGE_READ)
    K = [fs.getNode("M1").mat().astype(float), fs.getNode("M2").mat().astype(float)]
    D = [fs.getNode("D1").mat().astype(float).ravel(), fs.getNode("D2").mat().astype(float).ravel()]
    right = np.eye(4)  # x_right = R x_left + T (T in mm)
    right[:3, :3] = nearest_rotation(fs.getNode("R").mat().astype(float))
    right[:3, 3] = fs.getNode("T").mat().astype(float).ravel() / 1000.0
    fs.release()
    eyes = (frame[:, :1280], frame[:, 1280:])
    images = [np.ascontiguousarray(cv2.resize(e, (width, height), interpolation=cv2.INTER_CUBIC)
                                   [:, :, ::-1]) for e in eyes]
    scale = np.diag([width / eyes[0].shape[1], height / eyes[0].shape[0], 1.0])
    models = [CameraModel(scale @ k, d, width, height) for k, d in zip(K, D, strict=True)]
    return images, models, np.stack([np.eye(4), invert_pose(right)])


def child(source: str, mode: str) -> None:
    """Build one template in this process (one thread); print one JSON line. `source` is
    `sim:RUN_DIR:GT_PATH` or `real:WxH`."""
    import contextlib
    import dataclasses
    import hashlib
    import resource
    import time

    import numpy as np

    from surgrecon_cli.config import Config
    from surgrecon_cli.core.template.build import BuildOptions, TemplateFrame, build_template
    from surgrecon_cli.executors import single_threaded

    single_threaded()
    try:
        from surgrecon_cli.executors.heap import kept_heap
    except ImportError:  # a `--baseline` tree from before: its stage had none
        kept_heap = contextlib.nullcontext
    config = Config()
    config = dataclasses.replace(config, template=dataclasses.replace(config.template,
                                                                      **overrides(mode)))
    kind, _, rest = source.partition(":")
    if kind == "real":
        images, models, poses = real_inputs(rest)
        tool_pose, noise, gt = np.full((4, 4), np.nan), None, None
    else:
        from surgrecon_cli.core.noise.model import noise_from_report
        from surgrecon_cli.io.logs.ground_truth import load_ground_truth
        from surgrecon_cli.io.run.ingest_store import load_ingested

        run_dir, gt_path = rest.split(":")
        log = load_ingested(Path(run_dir) / "ingest")
        images, poses, models = log.frame_images(0), log.usable_poses(0), list(log.models)
        tool_pose = log.tool_poses[0]
        noise = noise_from_report(log.report, log.cameras, pixel_px=0.0)
        gt = load_ground_truth(Path(gt_path))
    marks: dict[str, float] = {}
    wall, cpu = time.perf_counter(), time.process_time()
    with kept_heap():
        result = build_template(TemplateFrame(images, poses, tool_pose), models,
                                config.template, config.tool,
                                BuildOptions(noise=noise, on_step=lambda name: marks.update(
                                    {name: time.process_time()})))
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    stats = result.stats
    median = p95 = float("nan")
    if gt is not None:
        from surgrecon_cli.core.evaluate.scoring import map_to_surface

        error_mm = map_to_surface(result.points, gt.vertices[0], gt.faces).distance * 1e3
        median, p95 = float(np.median(error_mm)), float(np.percentile(error_mm, 95))
    start = marks["points"] - cpu  # process time when the build began
    print(json.dumps({
        "points": len(result.points), "median_mm": median, "p95_mm": p95,
        "pairs": stats.get("pairs_matched", stats["candidate_pairs"]),
        "to_template": stats.get("matched_to_template", 0), "wall_s": wall, "cpu_s": cpu,
        "features_s": marks["features"] - start, "matches_s": marks["matches"] - marks["features"],
        "cameras": len(images),
        "rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6,
        "digest": hashlib.md5(np.ascontiguousarray(result.points).tobytes()).hexdigest()[:8]}))


def measure(source: str, mode: str, tree: Path) -> dict:
    """One template build in a child process with source tree `tree` first on the path."""
    env = dict(os.environ, PYTHONPATH=str(tree))
    out = subprocess.run([sys.executable, str(HERE), "--child", source, mode],
                         env=env, check=True, capture_output=True, text=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def baseline_tree(ref: str, tmp: Path) -> Path:
    """A source tree: `ref` itself when a directory, else the git revision exported."""
    if Path(ref).is_dir():
        return Path(ref).resolve()
    tree = tmp / "baseline"
    tree.mkdir()
    archive = subprocess.run(["git", "-C", str(SOURCE), "archive", ref], check=True,
                             capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(tree)], input=archive, check=True)
    return tree


def prepare(workdir: Path, size: str, seed: int, exe: str) -> tuple[Path, Path]:
    """Simulated log (6 cameras, 2 frames) and its ingested run, made once per size/seed."""
    width, height = size.split("x")
    stem = workdir / f"sim_{size}_{seed}"
    log, gt, run = stem.with_suffix(".mcap"), stem.with_suffix(".gt.npz"), workdir / stem.name
    if not (log.exists() and gt.exists()):
        subprocess.run([exe, "simulate", str(log), "--cameras", "6", "--frames", "2",
                        "--seed", str(seed), "--width", width, "--height", height, "-q"],
                       check=True, stdout=subprocess.DEVNULL)
    if not (run / "ingest").exists():
        subprocess.run([exe, "ingest", str(log), "-o", str(run), "-q", "--force"], check=True,
                       stdout=subprocess.DEVNULL)
    return run, gt


def print_rows(rows: list[dict]) -> None:
    """The table, and per source each mode's ratios to the first mode of that source."""
    head = (f"{'source':>14} {'seed':>4} {'mode':>28} {'points':>6} {'med mm':>7} {'p95 mm':>7} "
            f"{'pairs':>5} {'feat s':>6} {'match s':>7} {'cpu s':>6} {'wall s':>6} "
            f"{'RSS GB':>6} {'6-cam s':>7} {'digest':>8}")
    print(head)
    for r in rows:
        print(f"{r['size']:>14} {r['seed']:>4} {r['mode']:>28} {r['points']:>6} "
              f"{r['median_mm']:>7.3f} {r['p95_mm']:>7.3f} {r['pairs']:>5} "
              f"{r['features_s']:>6.2f} {r['matches_s']:>7.2f} {r['cpu_s']:>6.2f} "
              f"{r['wall_s']:>6.2f} {r['rss_gb']:>6.2f} {six_cameras(r):>7.2f} {r['digest']:>8}")
    print("\nratios to the first mode of the same source (same digest: the same template)")
    for r in rows:
        base = next(a for a in rows if a["size"] == r["size"] and a["seed"] == r["seed"])
        if base is r:
            continue
        print(f"{r['size']:>14} {r['seed']:>4} {r['mode']:>28} / {base['mode']:<10} "
              f"cpu {r['cpu_s'] / base['cpu_s']:.2f}  points {r['points'] / base['points']:.2f}  "
              f"median {r['median_mm'] / base['median_mm']:.3f}  "
              f"p95 {r['p95_mm'] / base['p95_mm']:.3f}  "
              f"same {'yes' if r['digest'] == base['digest'] else 'no'}")


def six_cameras(r: dict) -> float:
    """CPU s of a 6-camera template from a row's per-image and per-pair costs (a 6-camera
    row: its own CPU s)."""
    n = r["cameras"]
    per_image, per_pair = r["features_s"] / n, r["matches_s"] / max(1, r["pairs"])
    rest = r["cpu_s"] - r["features_s"] - r["matches_s"]
    return r["cpu_s"] if n == 6 else 6 * per_image + 15 * per_pair + rest


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[21, 22])
    parser.add_argument("--sizes", nargs="+", default=["640x480", "1920x1080"])
    parser.add_argument("--modes", nargs="+", default=list(MODES),
                        help="`default` or key=value[,key=value] of [template]")
    parser.add_argument("--baseline", help="another source tree or a git revision: `before`")
    parser.add_argument("--real", action="store_true", help="add the SurgT stereo pair")
    parser.add_argument("--workdir", type=Path, help="keep logs and runs here (reused)")
    parser.add_argument("--child", nargs=2, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        child(*args.child)
        return 0
    exe = surgrecon_executable()
    with tempfile.TemporaryDirectory() as tmp:
        workdir = args.workdir or Path(tmp)
        workdir.mkdir(parents=True, exist_ok=True)
        baseline = baseline_tree(args.baseline, Path(tmp)) if args.baseline else None
        sources = []
        for size in args.sizes:
            for seed in args.seeds:
                run, gt = prepare(workdir, size, seed, exe)
                sources.append((size, seed, f"sim:{run}:{gt}"))
            if args.real:
                sources.append((f"real {size}", 0, f"real:{size}"))
        rows = []
        for label, seed, source in sources:
            modes = [(m, SOURCE) for m in args.modes]
            if baseline is not None:
                modes.insert(0, ("before", baseline))
            for mode, tree in modes:
                row = measure(source, mode, tree)
                rows.append(dict(row, size=label, seed=seed, mode=mode))
                print(json.dumps(rows[-1]), flush=True)
        print()
        print_rows(rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
