"""`surgrecon register-pair`: non-rigid registration of two clouds, or of many pairs in one
process (a list file, or two folders of same-named PLYs)."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import click

from .common import common_options, progress

log = logging.getLogger(__name__)

SUMMARY_COLUMNS = ("source", "target", "output", "source_points", "target_points",
                   "supported", "unsupported", "residual_median_mm", "residual_p95_mm",
                   "along_surface_median_mm", "error_estimate_median_mm",
                   "error_estimate_p95_mm", "error_estimate_sees", "outliers",
                   "colour_weight_mm", "colour_decision", "colour_strays", "followed",
                   "rotation_deg", "scale", "seconds", "error")


def _register_one(job: Any, cfg: Any, *, use_ids: bool, landmarks: Path | None = None,
                  weights: Path | None = None, bar: Any = None) -> tuple[Any, Any, dict[str, Any]]:
    """Read, register and write one pair; returns (source cloud, result, summary row)."""
    import time

    import numpy as np

    from ..errors import InputError
    from ..io.logs.pair_inputs import read_cloud, read_landmarks, read_weights
    from ..io.run.ply import write_cloud_ply
    from ..registration import register_pair

    src, dst = read_cloud(job.source), read_cloud(job.target)
    lm = read_landmarks(landmarks, len(src.xyz), len(dst.xyz)) if landmarks else None
    w = read_weights(weights, len(src.xyz)) if weights else None
    target_ids = None
    if use_ids:
        if dst.point_id is None:
            raise InputError(f"{job.target}: --use-ids needs a 'point_id' vertex property")
        target_ids = np.where(dst.point_id < len(src.xyz), dst.point_id, -1).astype(np.int64)

    def on_step(step: int, state: dict[str, Any]) -> None:
        if bar is not None and "median_residual_mm" in state:
            bar.set_postfix(median_mm=f"{state['median_residual_mm']:.3f}")

    start = time.perf_counter()
    result = register_pair(src.xyz, dst.xyz, src.rgb, dst.rgb, cfg, target_ids=target_ids,
                           weights=w, landmarks=lm, callback=on_step)
    seconds = time.perf_counter() - start
    ids = src.point_id if src.point_id is not None else np.arange(len(src.xyz))
    write_cloud_ply(job.output, result.registered, rgb=src.rgb, point_id=ids,
                    residual=result.residuals,
                    extra={"correspondence": result.correspondences.astype(np.int32),
                           "outlier": result.outliers.astype(np.uint8),
                           "supported": result.supported.astype(np.uint8)})
    return src, result, _summary_row(job, result, src.xyz, len(dst.xyz), seconds)


def _summary_row(job: Any, result: Any, source: Any, n_target: int,
                 seconds: float) -> dict[str, Any]:
    """What the run can know of its own error (no ground truth): mm, degrees."""
    import numpy as np

    from ..core.evaluate.scoring import distance_stats_mm
    from ..core.registration.pair import error_estimate_mm

    est_median, est_p95, sees = error_estimate_mm(result, source)
    residual = distance_stats_mm(result.residuals)
    rigid = result.stats[0]
    cos = (np.trace(rigid["rotation"]) - 1.0) / 2.0
    return {"source": str(job.source), "target": str(job.target), "output": str(job.output),
            "source_points": len(result.registered), "target_points": n_target,
            "supported": int(result.supported.sum()),
            "unsupported": int((~result.supported).sum()),
            "residual_median_mm": residual["median_mm"],
            "residual_p95_mm": residual["p95_mm"],
            "along_surface_median_mm": distance_stats_mm(result.along_surface)["median_mm"],
            "error_estimate_median_mm": est_median, "error_estimate_p95_mm": est_p95,
            "error_estimate_sees": sees, "outliers": int(result.outliers.sum()),
            "colour_weight_mm": float(rigid["colour_weight_mm"]),
            "colour_decision": rigid["colour_reason"], "colour_strays": rigid["colour_strays"],
            "followed": rigid["followed"],
            "rotation_deg": float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))),
            "scale": float(rigid["scale"]), "seconds": seconds, "error": ""}


def _summary_line(row: dict[str, Any]) -> str:
    """The row in words, each figure labelled with what it measures."""
    colour = (f"colour {row['colour_weight_mm']:.0f} mm per RGB unit"
              if row["colour_weight_mm"] > 0 else "colour not used")
    return (f"registered {row['source_points']} points onto {row['target_points']} ({colour}: "
            f"{row['colour_decision']}; {row['colour_strays']} target points of stray colour "
            f"left out; rigid start {row['rotation_deg']:.1f} deg, scale {row['scale']:.3f}): "
            f"{row['supported']} on target surface, {row['unsupported']} without; "
            f"{row['followed']} followed their supported neighbours (those without and, with "
            f"colour, those matched onto the rim of a cut target; without colour within 2-5 % "
            f"of the diagonal of them, with colour within 1 %, beyond which they do not move); "
            f"estimated error (no ground truth) median "
            f"{row['error_estimate_median_mm']:.3f} mm, p95 {row['error_estimate_p95_mm']:.3f} "
            f"mm, it sees {row['error_estimate_sees']}; {row['outliers']} outliers; "
            f"{row['seconds']:.2f} s -> {row['output']}")


def _batch_jobs(source: Path | None, target: Path | None, pairs: Path | None,
                output: Path) -> list[Any] | None:
    """The batch's pairs, or None for a single pair (SOURCE and TARGET files)."""
    from ..io.logs.pair_inputs import pairs_from_folders, pairs_from_list

    if pairs is not None:
        if source is not None or target is not None:
            raise click.UsageError("give either SOURCE TARGET or --pairs LIST, not both")
        return pairs_from_list(pairs, output)
    if source is None or target is None:
        raise click.UsageError("give SOURCE and TARGET (files or folders), or --pairs LIST")
    if source.is_dir() != target.is_dir():
        raise click.UsageError("SOURCE and TARGET must both be files or both be folders")
    return pairs_from_folders(source, target, output) if source.is_dir() else None


def _run_batch(jobs: list[Any], output: Path, cfg: Any, use_ids: bool, quiet: bool) -> None:
    """Register every pair in this process; a failing pair is recorded and the rest go on.
    OUT/pairs.csv (written last, atomically) has one row per pair."""
    from ..errors import InputError, SurgReconError
    from ..io.run.metrics import write_csv

    rows, failed = [], []
    with progress(quiet)(jobs, desc="register-pair", unit="pair") as bar:
        for job in bar:
            try:
                rows.append(_register_one(job, cfg, use_ids=use_ids, bar=bar)[2])
            except SurgReconError as exc:
                failed.append(f"{job.source} -> {job.target}: {exc}")
                rows.append({"source": str(job.source), "target": str(job.target),
                             "output": "", "error": str(exc)})
                continue
            log.info("%s", _summary_line(rows[-1]))
    write_csv(output / "pairs.csv", SUMMARY_COLUMNS, rows)
    done = [r for r in rows if not r["error"]]
    seconds = sum(r["seconds"] for r in done)
    click.echo(f"registered {len(done)} of {len(jobs)} pairs in {seconds:.2f} s of registration "
               f"-> {output} (summary {output / 'pairs.csv'})")
    if failed:
        raise InputError(f"{len(failed)} of {len(jobs)} pairs failed; the others are written",
                         details=tuple(failed))


@click.command("register-pair")
@click.argument("source", required=False, type=click.Path(exists=True, path_type=Path))
@click.argument("target", required=False, type=click.Path(exists=True, path_type=Path))
@click.option("-o", "--output", type=click.Path(path_type=Path), required=True,
              help="Registered source cloud (PLY); a folder for a batch.")
@click.option("--pairs", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="Batch: a text file of 'SOURCE TARGET [OUTPUT]' lines, paths relative to it.")
@click.option("--apply", "apply_path", type=click.Path(exists=True, dir_okay=False,
              path_type=Path), help="Also move this cloud with the registration's transforms.")
@click.option("--apply-out", type=click.Path(dir_okay=False, path_type=Path),
              help="Where --apply writes (default: OUT's folder, NAME.registered.ply).")
@click.option("--landmarks", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="CSV of known pairs 'src_index,dst_index', matched with full weight.")
@click.option("--weights", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="Text file, one data weight per source point (0 = not observed).")
@click.option("--use-ids", is_flag=True,
              help="Target 'point_id' values are source indices (known correspondences).")
@common_options
def register_pair_cmd(source: Path | None, target: Path | None, output: Path,
                      pairs: Path | None, apply_path: Path | None, apply_out: Path | None,
                      landmarks: Path | None, weights: Path | None, use_ids: bool, config: Any,
                      quiet: bool) -> None:
    """Register SOURCE non-rigidly onto TARGET (sparse l1 energy, ADMM; Su et al. 2019).

    Writes SOURCE moved onto TARGET with its colours, point_id, residual (m: distance to
    the target's surface, NaN where there is none) and the extra properties
    `correspondence` (target index, -1 = none), `outlier` (0/1) and `supported` (0/1: had
    target surface near it; 0 = followed its neighbours, e.g. the target was cut there).

    \b
    Colour is used when both PLYs carry red/green/blue: its weight is measured from the
    target's texture on the points whose colour agrees with their neighbours (target points
    of stray colour are left out; 0 = colour not informative), or set in mm per RGB unit.
    Source points without target surface near them move with their supported neighbours
    (within 2-5 % of the cloud's diagonal of them; farther, they follow the smooth motion
    weakly pulled towards not moving).
    The keys that matter (--set registration.KEY=VALUE):
      color_weight_mm        0 = automatic; e.g. 50: a full RGB unit costs 50 mm
      max_correspondence_mm  5: matches farther than this are dropped (mm)
      alpha                  0.05: final smoothness; larger = stiffer motion
      outer_iterations       6: more lets matches slide further (slower)
      global_init            auto|on|off: coarse rotation + scale search first
      rigid_iterations       30: trimmed ICP (0 = no rigid start)

    Many pairs run in one process (imports and start-up paid once): SOURCE and TARGET
    folders register every NAME.ply onto the same-named target into the folder -o, or
    --pairs LIST names the pairs; OUT/pairs.csv sums them up, and a pair that fails is
    recorded there while the others go on (exit 2 if any failed).

    \b
    Examples:
      surgrecon register-pair frame0.ply frame7.ply -o frame0_on_7.ply \\
          --landmarks pairs.csv --set registration.color_weight_mm=50
      surgrecon register-pair before/ after/ -o registered/
      surgrecon register-pair --pairs pairs.txt -o registered/
    """
    jobs = _batch_jobs(source, target, pairs, output)
    cfg = config.registration
    if jobs is not None:
        if landmarks or weights or apply_path:
            raise click.UsageError("--landmarks, --weights and --apply take a single pair")
        _run_batch(jobs, output, cfg, use_ids, quiet)
        return
    from ..io.logs.pair_inputs import PairJob, read_cloud
    from ..io.run.ply import write_cloud_ply
    from ..registration import apply_transforms

    assert source is not None and target is not None
    with progress(quiet)(total=1, desc="register", unit="pair") as bar:
        src, result, row = _register_one(PairJob(source, target, output), cfg, use_ids=use_ids,
                                         landmarks=landmarks, weights=weights, bar=bar)
    if apply_path is not None:
        other = read_cloud(apply_path)
        moved = apply_transforms(result, src.xyz, other.xyz)
        out = apply_out or output.parent / f"{apply_path.stem}.registered.ply"
        write_cloud_ply(out, moved, rgb=other.rgb, point_id=other.point_id)
        log.info("moved %d points of %s -> %s", len(other.xyz), apply_path, out)
    click.echo(_summary_line(row))
