"""Report layer 1: read a run folder into `RunData` (None where a stage is not done) and the
images behind the labelled-cloud views.

Every artefact is read through io/run/artefacts.py, io/run/ingest_store.py and io/run/rows.py, whose
paths come from io/run/layout.py; per-frame arrays are read one frame at a time and reduced
at once (report/frames.py), so a long log's report does not hold all frames' points.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..config import ToolConfig
from ..core.classify.views import best_camera, pick_frames
from ..core.measure.indentation import SERIES_KEYS, DeformationSeries
from ..errors import RunFolderError
from ..io.run.artefacts import (
    read_deformation_summary,
    read_evaluation,
    read_registration,
    read_template,
    read_template_summary,
)
from ..io.run.folder import RunFolder
from ..io.run.ingest_store import IngestedLog, load_ingested
from ..io.run.layout import RunLayout
from ..io.run.rows import npz_rows
from .frames import CLASS_CODES, FrameAccumulator, FrameFigures


@dataclass(frozen=True)
class RunData:
    """What the report shows, as read from the run folder (None: that stage is not done).

    run: run.json; log: the ingested frames; template (N, 3) m and its summary; frames: the
    registered (and classified) frames in numbers (report/frames.py); evaluation scores
    and the per-point errors behind them (template_error_mm, on_tool (N,);
    registration_error_mm (K, N) of the sampled frames `frames.sampled`); the contact and
    indentation series, the deepest frame's displacement (inward_mm, deformed (N,)) and
    their summary."""

    run: dict[str, Any]
    log: IngestedLog
    template: np.ndarray | None = None
    template_summary: dict[str, Any] | None = None
    frames: FrameFigures | None = None
    evaluation: dict[str, Any] | None = None
    errors: dict[str, np.ndarray] | None = None
    deformation: DeformationSeries | None = None
    deepest_field: tuple[np.ndarray, np.ndarray] | None = None
    deformation_summary: dict[str, Any] | None = None

    @property
    def class_counts(self) -> np.ndarray | None:
        """Points per class (T, 4) (report/frames.CLASS_CODES order); None before classify."""
        return None if self.frames is None else self.frames.class_counts


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
    """Read whatever the run folder's done stages wrote, one frame at a time: the memory
    held grows with the frames only by their per-frame figures."""
    layout = RunLayout(run_dir)
    folder = RunFolder(layout.root)
    run, log = folder.read(), load_ingested(layout.ingest_dir)
    if not folder.is_done("build-template"):
        return RunData(run, log)
    template = read_template(layout).points
    evaluation = read_evaluation(layout) if folder.is_done("evaluate") else None
    frames = (_read_frames(layout, template, log.n_frames, folder.is_done("classify"))
              if folder.is_done("register") else None)
    summary = read_deformation_summary(layout) if folder.is_done("measure") else None
    return RunData(
        run, log, template, read_template_summary(layout), frames, evaluation,
        errors=(None if evaluation is None or frames is None
                else _read_errors(layout, frames.sampled)),
        deformation=None if summary is None else _read_series(layout, log.n_frames),
        deepest_field=(None if summary is None or summary.get("deepest_frame") is None
                       else _read_field(layout, int(summary["deepest_frame"]))),
        deformation_summary=summary)


def _read_frames(layout: RunLayout, template: np.ndarray, n_frames: int,
                 classified: bool) -> FrameFigures:
    """Frames 0.. of the registration (and their labels), one file at a time."""
    n = len(template)
    acc = FrameAccumulator(template, n_frames, classified)
    with contextlib.ExitStack() as stack:
        labels = floor = None
        if classified:
            labels = stack.enter_context(npz_rows(layout.labels, "labels"))
            with np.load(layout.labels, allow_pickle=False) as z:  # the directory only
                stored = "floor_mm" in z.files  # not in runs classified before it was
            floor = stack.enter_context(npz_rows(layout.labels, "floor_mm")) if stored else None
        for k in range(n_frames):
            acc.add(k, read_registration(layout, k, n) if k else None,
                    None if labels is None else labels.read(k),
                    None if floor is None else floor.read(k))
    return acc.result()


def _read_errors(layout: RunLayout, sampled: np.ndarray) -> dict[str, np.ndarray] | None:
    """The evaluation's per-point errors: the template's, and the registration's of the
    sampled frames only."""
    path = layout.evaluation_errors
    if not path.is_file():
        return None
    with np.load(path, allow_pickle=False) as z:
        out = {k: z[k] for k in ("template_error_mm", "on_tool") if k in z.files}
        registered = "registration_error_mm" in z.files
    if registered:
        with npz_rows(path, "registration_error_mm") as rows:
            out["registration_error_mm"] = np.array([rows.read(k) for k in sampled])
    return out


def _read_series(layout: RunLayout, n_frames: int) -> DeformationSeries:
    """The contact and indentation series (T,) of the measure stage."""
    with np.load(layout.deformation, allow_pickle=False) as z:
        series = DeformationSeries(**{k: z[k] for k in SERIES_KEYS})
    if len(series.contact) != n_frames:
        raise RunFolderError(f"{layout.deformation}: {len(series.contact)} frames, the run has "
                             f"{n_frames}; rerun `surgrecon measure`")
    return series


def _read_field(layout: RunLayout, frame: int) -> tuple[np.ndarray, np.ndarray]:
    """One frame's compensated displacement into the tissue (N,) mm and deformed flags."""
    with (npz_rows(layout.deformation, "inward_mm") as inward,
          npz_rows(layout.deformation, "deformed") as deformed):
        return inward.read(frame), deformed.read(frame)


def gather_views(layout: RunLayout, data: RunData, tool: ToolConfig) -> list[CloudView]:
    """The frames worth rendering (core/views.pick_frames), each seen by the camera that
    shows most of its points (core/views.best_camera), with that camera's image."""
    counts = data.class_counts
    picks = pick_frames(None if counts is None else dict(zip(CLASS_CODES.values(), counts.T,
                                                             strict=True)),
                        data.log.n_frames)
    views = []
    for k in picks:
        if data.template is None or (k > 0 and data.frames is None):
            continue
        xyz = (read_registration(layout, k, len(data.template)).registered if k
               else data.template)
        labels = None
        if counts is not None:
            with npz_rows(layout.labels, "labels") as rows:
                labels = rows.read(k)
        views.append(_view(data.log, k, xyz, labels, tool))
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
