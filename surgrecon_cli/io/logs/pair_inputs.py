"""Inputs of `surgrecon register-pair`: clouds, landmark and weight files, and the list of
pairs of a batch (a list file, or two folders of same-named PLYs)."""

from __future__ import annotations

import shlex
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...errors import InputError
from ..run.ply import read_ply


@dataclass(frozen=True)
class Cloud:
    """A PLY cloud: xyz (N, 3) metres, rgb (N, 3) uint8 or None, point_id (N,) or None."""

    xyz: np.ndarray
    rgb: np.ndarray | None
    point_id: np.ndarray | None


@dataclass(frozen=True)
class PairJob:
    """One registration of a batch: source onto target, written to output."""

    source: Path
    target: Path
    output: Path


def read_cloud(path: Path) -> Cloud:
    """The cloud of a PLY; colours given as floats (0..1) become uint8."""
    props = read_ply(path)
    xyz = np.stack([props["x"], props["y"], props["z"]], axis=1).astype(float)
    rgb = None
    if {"red", "green", "blue"} <= props.keys():
        rgb = np.stack([props["red"], props["green"], props["blue"]], axis=1)
        if not np.issubdtype(rgb.dtype, np.integer):
            rgb = np.clip(rgb, 0, 1) * 255
        rgb = rgb.astype(np.uint8)
    return Cloud(xyz, rgb, props.get("point_id"))


def read_landmarks(path: Path, n_source: int, n_target: int) -> np.ndarray:
    """(L, 2) int64 (source index, target index) from a CSV of `src_index,dst_index` rows
    (an optional header line; `#` starts a comment)."""
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read landmarks ({exc})") from exc
    rows: list[tuple[int, int]] = []
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
    pairs = np.array(rows, dtype=np.int64).reshape(-1, 2)
    if pairs.size and (pairs.min() < 0 or pairs[:, 0].max() >= n_source
                       or pairs[:, 1].max() >= n_target):
        raise InputError(f"{path}: indices must be in 0..{n_source - 1} (source) and "
                         f"0..{n_target - 1} (target)")
    return pairs


def read_weights(path: Path, n: int) -> np.ndarray:
    """(n,) data weights >= 0, one per source point, from a text/CSV file."""
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


def pairs_from_list(list_file: Path, out_dir: Path) -> list[PairJob]:
    """Pairs of a list file: one `SOURCE TARGET [OUTPUT]` per line (shell quoting for names
    with spaces; `#` comments). Relative paths are relative to the list file's folder; an
    output defaults to OUT_DIR/SOURCE-STEM_on_TARGET-STEM.ply, and a relative one is under
    OUT_DIR."""
    try:
        lines = list_file.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{list_file}: cannot read the list of pairs ({exc})") from exc
    base = list_file.parent
    jobs = []
    for number, line in enumerate(lines, 1):
        try:
            fields = shlex.split(line, comments=True)
        except ValueError as exc:
            raise InputError(f"{list_file}:{number}: {exc}") from exc
        if not fields:
            continue
        if len(fields) not in (2, 3):
            raise InputError(f"{list_file}:{number}: expected 'SOURCE TARGET [OUTPUT]', "
                             f"got {line!r}")
        source, target = base / fields[0], base / fields[1]
        output = (out_dir / fields[2] if len(fields) == 3
                  else out_dir / f"{source.stem}_on_{target.stem}.ply")
        jobs.append(PairJob(source, target, output))
    if not jobs:
        raise InputError(f"{list_file}: no pairs listed (one 'SOURCE TARGET [OUTPUT]' a line)")
    _check_unique_outputs(jobs, str(list_file))
    return jobs


def pairs_from_folders(source_dir: Path, target_dir: Path, out_dir: Path) -> list[PairJob]:
    """Every `NAME.ply` of SOURCE_DIR onto the same-named PLY of TARGET_DIR, written to
    OUT_DIR/NAME.ply; names present in only one folder are an error (listed)."""
    sources = {p.name: p for p in sorted(source_dir.glob("*.ply"))}
    targets = {p.name: p for p in sorted(target_dir.glob("*.ply"))}
    if not sources:
        raise InputError(f"{source_dir}: no .ply files to register")
    missing = sorted(set(sources) - set(targets))
    if missing:
        raise InputError(f"{target_dir}: no target for {len(missing)} source cloud(s) of "
                         f"{source_dir} (same file name expected)", details=tuple(missing))
    return [PairJob(sources[name], targets[name], out_dir / name) for name in sources]


def _check_unique_outputs(jobs: list[PairJob], where: str) -> None:
    seen: dict[Path, int] = {}
    for number, job in enumerate(jobs, 1):
        if job.output in seen:
            raise InputError(f"{where}: pairs {seen[job.output]} and {number} write the same "
                             f"output {job.output}; give an OUTPUT column")
        seen[job.output] = number
