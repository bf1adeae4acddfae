"""Real-footage benchmark: public real stereo clips and the simulator's real-image variants.

    .venv/bin/python benchmarks/real.py [--real NAME=LOG.mcap[:CONFIG.toml] ...]
        [--variants stereo stereo-real ...] [--seeds 201 ...] [--frames 12]
        [--workdir /tmp/surgrecon-real] [--code SRC] [--fresh]

Every log is run with `surgrecon run` (with `--code SRC`, the run uses the surgrecon source
tree SRC instead of this checkout: e.g. `git archive main surgrecon_cli | tar -x -C SRC`
for a before/after table; simulating, evaluating and these checks always use this
checkout). One table, a row per log:
- σ run: the pixel noise the run measured (metrics/summary.json noise.pixel_px);
- σ NCC: an independent localisation check on the same images (benchmarks/real_reference:
  NCC row offsets on the rectified frame-0 pair: NCC's own localisation error), and σ run over it;
- σ loc: the localisation part of σ run (summary noise.localisation_px: the residuals less
  each camera's median, the systematic offset a calibration error leaves);
- σ disp: the run's own localisation error along the epipolar lines, where it makes depth
  (real_reference.disparity_localisation_px: its frame-0 disparities against NCC's and
  StereoSGBM's, separated by the three-cornered hat), and σ loc over it (a calibration
  error moves views across the epipolar lines, which σ run and NCC's row offsets see and
  disparities do not);
- σ truth: simulator only, the localisation error against the true geometry;
- trk run: the tracking noise the run measured (summary noise.tracking_px, the median over
  frames); trk rigid: real logs of a rigid scene only, an independent check (the SurgT
  clip; real_reference.rigid_tracking_px, epipolar residuals of the tracks); trk truth:
  logs with a ground truth (the simulator's, and the `breathe=A` clips: real texture, known
  motion, `clip_truth_tracking`), the tracks against the true motion
  (real_reference.ground_truth_tracking_px); both over every camera, as the run;
  trk/check: trk run over trk truth or trk rigid;
- tracked / outlier: mean share of template points observed / outliers, frames 1 on;
- static / shifting / deforming / unknown: label shares over point-frames, frames 1 on;
  "deform|lab" the share of labelled point-frames called deforming;
- ref med / ref p95: labelled positions against a reference built from the images (DIS flow
  on camera 0 + StereoSGBM depth), mm, frames 1 on; "refT med" / "refT p95" (logs with a
  ground truth) that reference's own error against the truth where the truth covers the
  point: what the reference can resolve;
- macro-F1 and calib 2σ: logs with a ground truth beside them (`surgrecon evaluate`): the
  simulator's, and SurgT clips with `breathe=A` (real texture, known breathing motion:
  benchmarks/surgt_breathing.py);
- logs with a ground truth only (the issue's "real breathing" goals, measured on the
  simulator's `breathing` variant and the `breathe=A` clips): "true med" / "true p95"
  labelled positions against the true surface (mm); "de|rigid" the share of point-frames
  whose true neighbourhood is confidently rigid (moved, or not, with a rigid-fit RMS under
  half of classify.deform_mm) called deforming;
  "moving det" the share of truly moving point-frames (shifting or deforming) called moving;
  "covered" the share of template points the true surface covers (the breathing clips'
  truth has holes where SGBM measured nothing, and maps a point over one to its rim:
  core/evaluate/scoring.on_mesh_rim, as `surgrecon evaluate`'s calib2σ counts them), "cov
  med" / "cov p95" the labelled positions of those against the truth (mm, frames 1 on):
  "true med" / "true p95" without the points over holes.
Real logs without a ground truth also get a second table, "real motion" (issue 24; the
scene must be rigid and the rig fixed in the world, as `surgrecon convert` writes it
without --camera-poses), against the scene's rigid motion measured from the images alone
(real_reference.rigid_scene_motion):
- deg / px: the camera's motion from the previous frame (degrees; px, median over the
  template points in camera 0), median and max over frames;
- trk|vis: the share of visible template points (the rigidly moved template inside some
  camera's image) that the run found in some camera (worst frame and mean);
- labelled: the labelled share of point-frames; deform|lab: the deforming share of those;
- rigid p95: labelled positions against the rigidly moved template (mm, over point-frames);
- fits: the report's quality verdict (summary quality.verdict.fits).
`--per-frame` prints the same per frame. `--surgt SPEC ...` builds clips of the SurgT sample
(benchmarks/surgt_clips.py: frame step, 640x512, ping-pong, a turn about the baseline of
1-3.5° a frame, JPEG) and runs them as real logs, e.g.

    .venv/bin/python benchmarks/real.py --variants --surgt "" "scale=0.5,step=3,length=16" \
        "scale=0.5,step=2,pitch=1,length=16" "scale=0.5,step=3,pitch=2,length=16" \
        "scale=0.5,step=3,pitch=3.5,length=16,jpeg=70" --per-frame

and the real-texture breathing clip at the size of a rectified in-vivo stereo recording:

    .venv/bin/python benchmarks/real.py --variants --surgt \
        "breathe=4,length=39,scale=0.28125,jpeg=80"

Cameras 0 and 1 of every log must be a stereo pair. The rows go to WORKDIR/real.json.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
from real_reference import (
    disparity_localisation_px,
    ground_truth_localisation_px,
    ground_truth_tracking_px,
    ncc_localisation_px,
    reference_positions,
    rigid_scene_motion,
    rigid_tracking_px,
)
from surgt_clips import clip_name, make_clip

from surgrecon_cli.core.classify.labels import DEFORMING, SHIFTING, STATIC, UNKNOWN
from surgrecon_cli.core.geometry.cameras import project
from surgrecon_cli.io.logs.ground_truth import gt_path_beside, load_ground_truth
from surgrecon_cli.io.run.artefacts import (
    read_observations,
    read_registration,
    read_template,
)
from surgrecon_cli.io.run.ingest_store import load_ingested
from surgrecon_cli.io.run.layout import RunLayout
from surgrecon_cli.io.run.ply import read_ply

DEFAULT_VARIANTS = ("stereo", "stereo-real", "stereo-sweep", "breathing")
DEFAULT_SEEDS = (201,)


def surgrecon_command() -> list[str]:
    beside = Path(sys.executable).with_name("surgrecon")
    if not beside.exists():
        sys.exit("surgrecon is not installed (run `make install`, then .venv/bin/python ...)")
    return [str(beside)]


def call(argv: list[str], log: Path, code: Path | None = None) -> None:
    env = dict(os.environ)
    if code is not None:
        env["PYTHONPATH"] = str(code.absolute())
    proc = subprocess.run(argv, capture_output=True, text=True, env=env)
    with log.open("a") as f:
        f.write(f"$ {' '.join(argv)}\n{proc.stdout}{proc.stderr}(exit {proc.returncode})\n")
    if proc.returncode != 0:
        lines = (proc.stderr or proc.stdout).strip().splitlines() or ["failed"]
        raise RuntimeError(lines[-1])


def label_shares(layout: RunLayout, n_frames: int) -> dict[str, float]:
    counts = np.zeros(256)
    for k in range(1, n_frames):
        counts += np.bincount(read_ply(layout.cloud(k))["label"].astype(int), minlength=256)
    total = max(counts.sum(), 1.0)
    labelled = max(counts[[STATIC, SHIFTING, DEFORMING]].sum(), 1.0)
    return {"static": counts[STATIC] / total, "shifting": counts[SHIFTING] / total,
            "deforming": counts[DEFORMING] / total, "unknown": counts[UNKNOWN] / total,
            "deform_of_labelled": counts[DEFORMING] / labelled}


def reference_errors(layout: RunLayout, n_frames: int, obs: Any, n: int, ref: np.ndarray
                     ) -> tuple[float, float]:
    """Median and p95 (mm) of labelled positions against the image reference ref (T, M, 3) m
    of the camera-0 observations, frames 1 on."""
    cam0 = obs.camera == 0
    errors = []
    for k in range(1, n_frames):
        cloud = read_ply(layout.cloud(k))
        xyz = np.full((n, 3), np.nan)
        keep = cloud["label"] != UNKNOWN
        xyz[cloud["point_id"][keep]] = np.column_stack(
            [cloud[a][keep] for a in "xyz"]).astype(float)
        e = np.linalg.norm(xyz[obs.point[cam0]] - ref[k], axis=1)
        errors.append(e[np.isfinite(e)])
    e = np.concatenate(errors) * 1e3 if errors else np.zeros(0)
    if not e.size:
        return float("nan"), float("nan")
    return float(np.median(e)), float(np.percentile(e, 95))


def truth_sigma(variant: str, seed: int, frames: int, obs: Any) -> float:
    from surgrecon_cli.sim.simulate import LogBuilder
    from surgrecon_cli.sim.variants import variant_config

    builder = LogBuilder(variant_config(variant, seed=seed, frames=frames))
    poses = np.stack([builder.motion.camera_pose(c, builder.image_stamp(0, c)) for c in (0, 1)])
    both = np.full((int(obs.point.max()) + 1, 2, 2), np.nan)
    for c in (0, 1):
        both[obs.point[obs.camera == c], c] = obs.pixels[obs.camera == c]
    both = both[np.isfinite(both).all((1, 2))]
    return ground_truth_localisation_px(poses, builder.models, builder.motion.tissue_vertices(0.0),
                                        builder.mesh.faces, both)


def tracked_pixels(layout: RunLayout, n: int, n_frames: int) -> np.ndarray:
    """(F, N, C, 2) px: where each template point was tracked in frames 1..F (NaN = not)."""
    return np.stack([read_registration(layout, k, n).pixels for k in range(1, n_frames)])


def truth_tracking(variant: str, seed: int, frames: int, template_px: np.ndarray,
                   tracked: np.ndarray) -> float:
    from surgrecon_cli.sim.simulate import LogBuilder
    from surgrecon_cli.sim.variants import variant_config

    builder = LogBuilder(variant_config(variant, seed=seed, frames=frames))
    cams = range(template_px.shape[1])
    stamps = [[builder.image_stamp(k, c) for c in cams] for k in range(len(tracked) + 1)]
    poses = np.array([[builder.motion.camera_pose(c, t) for c, t in zip(cams, row,
                                                                         strict=True)]
                      for row in stamps])
    vertices = np.array([[builder.motion.tissue_vertices(t) for t in row] for row in stamps])
    return ground_truth_tracking_px(poses, builder.models, vertices, builder.mesh.faces,
                                    template_px, tracked)


def clip_truth_tracking(log: Any, gt_path: Path, template_px: np.ndarray,
                        tracked: np.ndarray) -> float:
    """`trk truth` of a real-texture clip with a ground truth beside it (the `breathe=A`
    clips): its rig is fixed and calibrated, so the ingested poses are the true ones, and
    the truth's surface is the same for every camera of a frame."""
    gt = load_ground_truth(gt_path)
    frames = len(tracked) + 1
    cams = template_px.shape[1]
    vertices = np.repeat(gt.vertices[:frames, None], cams, axis=1)
    return ground_truth_tracking_px(log.poses[:frames, :cams], list(log.models), vertices,
                                    gt.faces, template_px, tracked)


def rotation_deg(transform: np.ndarray) -> float:
    """Rotation angle (degrees) of a rigid transform (4, 4)."""
    c = np.clip((np.trace(transform[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)
    return float(np.degrees(np.arccos(c)))


def motion_frames(layout: RunLayout, log: Any, n: int) -> list[dict[str, float]]:
    """Per frame 1 on, against the scene's rigid motion (a rigid scene only: real logs with the
    rig fixed in the world; real_reference.rigid_scene_motion): the camera's motion from the
    previous frame (deg; px, median over template points in camera 0), the share of visible
    template points (the rigidly moved template inside a camera's image, 8 px margin) that
    the run tracked (a pixel in some camera), the labelled share of template points, the
    deforming share of the labelled, and the labelled positions against the rigidly moved
    template (median / p95, mm)."""
    template = read_template(layout).points
    motion = rigid_scene_motion(log)
    moved = np.einsum("kij,nj->kni", motion[:, :3, :3], template) + motion[:, None, :3, 3]
    rows = []
    for k in range(1, log.n_frames):
        row: dict[str, float] = {"frame": k}
        step = motion[k] @ np.linalg.inv(motion[k - 1])
        row["deg"] = rotation_deg(step) if np.isfinite(step).all() else float("nan")
        uv0 = [project(moved[f], log.poses[f, 0], log.models[0])[0] for f in (k - 1, k)]
        row["px"] = float(np.nanmedian(np.linalg.norm(uv0[1] - uv0[0], axis=1)))
        visible = np.zeros(n, bool)
        for c, m in enumerate(log.models):
            if not log.usable[k, c]:
                continue
            uv = project(moved[k], log.poses[k, c], m)[0]
            visible |= ((uv >= 8).all(1) & (uv[:, 0] < m.width - 8)
                        & (uv[:, 1] < m.height - 8))
        reg = read_registration(layout, k, n)
        tracked = np.isfinite(reg.pixels).all(2).any(1)
        row["visible"] = float(visible.mean())
        row["tracked_visible"] = float((tracked & visible).sum() / max(visible.sum(), 1))
        cloud = read_ply(layout.cloud(k))
        label = np.full(n, UNKNOWN)
        label[cloud["point_id"]] = cloud["label"]
        xyz = np.full((n, 3), np.nan)
        xyz[cloud["point_id"]] = np.column_stack([cloud[a] for a in "xyz"]).astype(float)
        lab = np.isin(label, (STATIC, SHIFTING, DEFORMING))
        row["labelled"] = float(lab.mean())
        row["deform_of_labelled"] = float((label == DEFORMING).sum() / max(lab.sum(), 1))
        e = np.linalg.norm(xyz[lab] - moved[k][lab], axis=1) * 1e3
        e = e[np.isfinite(e)]
        row["rigid_med_mm"] = float(np.median(e)) if e.size else float("nan")
        row["rigid_p95_mm"] = float(np.percentile(e, 95)) if e.size else float("nan")
        row["n_labelled"] = float(lab.sum())
        row["errors"] = e  # type: ignore[assignment]
        rows.append(row)
    return rows


def motion_summary(frames: list[dict[str, Any]]) -> dict[str, float]:
    """The clip's figures over frames 1 on (point-frame weighted where it matters)."""
    errors = np.concatenate([f.pop("errors") for f in frames])
    labelled = sum(f["n_labelled"] for f in frames)
    deform = sum(f["deform_of_labelled"] * f["n_labelled"] for f in frames)
    return {"deg_med": float(np.nanmedian([f["deg"] for f in frames])),
            "deg_max": float(np.nanmax([f["deg"] for f in frames])),
            "px_med": float(np.nanmedian([f["px"] for f in frames])),
            "px_max": float(np.nanmax([f["px"] for f in frames])),
            "trk_vis_min": float(min(f["tracked_visible"] for f in frames)),
            "trk_vis_mean": float(np.mean([f["tracked_visible"] for f in frames])),
            "labelled_share": float(np.mean([f["labelled"] for f in frames])),
            "deform_lab": deform / max(labelled, 1.0),
            "rigid_p95_mm": float(np.percentile(errors, 95)) if errors.size else float("nan")}


def measure(name: str, run: Path, variant: str | None, seed: int | None,
            frames: int, log_path: Path) -> dict[str, Any]:
    layout = RunLayout(run)
    log = load_ingested(layout.ingest_dir)
    n = len(read_template(layout).points)
    obs = read_observations(layout, n)
    summary = json.loads(layout.summary_json.read_text())
    quality = summary.get("quality", {}).get("per_frame", [])
    row: dict[str, Any] = {"name": name, "sigma_run": summary["noise"]["pixel_px"],
                           "sigma_loc": summary["noise"].get("localisation_px")}
    row["sigma_ncc"] = ncc_localisation_px(log, obs.pixels[obs.camera == 0])
    row["trk_run"] = summary["noise"].get("tracking_px")
    template_px = obs.pixels_by_camera(n, len(log.models))  # every camera, as the run
    stereo = np.isfinite(template_px[:, :2]).all((1, 2))
    row["sigma_disp"], _ = disparity_localisation_px(log, template_px[stereo, :2])
    tracked = tracked_pixels(layout, n, log.n_frames)
    if variant is not None and seed is not None:
        row["trk_truth"] = truth_tracking(variant, seed, frames, template_px, tracked)
    elif gt_path_beside(log_path).exists():  # a real-texture clip of known (breathing) motion
        row["trk_truth"] = clip_truth_tracking(log, gt_path_beside(log_path), template_px,
                                               tracked)
    else:
        row["trk_rigid"] = rigid_tracking_px(log.models, template_px, tracked)
    check = row.get("trk_truth", row.get("trk_rigid"))
    row["trk_ratio"] = row["trk_run"] / check if row["trk_run"] and check else None
    row["sigma_truth"] = (truth_sigma(variant, seed, frames, obs)
                          if variant is not None and seed is not None else None)
    row["tracked"] = float(np.mean([q["observed_fraction"] for q in quality]))
    row["outlier"] = float(np.mean([q["outlier_fraction"] for q in quality]))
    row.update(label_shares(layout, log.n_frames))
    reference = reference_positions(log, obs.pixels[obs.camera == 0])
    row["ref_median_mm"], row["ref_p95_mm"] = reference_errors(layout, log.n_frames, obs, n,
                                                               reference)
    if layout.evaluation_json.exists():
        ev = json.loads(layout.evaluation_json.read_text())
        row["macro_f1"] = ev["labels"]["overall"]["macro_f1"]
        row["calib_2sigma"] = ev["labels"].get("calibration_2sigma")
        labelled = ev["registration"].get("labelled") or {}
        row["true_median_mm"] = labelled.get("median_mm")
        row["true_p95_mm"] = labelled.get("p95_mm")
    if gt_path_beside(log_path).exists():
        row.update(truth_label_checks(layout, log.n_frames, log_path,
                                      (obs.point[obs.camera == 0], reference)))
    else:
        row["motion_frames"] = motion_frames(layout, log, n)
        row.update(motion_summary(row["motion_frames"]))
    verdict = summary.get("quality", {}).get("verdict", {})
    row["fits"] = verdict.get("fits")
    return row


def truth_label_checks(layout: RunLayout, n_frames: int, log_path: Path,
                       reference: tuple[np.ndarray, np.ndarray]) -> dict[str, float]:
    """Deforming where the truth is confidently rigid, truly moving point-frames called
    moving, labelled positions against the truth where it covers them, and the image
    reference's own error there (reference: template points (M,) and their reference
    positions (T, M, 3) m: a reference that is itself this far off cannot check a run
    closer); frames 1 on; module docstring."""
    from surgrecon_cli.config import Config
    from surgrecon_cli.core.classify.labels import rigid_fit_rms
    from surgrecon_cli.core.classify.rules import template_neighbourhoods
    from surgrecon_cli.core.evaluate.scoring import map_to_surface, on_mesh_rim
    gt = load_ground_truth(gt_path_beside(log_path))
    template = read_template(layout).points
    mapping = map_to_surface(template, gt.vertices[0], gt.faces)
    cfg = Config().classify
    nb = template_neighbourhoods(template, cfg.neighbourhood_mm, cfg.min_neighbours,
                                 cfg.max_neighbours)
    index, mask = nb.members()
    truth = np.load(layout.evaluation_errors)["true_labels"]
    start = mapping.follow(gt.vertices[0], gt.faces)  # the true frame-0 material points
    covered = ~on_mesh_rim(mapping, gt.faces)
    point, positions = reference
    ref_covered = covered[point]
    rigid = moving = rigid_deforming = moving_found = 0
    errors, ref_errors = [], []
    for k in range(1, n_frames):
        label = np.full(len(template), UNKNOWN)
        cloud = read_ply(layout.cloud(k))
        label[cloud["point_id"]] = cloud["label"]
        xyz = np.column_stack([cloud[a] for a in "xyz"]).astype(float)
        use = covered[cloud["point_id"]] & (cloud["label"] != UNKNOWN)
        true_k = mapping.follow(gt.vertices[k], gt.faces)
        errors.append(np.linalg.norm(xyz[use] - true_k[cloud["point_id"][use]], axis=1))
        ref_errors.append(np.linalg.norm(positions[k][ref_covered]
                                         - true_k[point[ref_covered]], axis=1))
        true_rms = rigid_fit_rms(start, true_k, index, mask) * 1e3
        confident = true_rms < 0.5 * cfg.deform_mm
        rigid += int(confident.sum())
        rigid_deforming += int((confident & (label == DEFORMING)).sum())
        truly = np.isin(truth[k], (SHIFTING, DEFORMING))
        moving += int(truly.sum())
        moving_found += int((truly & np.isin(label, (SHIFTING, DEFORMING))).sum())
    e = np.concatenate(errors) * 1e3
    r = np.concatenate(ref_errors) * 1e3
    r = r[np.isfinite(r)]
    return {"deforming_of_rigid": rigid_deforming / max(rigid, 1),
            "moving_detected": moving_found / moving if moving else float("nan"),
            "covered": float(covered.mean()),
            "covered_median_mm": float(np.median(e)) if e.size else float("nan"),
            "covered_p95_mm": float(np.percentile(e, 95)) if e.size else float("nan"),
            "ref_truth_median_mm": float(np.median(r)) if r.size else float("nan"),
            "ref_truth_p95_mm": float(np.percentile(r, 95)) if r.size else float("nan")}


COLUMNS = (("sigma_run", "σ run", ".3f"), ("sigma_ncc", "σ NCC", ".3f"),
           ("ratio", "run/NCC", ".2f"), ("sigma_loc", "σ loc", ".3f"),
           ("sigma_disp", "σ disp", ".3f"), ("ratio_disp", "loc/disp", ".2f"),
           ("sigma_truth", "σ truth", ".3f"),
           ("trk_run", "trk run", ".3f"), ("trk_rigid", "trk rigid", ".3f"),
           ("trk_truth", "trk truth", ".3f"), ("trk_ratio", "trk/check", ".2f"),
           ("tracked", "tracked", ".1%"), ("outlier", "outlier", ".1%"),
           ("static", "static", ".1%"), ("shifting", "shift", ".1%"),
           ("deforming", "deform", ".1%"), ("unknown", "unknown", ".1%"),
           ("deform_of_labelled", "deform|lab", ".1%"), ("ref_median_mm", "ref med", ".2f"),
           ("ref_p95_mm", "ref p95", ".2f"), ("ref_truth_median_mm", "refT med", ".2f"),
           ("ref_truth_p95_mm", "refT p95", ".2f"), ("macro_f1", "macroF1", ".3f"),
           ("calib_2sigma", "calib2σ", ".1%"), ("true_median_mm", "true med", ".2f"),
           ("true_p95_mm", "true p95", ".2f"), ("covered", "covered", ".1%"),
           ("covered_median_mm", "cov med", ".2f"), ("covered_p95_mm", "cov p95", ".2f"),
           ("deforming_of_rigid", "de|rigid", ".1%"),
           ("moving_detected", "moving det", ".1%"))


MOTION_COLUMNS = (("deg_med", "deg med", ".2f"), ("deg_max", "deg max", ".2f"),
                  ("px_med", "px med", ".1f"), ("px_max", "px max", ".1f"),
                  ("trk_vis_min", "trk|vis min", ".1%"), ("trk_vis_mean", "trk|vis", ".1%"),
                  ("labelled_share", "labelled", ".1%"), ("deform_lab", "deform|lab", ".1%"),
                  ("rigid_p95_mm", "rigid p95", ".2f"), ("fits", "fits", "s"))
FRAME_COLUMNS = (("frame", "frame", ".0f"), ("deg", "deg", ".2f"), ("px", "px", ".1f"),
                 ("visible", "visible", ".1%"), ("tracked_visible", "trk|vis", ".1%"),
                 ("labelled", "labelled", ".1%"), ("deform_of_labelled", "deform|lab", ".1%"),
                 ("rigid_med_mm", "rigid med", ".2f"), ("rigid_p95_mm", "rigid p95", ".2f"))


def print_motion(rows: list[dict[str, Any]], per_frame: bool) -> None:
    """The real-motion table (issue 24): a row per real log, and optionally its frames."""
    rows = [r for r in rows if "deg_med" in r]
    if not rows:
        return
    width = max(len(r["name"]) for r in rows) + 2
    print(f"\n{'real motion':<{width}}" + "".join(f"{h:>12}" for _, h, _ in MOTION_COLUMNS))
    for r in rows:
        print(f"{r['name']:<{width}}" + "".join(
            f"{str(r.get(k)) if s == 's' else _fmt(r.get(k), s):>12}"
            for k, _, s in MOTION_COLUMNS))
    if not per_frame:
        return
    for r in rows:
        print(f"\n{r['name']}:" + "".join(f"{h:>11}" for _, h, _ in FRAME_COLUMNS))
        for f in r["motion_frames"]:
            print(" " * (len(r["name"]) + 1)
                  + "".join(f"{_fmt(f.get(k), s):>11}" for k, _, s in FRAME_COLUMNS))


def _fmt(value: Any, spec: str) -> str:
    try:
        return format(float(value), spec) if value is not None else "-"
    except (TypeError, ValueError):
        return "-"


def print_table(rows: list[dict[str, Any]]) -> None:
    width = max(len(r["name"]) for r in rows) + 2
    print(f"{'log':<{width}}" + "".join(f"{h:>11}" for _, h, _ in COLUMNS))
    for r in rows:
        if "error" in r:
            print(f"{r['name']:<{width}}  failed: {r['error']}")
            continue
        for key, value, check in (("ratio", "sigma_run", "sigma_ncc"),
                                  ("ratio_disp", "sigma_loc", "sigma_disp")):
            r[key] = r[value] / r[check] if r.get(value) and r.get(check) else None
        print(f"{r['name']:<{width}}" + "".join(f"{_fmt(r.get(k), s):>11}" for k, _, s in COLUMNS))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--real", nargs="*", default=[], help="NAME=LOG.mcap[:CONFIG.toml]")
    ap.add_argument("--variants", nargs="*", default=list(DEFAULT_VARIANTS))
    ap.add_argument("--seeds", nargs="*", type=int, default=list(DEFAULT_SEEDS))
    ap.add_argument("--frames", type=int, default=12)
    ap.add_argument("--workdir", type=Path, default=Path("/tmp/surgrecon-real"))
    ap.add_argument("--code", type=Path, default=None, help="surgrecon source tree for runs")
    ap.add_argument("--fresh", action="store_true")
    ap.add_argument("--surgt", nargs="*", default=[],
                    help="clips of the SurgT sample, e.g. 'step=3,scale=0.5,length=16' "
                    "(benchmarks/surgt_clips.py; '' = the clip as it is)")
    ap.add_argument("--per-frame", action="store_true",
                    help="print each real log's frames in the real-motion table")
    args = ap.parse_args()
    exe = surgrecon_command()
    work = args.workdir
    (work / "logs").mkdir(parents=True, exist_ok=True)
    jobs: list[tuple[str, Path, Path | None, str | None, int | None]] = []
    for spec in args.real:
        name, _, rest = spec.partition("=")
        log, _, config = rest.partition(":")
        jobs.append((name, Path(log), Path(config) if config else None, None, None))
    for spec in args.surgt:
        clip = work / "clips" / clip_name(spec)
        if args.fresh or not (clip / "clip.mcap").exists():
            shutil.rmtree(clip, ignore_errors=True)
            clip.mkdir(parents=True)
            make_clip(spec, clip)
        jobs.append((clip_name(spec), clip / "clip.mcap", clip / "clip.toml", None, None))
    for variant in args.variants:
        for seed in args.seeds:
            jobs.append((f"{variant}-s{seed}", work / "logs" / f"{variant}-s{seed}.mcap", None,
                         variant, seed))
    rows = []
    for name, log, config, variant, seed in jobs:
        run, log_file = work / "runs" / name, work / f"{name}.log"
        try:
            if variant is not None and (args.fresh or not log.exists()):
                call([*exe, "simulate", str(log), "--variant", variant, "--seed", str(seed),
                      "--frames", str(args.frames), "-q"], log_file)
            if args.fresh and run.exists():
                shutil.rmtree(run)
            extra = ["--config", str(config)] if config else []
            call([*exe, "run", str(log), "-o", str(run), "-q", *extra], log_file, args.code)
            gt = gt_path_beside(log)
            if gt.exists():
                call([*exe, "evaluate", str(run), "--ground-truth", str(gt), "-q"], log_file)
            rows.append(measure(name, run, variant, seed, args.frames, log))
        except (RuntimeError, OSError, KeyError, ValueError) as exc:
            rows.append({"name": name, "error": str(exc)})
        print(f"  {name}: done", file=sys.stderr)
    print_table(rows)
    print_motion(rows, args.per_frame)
    (work / "real.json").write_text(json.dumps(rows, indent=1, default=float))


if __name__ == "__main__":
    main()
