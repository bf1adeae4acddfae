"""`surgrecon register-pair SRC.ply DST.ply -o OUT.ply`: non-rigid registration of two clouds."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import click

from .common import common_options, progress

log = logging.getLogger(__name__)


def _read_indices_csv(path: Path) -> Any:
    """(L, 2) int array from a CSV of `src_index,dst_index` rows (an optional header)."""
    import numpy as np

    from ..errors import InputError

    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read landmarks ({exc})") from exc
    rows = []
    for number, line in enumerate(lines, 1):
        text = line.split("#", 1)[0].strip()
        if not text:
            continue
        parts = [p.strip() for p in text.split(",")]
        if len(parts) != 2 or not all(p.lstrip("-").isdigit() for p in parts):
            if not rows and number == 1:  # a header line
                continue
            raise InputError(f"{path}:{number}: expected 'src_index,dst_index', got {line!r}")
        rows.append((int(parts[0]), int(parts[1])))
    return np.array(rows, dtype=np.int64).reshape(-1, 2)


def _read_weights(path: Path, n: int) -> Any:
    import numpy as np

    from ..errors import InputError

    try:
        values = np.loadtxt(path, dtype=float, ndmin=1, comments="#", delimiter=",")
    except (OSError, ValueError) as exc:
        raise InputError(f"{path}: cannot read weights ({exc})") from exc
    if values.shape != (n,):
        raise InputError(f"{path}: expected {n} weights (one per source point), got {values.size}")
    bad = np.flatnonzero(~np.isfinite(values) | (values < 0))
    if bad.size:
        raise InputError(f"{path}: weight {bad[0] + 1} is {values[bad[0]]}; weights must be "
                         "finite and >= 0")
    return values


def _cloud(path: Path) -> tuple[Any, Any, Any]:
    """xyz (N, 3) float64, rgb (N, 3) uint8 or None, point_id (N,) or None, from a PLY."""
    import numpy as np

    from ..io.ply import read_ply

    props = read_ply(path)
    xyz = np.stack([props["x"], props["y"], props["z"]], axis=1).astype(float)
    rgb = None
    if {"red", "green", "blue"} <= props.keys():
        rgb = np.stack([props["red"], props["green"], props["blue"]], axis=1)
        if not np.issubdtype(rgb.dtype, np.integer):
            rgb = np.clip(rgb, 0, 1) * 255
        rgb = rgb.astype(np.uint8)
    return xyz, rgb, props.get("point_id")


@click.command("register-pair")
@click.argument("source", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.argument("target", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option("-o", "--output", type=click.Path(dir_okay=False, path_type=Path), required=True,
              help="Registered source cloud (PLY).")
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
def register_pair_cmd(source: Path, target: Path, output: Path, apply_path: Path | None,
                      apply_out: Path | None, landmarks: Path | None, weights: Path | None,
                      use_ids: bool, config: Any, quiet: bool) -> None:
    """Register SOURCE non-rigidly onto TARGET (sparse l1 energy, ADMM; Su et al. 2019).

    Writes SOURCE moved onto TARGET with its colours, point_id, residual (m) and the extra
    properties `correspondence` (target index, -1 = none) and `outlier` (0/1).

    \b
    Example:
      surgrecon register-pair frame0.ply frame7.ply -o frame0_on_7.ply \\
          --landmarks pairs.csv --set registration.alpha=0.1
    """
    import time

    import numpy as np

    from ..errors import InputError
    from ..io.ply import write_cloud_ply
    from ..registration import apply_transforms, register

    src, src_rgb, src_ids = _cloud(source)
    dst, dst_rgb, dst_ids = _cloud(target)
    lm = _read_indices_csv(landmarks) if landmarks else None
    if lm is not None and lm.size and (lm.min() < 0 or lm[:, 0].max() >= len(src)
                                       or lm[:, 1].max() >= len(dst)):
        raise InputError(f"{landmarks}: indices must be in 0..{len(src) - 1} (source) and "
                         f"0..{len(dst) - 1} (target)")
    w = _read_weights(weights, len(src)) if weights else None
    target_ids = None
    if use_ids:
        if dst_ids is None:
            raise InputError(f"{target}: --use-ids needs a 'point_id' vertex property")
        target_ids = np.where(dst_ids < len(src), dst_ids, -1).astype(np.int64)
    cfg = config.registration
    t0 = time.perf_counter()
    with progress(quiet)(total=cfg.outer_iterations + 1, desc="register", unit="step") as bar:

        def on_step(step: int, state: dict[str, Any]) -> None:
            bar.update(1)
            if "median_residual_mm" in state:
                bar.set_postfix(median_mm=f"{state['median_residual_mm']:.3f}")

        result = register(src, dst, src_rgb, dst_rgb, cfg, target_ids=target_ids,
                          weights=w, landmarks=lm, callback=on_step)
    seconds = time.perf_counter() - t0
    ids = src_ids if src_ids is not None else np.arange(len(src))
    write_cloud_ply(output, result.registered, rgb=src_rgb, point_id=ids,
                    residual=result.residuals,
                    extra={"correspondence": result.correspondences.astype(np.int32),
                           "outlier": result.outliers.astype(np.uint8)})
    if apply_path is not None:
        other, other_rgb, other_ids = _cloud(apply_path)
        moved = apply_transforms(result, src, other)
        out = apply_out or output.parent / f"{apply_path.stem}.registered.ply"
        write_cloud_ply(out, moved, rgb=other_rgb, point_id=other_ids)
        log.info("moved %d points of %s -> %s", len(other), apply_path, out)
    res_mm = result.residuals[np.isfinite(result.residuals)] * 1e3
    med = float(np.median(res_mm)) if res_mm.size else float("nan")
    p95 = float(np.percentile(res_mm, 95)) if res_mm.size else float("nan")
    click.echo(f"registered {len(src)} points onto {len(dst)}: residual median {med:.3f} mm, "
               f"p95 {p95:.3f} mm, {int(result.outliers.sum())} outliers, {seconds:.2f} s "
               f"-> {output}")
