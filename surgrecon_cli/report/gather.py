"""Report layer 1: read a run folder into `RunData` (None where a stage is not done) and the
images behind the labelled-cloud views.

Every artefact is read through io/artefacts.py and io/ingest_store.py, whose paths come from
io/run_layout.py; nothing is computed here beyond stacking the registered frames.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..config import ToolConfig
from ..core.views import best_camera, pick_frames
from ..errors import RunFolderError
from ..io.artefacts import (
    read_evaluation,
    read_evaluation_errors,
    read_labels,
    read_registration,
    read_template,
    read_template_summary,
)
from ..io.ingest_store import IngestedLog, load_ingested
from ..io.run_folder import RunFolder
from ..io.run_layout import RunLayout


@dataclass(frozen=True)
class RegisteredFrames:
    """Every registered frame stacked, T frames x N template points; frame 0 is the template
    (no target, not solved).

    positions (T, N, 3) m; status (T, N) reprojection check; residual (T, N) m to the target,
    meaningful where has_target (T, N); sigma and target_sigma (T, N) m; failed, converged
    (T,) bool and errors (T,) how each solve went; tracking_px (T,) the frame's tracking
    noise; seconds (T, 2) s building the target and registering (frame 0: NaN)."""

    positions: np.ndarray
    status: np.ndarray
    residual: np.ndarray
    has_target: np.ndarray
    sigma: np.ndarray
    target_sigma: np.ndarray
    failed: np.ndarray
    converged: np.ndarray
    errors: tuple[str, ...]
    tracking_px: np.ndarray
    seconds: np.ndarray


@dataclass(frozen=True)
class RunData:
    """What the report shows, as read from the run folder (None: that stage is not done).

    run: run.json; log: the ingested frames; template (N, 3) m and its summary; registered
    frames; labels (T, N); evaluation scores and the per-point errors behind them."""

    run: dict[str, Any]
    log: IngestedLog
    template: np.ndarray | None = None
    template_summary: dict[str, Any] | None = None
    registered: RegisteredFrames | None = None
    labels: np.ndarray | None = None
    evaluation: dict[str, Any] | None = None
    errors: dict[str, np.ndarray] | None = None


@dataclass(frozen=True)
class CloudView:
    """One frame's cloud as the report renders it: points xyz (N, 3) m, labels (N,) (None:
    not classified) and, when a camera sees it, that camera's id, its image (H, W, 3) RGB
    and the points' pixels uv (N, 2) px (NaN: not seen or behind the tool)."""

    frame: int
    xyz: np.ndarray
    labels: np.ndarray | None
    camera: str = ""
    image: np.ndarray | None = None
    uv: np.ndarray | None = None


def gather(run_dir: Path) -> RunData:
    """Read whatever the run folder's done stages wrote."""
    layout = RunLayout(run_dir)
    folder = RunFolder(layout.root)
    run, log = folder.read(), load_ingested(layout.ingest_dir)
    if not folder.is_done("build-template"):
        return RunData(run, log)
    template = read_template(layout).points
    evaluation = read_evaluation(layout) if folder.is_done("evaluate") else None
    return RunData(
        run, log, template, read_template_summary(layout),
        registered=(_read_registered(layout, template, log.n_frames)
                    if folder.is_done("register") else None),
        labels=(read_labels(layout, (log.n_frames, len(template))).labels
                if folder.is_done("classify") else None),
        evaluation=evaluation,
        errors=None if evaluation is None else read_evaluation_errors(layout))


def _read_registered(layout: RunLayout, template: np.ndarray, n_frames: int) -> RegisteredFrames:
    """Frames 1.. of the registration, one file at a time, into (T, ...) arrays."""
    n = len(template)
    positions = np.full((n_frames, n, 3), np.nan)
    positions[0] = template
    status = np.zeros((n_frames, n), np.uint8)
    residual, sigma, target_sigma = (np.full((n_frames, n), np.nan, np.float32)
                                     for _ in range(3))
    has_target = np.zeros((n_frames, n), bool)
    failed, converged = np.zeros(n_frames, bool), np.ones(n_frames, bool)
    errors = [""] * n_frames
    tracking_px = np.full(n_frames, np.nan)
    seconds = np.full((n_frames, 2), np.nan)
    for k in range(1, n_frames):
        reg = read_registration(layout, k, n)
        positions[k], status[k], residual[k] = reg.registered, reg.status, reg.residual
        has_target[k], sigma[k], target_sigma[k] = reg.has_target, reg.sigma, reg.target_sigma
        failed[k], converged[k], errors[k] = reg.failed, reg.converged, reg.error
        tracking_px[k] = reg.tracking_px
        seconds[k] = [reg.seconds_target, reg.seconds_register]
    return RegisteredFrames(positions, status, residual, has_target, sigma, target_sigma,
                            failed, converged, tuple(errors), tracking_px, seconds)


def gather_views(data: RunData, tool: ToolConfig) -> list[CloudView]:
    """The frames worth rendering (core/views.pick_frames), each seen by the camera that
    shows most of its points (core/views.best_camera), with that camera's image."""
    views = []
    for k in pick_frames(data.labels, data.log.n_frames):
        if data.registered is not None:
            xyz = data.registered.positions[k]
        elif k == 0 and data.template is not None:
            xyz = data.template
        else:
            continue
        views.append(_view(data.log, k, xyz, None if data.labels is None else data.labels[k],
                           tool))
    return views


def _view(log: IngestedLog, frame: int, xyz: np.ndarray, labels: np.ndarray | None,
          tool: ToolConfig) -> CloudView:
    seen = best_camera(xyz, log.poses[frame], log.models, log.usable[frame],
                       log.tool_poses[frame], tool)
    if seen is None:
        return CloudView(frame, xyz, labels)
    camera, uv = seen
    try:
        image = log.load_image(frame, camera)
    except RunFolderError:
        return CloudView(frame, xyz, labels)
    return CloudView(frame, xyz, labels, log.cameras[camera], image, uv)
