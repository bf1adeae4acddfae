"""Where a classified simulator run loses its labels, and what the truth allows at all.

    PYTHONPATH=$PWD .venv/bin/python benchmarks/label_losses.py RUN GT.npz [RUN GT.npz ...]

For runs of `benchmarks/accuracy.py` (RUN = WORKDIR/runs/V-sS-f12-640x480, GT =
WORKDIR/logs/V-sS-f12-640x480.gt.npz), frames 1 on, every template point scored as
`surgrecon evaluate` does (its nearest true vertex's label; the material point it maps to
followed through the frames):

- the confusion (rows: truth static / shifting / deforming; columns: the run's labels, then
  unknown);
- per true class, the step of core/classify/rules.classify_frame that decided each
  point-frame, recomputed from the run's registration with stages/classify's evidence
  (`agree` is the share where that recomputation gives the stored label; points that
  core/classify/quality.unsupported_points makes unknown differ): `unknown` (displacement σ
  above classify.max_sigma_mm and the displacement within it), `< static` (measured
  displacement below classify.static_mm), `motion n.s.` (displacement within its noise),
  `rms < deform` (the registered neighbourhood's rigid-fit RMS below classify.deform_mm),
  `departure n.s.` (the RMS reaches it, but the neighbourhood's departure from one rigid
  motion is within the frame's calibrated noise), `deforming`;
  with each step's median true displacement, the median error of the measured position
  against the true one (mm) and the median measured displacement;
- three bounds, macro-F1 and deforming precision / recall, frames 1 on:
  `truth rule on template` the spec's rule applied to the true positions of the template
  points over their classify neighbourhoods (what the template's sampling allows);
  `classifier on truth` the run's classifier (σ, covariances, tests) fed the true
  displacements; `... + noise` fed the true displacements plus noise drawn from the run's
  own covariances (the independent part per point, the shared pose part once per frame),
  seed 0: what the tests make of data as noisy as the run says its data are; `... x
  measured scale` the same with the independent part scaled by what the frame's
  neighbourhoods show (departure.noise_scale's lower-quartile ratio, not floored at 1);
- the labels' sensitivity: the truly deforming point-frames whose true rigid-fit RMS is
  below / at least the run's deformation floor (labels.npz floor_mm: the smallest departure
  along the lines of sight labelled deforming), and the share of each labelled deforming;
  neighbourhoods with a member over the truth's holes or beyond its border
  (scoring.on_mesh_rim: the truth is wrong there) are left out.
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

import numpy as np

from surgrecon_cli.config import Config
from surgrecon_cli.config.load import load_config
from surgrecon_cli.core.classify import departure, rules
from surgrecon_cli.core.classify.labels import UNKNOWN
from surgrecon_cli.core.evaluate.evaluation import true_point_labels
from surgrecon_cli.core.evaluate.scoring import label_scores, map_to_surface, on_mesh_rim
from surgrecon_cli.io.logs.ground_truth import load_ground_truth
from surgrecon_cli.io.run.artefacts import read_labels, read_registration
from surgrecon_cli.io.run.ingest_store import load_ingested
from surgrecon_cli.io.run.layout import RunLayout
from surgrecon_cli.stages import classify as stage

STEPS = ("unknown", "< static", "motion n.s.", "departure n.s.", "rms < deform", "deforming")
CLASSES = ("static", "shifting", "deforming")


def decisions(template: np.ndarray, registered: np.ndarray, status: np.ndarray,
              evidence: rules.Evidence, nb: rules.Neighbourhoods,
              config: Config) -> np.ndarray:
    """The step (N,) index into STEPS that decides each point's label, as in
    rules.classify_frame with evidence and measure "rigid_rms" (dynamic points only reach
    the departure and RMS steps)."""
    cfg = config.classify
    n = len(template)
    labels = rules.classify_frame(template, rules.RegisteredFrame(registered, None, status), nb,
                                  cfg, evidence=evidence)
    moved = labels.displacement_mm >= cfg.static_mm
    known, significant = rules.labelled_motion(registered - template, evidence, cfg)
    step = np.full(n, STEPS.index("deforming"))
    dynamic = known & moved & significant
    rms = np.where(dynamic, labels.deformation_mm, np.nan)
    shifting = dynamic & (labels.labels == 1)
    step[shifting & (rms >= cfg.deform_mm)] = STEPS.index("departure n.s.")
    step[shifting & ~(rms >= cfg.deform_mm)] = STEPS.index("rms < deform")
    step[known & moved & ~significant] = STEPS.index("motion n.s.")
    step[known & ~moved] = STEPS.index("< static")
    step[~known] = STEPS.index("unknown")
    return step


def measured_scale(template: np.ndarray, registered: np.ndarray, evidence: rules.Evidence,
                   nb: rules.Neighbourhoods, config: Config) -> float:
    """The frame's departures over what its covariances predict, as departure.noise_scale reads
    it but not floored at 1 (below 1: the covariances overstate the scatter)."""
    cfg = config.classify
    judged = np.flatnonzero(rules.labelled_motion(registered - template, evidence, cfg)[0])
    ratio = departure.departure_ratio(*departure.departure_statistic(
        template, evidence.measured, evidence.departure_cov, nb, judged),
        departure.SCALE_QUANTILE)
    return 1.0 if ratio is None else ratio


def noisy_truth(template: np.ndarray, moved: np.ndarray, evidence: rules.Evidence,
                scale: float, rng: np.random.Generator) -> np.ndarray:
    """Template (N, 3) m + the true displacement (moved, (N, 3) m, from frame 0) + noise
    from the evidence's covariances: the independent part per point (times `scale`), the
    shared (pose) part drawn once from its median over the points."""
    independent = scale * np.nan_to_num(evidence.departure_cov, nan=0.0, posinf=0.0)
    shared = np.nan_to_num(evidence.displacement_cov - evidence.departure_cov, nan=0.0,
                           posinf=0.0)
    chol = np.linalg.cholesky(independent + np.eye(3) * 1e-14)
    noise = np.einsum("nij,nj->ni", chol, rng.standard_normal(moved.shape))
    common = np.linalg.cholesky(np.median(shared, axis=0) + np.eye(3) * 1e-14)
    return template + moved + noise + common @ rng.standard_normal(3)


def analyse(run_dir: Path, gt_path: Path) -> None:
    """Print one run's losses and bounds (module docstring)."""
    layout = RunLayout(run_dir.absolute())
    config = load_config(layout.root / "config.toml")
    cfg = config.classify
    template, nb, template_noise = stage.template_and_neighbourhoods(layout.root, config)
    gt = load_ground_truth(gt_path)
    mapping = map_to_surface(template, gt.vertices[0], gt.faces)
    truth = true_point_labels(mapping, gt.faces, gt.labels)
    start = mapping.follow(gt.vertices[0], gt.faces)
    log = load_ingested(layout.ingest_dir)
    stored_labels = read_labels(layout, truth.shape)
    stored = stored_labels.labels
    members, member_mask = nb.members(np.arange(len(template)))
    on_rim = (on_mesh_rim(mapping, gt.faces)[members] & member_mask).any(1)
    rng = np.random.default_rng(0)
    rows: dict[str, list[np.ndarray]] = {k: [] for k in (
        "truth", "label", "step", "true_disp", "error", "disp", "rule", "clean", "noisy",
        "scaled", "true_rms", "floor", "rim")}
    scales = []
    agree = 0
    for k in range(1, log.n_frames):
        reg = read_registration(layout, k, len(template))
        registered, evidence = stage.frame_inputs(reg, template_noise, log, k, config)
        step = decisions(template, registered, reg.status, evidence, nb, config)
        recomputed = rules.classify_frame(template, rules.RegisteredFrame(
            registered, None, reg.status), nb, cfg, evidence=evidence).labels
        agree += int((recomputed == stored[k]).sum())
        true_now = mapping.follow(gt.vertices[k], gt.faces)
        moved = true_now - start
        unseen = ~np.isfinite(registered).all(1)
        rows["truth"].append(truth[k])
        rows["label"].append(stored[k])
        rows["step"].append(step)
        rows["true_disp"].append(np.linalg.norm(moved, axis=1) * 1e3)
        rows["error"].append(np.linalg.norm(evidence.measured - true_now, axis=1) * 1e3)
        rows["disp"].append(np.linalg.norm(registered - template, axis=1) * 1e3)
        rms = rules.rigid_rms_mm(start, true_now, nb)
        rows["true_rms"].append(rms)
        rows["floor"].append(stored_labels.floor_mm[k])
        rows["rim"].append(on_rim)
        rows["rule"].append(np.where(np.linalg.norm(moved, axis=1) * 1e3 < cfg.static_mm, 0,
                                     np.where(rms > cfg.deform_mm, 2, 1)))
        scales.append(measured_scale(template, registered, evidence, nb, config))
        for name, positions in (("clean", template + moved),
                                ("noisy", noisy_truth(template, moved, evidence, 1.0, rng)),
                                ("scaled", noisy_truth(template, moved, evidence, scales[-1],
                                                       rng))):
            positions[unseen] = np.nan
            rows[name].append(rules.classify_frame(
                template, rules.RegisteredFrame(positions, None, reg.status), nb, cfg,
                evidence=replace(evidence, measured=positions)).labels)
    data = {k: np.concatenate(v) for k, v in rows.items()}
    t = data["truth"]
    scores = label_scores(data["label"], t)
    print(f"\n{run_dir.name}: macro-F1 {scores['macro_f1']:.3f} (frames 1 on), "
          f"recomputed labels agree {agree / t.size:.1%}")
    print("  truth \\ label   static  shifting  deforming  unknown")
    for name, row in zip(CLASSES, scores["confusion"], strict=True):
        print(f"  {name:14s}" + "".join(f"{v:>10d}" for v in row))
    for code, name in enumerate(CLASSES):
        true_class = t == code
        print(f"  truly {name} ({true_class.sum()}): step  n  true disp / position error / "
              "measured disp (medians, mm)")
        for i, step_name in enumerate(STEPS):
            m = true_class & (data["step"] == i)
            if m.any():
                print(f"    {step_name:15s}{m.sum():6d}  {np.median(data['true_disp'][m]):5.2f} "
                      f"/ {np.nanmedian(data['error'][m]):5.2f} / "
                      f"{np.nanmedian(data['disp'][m]):5.2f}")
    for name, key in (("truth rule on template", "rule"), ("classifier on truth", "clean"),
                      ("classifier on truth + noise", "noisy"),
                      ("... noise x measured scale", "scaled")):
        s = label_scores(data[key], t)
        de = s["per_class"]["deforming"]
        print(f"  bound, {name:28s} macro-F1 {s['macro_f1']:.3f}  P/R de "
              f"{de['precision']:.3f} / {de['recall']:.3f}")
    deforming = (t == CLASSES.index("deforming")) & ~data["rim"] & np.isfinite(data["floor"])
    for name, side in (("below", data["true_rms"] < data["floor"]),
                       ("at or above", data["true_rms"] >= data["floor"])):
        m = deforming & side
        found = float(np.mean(data["label"][m] == CLASSES.index("deforming"))) if m.any() \
            else float("nan")
        print(f"  truly deforming, true RMS {name:11s} the floor (median "
              f"{np.nanmedian(data['floor'][deforming]) if deforming.any() else np.nan:.2f} mm): "
              f"{m.sum():6d}, labelled deforming {found:.2f}")
    unknown_share = float((data["label"] == UNKNOWN).mean())
    print(f"  unknown {unknown_share:.1%}; departures / covariances (unfloored noise scale) "
          f"median over frames {np.median(scales):.2f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("pairs", nargs="+", help="RUN GT.npz [RUN GT.npz ...]")
    args = ap.parse_args()
    if len(args.pairs) % 2:
        ap.error("give RUN and GT.npz in pairs")
    for run_dir, gt_path in zip(args.pairs[::2], args.pairs[1::2], strict=True):
        analyse(Path(run_dir), Path(gt_path))


if __name__ == "__main__":
    main()
