"""Views of a labelled cloud: which frames are worth showing, and which camera sees a set of
3D points best with the tool hidden. Pure numpy; no I/O."""

from __future__ import annotations

import dataclasses

import numpy as np

from ...config import ToolConfig
from ..geometry.cameras import CameraModel, in_image, project
from ..geometry.tool import tool_pixel_mask
from .labels import DEFORMING, SHIFTING


def pick_frames(counts: dict[int, np.ndarray] | None, n_frames: int) -> list[int]:
    """Frames worth rendering, sorted: 0, the most deforming, the most shifting, the last
    (counts: points per frame (T,) of each label code, or None: only the first and the
    last)."""
    picks = {0, n_frames - 1}
    if counts is not None and n_frames > 1:
        for code in (DEFORMING, SHIFTING):
            if code in counts and counts[code].max() > 0:
                picks.add(int(np.argmax(counts[code])))
    return sorted(picks)[:4]


def best_camera(xyz: np.ndarray, poses: np.ndarray, models: tuple[CameraModel, ...],
                usable: np.ndarray, tool_pose: np.ndarray,
                tool: ToolConfig) -> tuple[int, np.ndarray] | None:
    """The usable camera seeing most of the points xyz (N, 3) m, with their pixels (N, 2)
    (NaN where not in the image or hidden by the tool); None if no camera sees any.

    poses (C, 4, 4) camera-to-world, usable (C,) bool, tool_pose (4, 4) tool tip in world
    (NaN: no tool to hide behind); the tool is its bare capsule (no pixel margin)."""
    bare_tool = dataclasses.replace(tool, mask_margin_px=0.0)
    best: tuple[int, np.ndarray] | None = None
    best_count = 0
    for c, model in enumerate(models):
        if not usable[c]:
            continue
        uv, z = project(np.nan_to_num(xyz), poses[c], model)
        ok = (z > 0) & in_image(uv, model) & np.isfinite(xyz).all(1)
        ok[ok] &= ~tool_pixel_mask(uv[ok], model, poses[c], tool_pose, bare_tool)
        if ok.sum() > best_count:
            best_count = int(ok.sum())
            best = (c, np.where(ok[:, None], uv, np.nan))
    return best
