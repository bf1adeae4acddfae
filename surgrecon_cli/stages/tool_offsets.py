"""Per-camera tool offsets fitted to an ingested run's images (`surgrecon fit-tools`).

When each camera group (e.g. a stereo pair) has its own hand-eye calibration and they
disagree, the kinematic tool lands beside the instrument in some cameras. For each group
and tool, `core.geometry.tool_fit.fit_tool_offset` finds the translation (world, m) that
lays the tool's shaft on the dark instrument in the group's images at one frame; a fit
whose contrast reaches `min_contrast` (and beats no move) becomes that tool's
`camera_offsets` entry for every camera of the group. Nothing is written to the run folder.
"""

from __future__ import annotations

import dataclasses
import shlex
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

import cv2
import numpy as np

from ..config import Config, ToolConfig
from ..core.geometry.tool import tool_name
from ..core.geometry.tool_fit import ShaftFit, fit_tool_offset
from ..errors import InputError
from ..io.run.ingest_store import load_ingested
from ..io.run.layout import RunLayout
from .common import tool_poses

ToolT = TypeVar("ToolT", bound=ToolConfig)


@dataclass(frozen=True)
class OffsetRow:
    """One group's fit for one tool: `offset_m` (3,) world translation, contrasts (grey
    levels) without and with it, `spread_m` (3,) how loosely the images pin it, `used`."""

    group: tuple[str, ...]
    tool: str
    offset_m: np.ndarray
    contrast_at_zero: float
    contrast: float
    spread_m: np.ndarray
    used: bool


def _groups(cameras: Sequence[str], groups: Sequence[Sequence[str]]) -> list[tuple[str, ...]]:
    if not groups:
        return [tuple(cameras)]
    known = set(cameras)
    out = []
    for group in groups:
        unknown = [c for c in group if c not in known]
        if unknown:
            raise InputError(f"--group names camera {unknown[0]!r}; the log's cameras are "
                             f"{', '.join(cameras)}")
        out.append(tuple(group))
    return out


def fit_run_tool_offsets(run_dir: Path, config: Config, frame: int = 0,
                         groups: Sequence[Sequence[str]] = (), radius_m: float = 0.004,
                         min_contrast: float = 40.0, search_m: float = 0.024
                         ) -> tuple[Config, list[OffsetRow]]:
    """Fit every tool's translation per camera group at `frame` of an ingested run; return
    the config with those fits as `camera_offsets` (entries of the fitted cameras replaced,
    others kept) and one row per group and tool. groups: camera names per group (default:
    all cameras, one group); radius_m the instruments' real shaft radius (dVRK 8 mm
    instruments: 4 mm)."""
    layout = RunLayout(run_dir)
    if not layout.ingest_dir.is_dir():
        raise InputError(f"{run_dir}: not ingested; run `surgrecon ingest LOG -o "
                         f"{shlex.quote(str(run_dir))}` first")
    log = load_ingested(layout.ingest_dir)
    if not 0 <= frame < log.n_frames:
        raise InputError(f"--frame {frame}: the run has frames 0..{log.n_frames - 1}")
    cfgs = config.tool_configs()
    tools = tool_poses(log, config, frame)
    index = {name: c for c, name in enumerate(log.cameras)}
    poses = log.usable_poses(frame)
    options = ShaftFit(radius_m=radius_m, search_m=search_m, max_turn_deg=0.0)
    rows: list[OffsetRow] = []
    offsets: list[dict[str, np.ndarray]] = [{} for _ in cfgs]
    for group in _groups(log.cameras, groups):
        cams = [index[c] for c in group if log.usable[frame, index[c]]]
        if not cams:
            continue
        grays = [cv2.cvtColor(log.load_image(frame, c), cv2.COLOR_RGB2GRAY) for c in cams]
        models = [log.models[c] for c in cams]
        for k, cfg in enumerate(cfgs):
            if not np.isfinite(tools[k]).all():
                continue
            fit = fit_tool_offset(grays, models, poses[cams], tools[k:k + 1], [cfg], options)
            used = fit.contrast >= min_contrast and fit.contrast > fit.contrast_at_zero
            rows.append(OffsetRow(group, tool_name(k), fit.move[:3, 3].copy(), fit.contrast_at_zero,
                                  fit.contrast, fit.spread_m, bool(used)))
            if used:
                offsets[k].update({c: fit.move[:3, 3] for c in group})
    tool = _with_offsets(config.tool, offsets[0])
    extra = tuple(_with_offsets(cfg, found) for cfg, found in zip(config.tools, offsets[1:],
                                                                    strict=True))
    return dataclasses.replace(config, tool=tool, tools=extra), rows


def _with_offsets(cfg: ToolT, found: dict[str, np.ndarray]) -> ToolT:
    """The tool config with the `camera_offsets` entries of the cameras in `found` replaced
    by the fits (other cameras' entries kept)."""
    kept = [e for e in cfg.camera_offsets if e.split()[0] not in found]
    new = [f"{c} {' '.join(f'{v:.4f}' for v in xyz)}" for c, xyz in found.items()]
    return dataclasses.replace(cfg, camera_offsets=tuple(kept + new))
