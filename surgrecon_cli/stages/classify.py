"""Stage `classify`: label every template point at every frame (core/classify/rules.py).

Reads the template and every registered frame (io/run/artefacts.py); intra-camera inliers are
classified from their own re-triangulated pixels (`static_verdicts_checked`); the points the
logged tools touch are found (`frame_inputs`: the deforming test takes the touch as evidence);
a frame's points whose evidence does not support a label (core/quality.unsupported_points) are
unknown. Writes RUN/classify/labels.npz (`io/artefacts.FrameLabels`: labels after hysteresis,
raw labels, the displacement, deformation and deformation-floor measures, reprojection
status) and every frame's labelled cloud RUN/clouds/FFFFFF.ply, written once, here:
positions, template colours, point_id, label, residual (m, NaN without a target), sigma (m)
and the reprojection status and views of its target (frame 0, the reference, all static:
the template's n_views, reprojection_px and sigma).
"""

from __future__ import annotations

import functools
import logging
import shutil
from collections.abc import Callable, Collection
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..config import Config
from ..core.classify.hysteresis import HysteresisAhead, hysteresis_step
from ..core.classify.labels import CLASS_NAMES, INTRA, STATIC, UNKNOWN
from ..core.classify.quality import FrameFit, frame_quality, unsupported_points
from ..core.classify.rules import (
    Evidence,
    FrameClasses,
    Neighbourhoods,
    RegisteredFrame,
    classify_frame,
    displacement_covariance,
    template_neighbourhoods,
)
from ..core.geometry.cameras import CameraModel
from ..core.geometry.tool import points_near_tool
from ..core.noise.frame_noise import retriangulate
from ..core.noise.model import NoiseModel, covariance_sigma, noise_from_report
from ..errors import RunFolderError
from ..executors import Executor, Task
from ..executors.heap import adapted_heap
from ..executors.serial import SerialExecutor
from ..io.run.artefacts import (
    FrameRegistration,
    read_observations,
    read_registration,
    read_template,
    write_frame_cloud,
)
from ..io.run.atomic import file_identity, write_npz
from ..io.run.ingest_store import IngestedLog, load_ingested
from ..io.run.layout import RunLayout
from ..io.run.rows import RowFile, npz_rows, write_npz_rows
from .common import stage_run, tool_poses
from .registry import StageContext

logger = logging.getLogger(__name__)

STAGE = "classify"
# The arrays of labels.npz (T, N), as io/artefacts.write_labels stores them.
_LABEL_DTYPES = {"labels": np.uint8, "raw_labels": np.uint8, "displacement_mm": np.float32,
                 "deformation_mm": np.float32, "floor_mm": np.float32, "status": np.uint8}
# Labelled clouds written per executor call (their label rows are in memory meanwhile).
_CLOUD_BLOCK = 64


@dataclass(frozen=True)
class TemplateNoise:
    """The template points' uncertainty: covariance (N, 3, 3) m² from image noise,
    pose_covariance (N, 3, 3) m² from the cameras' pose errors (common to nearby points),
    sigma (N,) m = √trace of their sum; the run's noise model (its tracking_px is each
    frame's own)."""

    covariance: np.ndarray
    pose_covariance: np.ndarray
    sigma: np.ndarray
    model: NoiseModel


# template (N, 3) m, its neighbourhoods, its points' uncertainty
TemplateInputs = tuple[np.ndarray, Neighbourhoods, TemplateNoise]


@functools.lru_cache(maxsize=4)
def _cached_template(run_dir: str, _stamp: tuple[tuple[int, ...], ...], neighbourhood_mm: float,
                     min_neighbours: int, max_neighbours: int) -> TemplateInputs:
    adapted_heap()  # each frame's fits build and free (N, K, 9) arrays of ~20 MB
    layout = RunLayout(run_dir)
    template = read_template(layout).points
    nb = template_neighbourhoods(template, neighbourhood_mm, min_neighbours, max_neighbours)
    obs = read_observations(layout, len(template))
    cov, pose_cov = obs.covariance, obs.pose_covariance
    log = load_ingested(layout.ingest_dir)
    noise = TemplateNoise(cov, pose_cov, covariance_sigma(cov + pose_cov),
                          noise_from_report(log.report, log.cameras, obs.pixel_noise_px))
    for array in (template, nb.index, nb.mask, cov, pose_cov, noise.sigma):
        array.flags.writeable = False  # shared by every frame this process classifies
    return template, nb, noise


def template_and_neighbourhoods(run_dir: Path, config: Config) -> TemplateInputs:
    """The run's template (N, 3) m and its classify neighbourhoods, built once per process
    and template file (~30 ms on the sample; a worker classifies many frames). The file is
    replaced, never rewritten in place, so its device, inode, times and size identify it."""
    layout = RunLayout(Path(run_dir).absolute())
    cfg = config.classify
    return _cached_template(str(layout.root), file_identity(layout.template_ply),
                            cfg.neighbourhood_mm, cfg.min_neighbours, cfg.max_neighbours)


def classify_one_frame(run_dir: Path, frame: int, config: Config) -> int:
    """Labels of one frame k >= 1 from its registration (a task), written with the measures
    behind them and its reprojection check status to RUN/classify/frames/k.npz (before
    hysteresis, which needs every frame: `run_classify` reads them back one at a time).
    Returns the frame: the stage's memory holds no frame's per-point arrays."""
    template, nb, template_noise = template_and_neighbourhoods(run_dir, config)
    layout = RunLayout(run_dir)
    reg = read_registration(layout, frame, len(template))
    cfg = config.classify
    transforms = reg.transforms.astype(float) if cfg.measure == "transform_diff" else None
    registered, evidence = frame_inputs(reg, template_noise, load_ingested(layout.ingest_dir),
                                        frame, config)
    classes = classify_frame(template, RegisteredFrame(registered, transforms, reg.status), nb,
                             cfg, evidence=evidence)
    quality = frame_quality(frame, FrameFit(
        reg.status, reg.sigma.astype(float), reg.residual.astype(float),
        reg.target_sigma.astype(float), bool(reg.failed), bool(reg.converged), reg.error))
    unsupported = unsupported_points(quality, reg.status, classes.labels)
    classes.labels[unsupported] = UNKNOWN
    classes.floor_mm[unsupported] = np.nan
    write_npz(layout.classified(frame), **_rows(classes, reg.status))
    return frame


def _rows(classes: FrameClasses, status: np.ndarray) -> dict[str, np.ndarray]:
    """One frame's rows of labels.npz (before hysteresis), as io/artefacts.write_labels
    stores them."""
    return {"raw_labels": classes.labels.astype(np.uint8),
            "displacement_mm": classes.displacement_mm.astype(np.float32),
            "deformation_mm": classes.deformation_mm.astype(np.float32),
            "floor_mm": classes.floor_mm.astype(np.float32),
            "status": status.astype(np.uint8)}


def frame_inputs(reg: FrameRegistration, template_noise: TemplateNoise, log: IngestedLog,
                 frame: int, config: Config) -> tuple[np.ndarray, Evidence]:
    """Registered positions (N, 3) m and evidence of frame k that `classify_frame` labels:
    `frame_evidence`, the reprojection check's static verdicts re-measured
    (`static_verdicts_checked`), and the points the tools touch at their registered
    positions (core/geometry/tool.points_near_tool: within a capsule's radius + margin_m;
    none where the log has no tool pose)."""
    evidence = frame_evidence(reg, reg.registered.astype(float), template_noise)
    registered, evidence = static_verdicts_checked(
        reg, template_noise, evidence, list(log.models), log.usable_poses(frame))
    touched = points_near_tool(registered, tool_poses(log, config, frame),
                               config.tool_configs())
    return registered, replace(evidence, touched=touched)


def frame_evidence(reg: FrameRegistration, registered: np.ndarray,
                   template: TemplateNoise) -> Evidence:
    """The classifier's uncertainties of one registered frame: measured positions are the
    targets where the reprojection check gave one, else the registered positions; the
    displacement's covariance is the target's and the template point's without the image
    error they share (`displacement_covariance`: tracking carries the template's frame-0
    error into the target) where there is a target (a narrow baseline knows depth far worse
    than the other directions), else isotropic from σ. The rigid-motion test leaves out the
    pose errors (common to nearby points, so the neighbourhood's rigid fit absorbs them)."""
    sigma = reg.sigma.astype(float)
    target = reg.target.astype(float)
    target_sigma = reg.target_sigma.astype(float)
    has = reg.has_target
    iso = (np.nan_to_num(sigma, posinf=1e3) ** 2 + template.sigma**2) / 3.0
    departure = iso[:, None, None] * np.eye(3)
    departure[has] = displacement_covariance(reg.target_covariance[has].astype(float),
                                             template.covariance[has])
    displacement = departure.copy()
    displacement[has] += (reg.target_pose_covariance[has].astype(float)
                          + template.pose_covariance[has])
    return Evidence(sigma=sigma, template_sigma=template.sigma,
                    measured=np.where(has[:, None], target, registered),
                    measured_sigma=np.where(has, target_sigma, sigma),
                    displacement_cov=displacement, departure_cov=departure,
                    template_shared_var=np.trace(template.covariance, axis1=1, axis2=2))


def static_verdicts_checked(reg: FrameRegistration, template_noise: TemplateNoise,
                            evidence: Evidence, models: list[CameraModel],
                            poses: np.ndarray) -> tuple[np.ndarray, Evidence]:
    """Registered positions (N, 3) m and evidence of a frame, where the reprojection check's
    static verdicts (intra-camera inliers: target = frame-0 position) are replaced by what
    the points' own views say: every such point whose tracked pixels re-triangulate
    (without a gate, core/noise/frame_noise.retriangulate) is measured there, with that
    position's and the template's covariance less the image error they share, and the
    classification's significance test decides. (The check tests every view alone with
    the pose error as per-view noise: with a narrow stereo baseline, motion along the line
    of sight moves each view by less than that noise, but their disparity by far more than
    the image noise; on the stereo simulator a third of truly deforming points were called
    static that way.)"""
    intra = reg.status == INTRA
    found = np.isfinite(reg.pixels).all(2) & intra[:, None]
    noise = replace(template_noise.model, tracking_px=float(reg.tracking_px),
                    tracking_shared_px=float(reg.tracking_shared_px))
    position, image_cov, pose_cov = retriangulate(found, reg.pixels.astype(float), models,
                                                  poses, noise)
    seen = intra & np.isfinite(position).all(1)
    registered = reg.registered.astype(float)
    if not seen.any():
        return registered, evidence
    registered[seen] = position[seen]
    measured, measured_sigma = evidence.measured.copy(), evidence.measured_sigma.copy()
    displacement, departure = evidence.displacement_cov.copy(), evidence.departure_cov.copy()
    measured[seen] = position[seen]
    measured_sigma[seen] = covariance_sigma(image_cov[seen] + pose_cov[seen])
    departure[seen] = displacement_covariance(image_cov[seen], template_noise.covariance[seen])
    displacement[seen] = departure[seen] + pose_cov[seen] + template_noise.pose_covariance[seen]
    return registered, replace(evidence, measured=measured, measured_sigma=measured_sigma,
                               displacement_cov=displacement, departure_cov=departure)


def classify_task(run_dir: Path, config: Config, frame: int) -> Task:
    """The task classifying frame k (e.g. for run_register's `after_frame`, to classify
    frames as they are registered)."""
    return Task(f"classify-{frame}", classify_one_frame, (Path(run_dir).absolute(), frame,
                                                          config))


def run_classify(run_dir: Path, config: Config,
                 on_step: Callable[[int, int], None] | None = None,
                 executor: Executor | None = None,
                 classified: Collection[int] = ()) -> dict:
    """Classify every frame of a registered run; returns the stage info (class counts etc.).

    Frames are classified as independent tasks on `executor` (default: serial), each
    written to RUN/classify/frames/; the hysteresis then runs over time, streaming over
    those files (`write_labels_streaming`), and every frame's
    labelled cloud is written (tasks again, in blocks of frames). Memory is flat in the
    number of frames. `classified`: frames already classified with this config and the
    current registration (e.g. alongside register); only the others are computed.
    `on_step(done, total)` reports progress over 2T steps (T frames classified, T clouds
    written)."""
    layout = RunLayout(run_dir)
    executor = executor or SerialExecutor()
    with stage_run(layout.root, STAGE, config) as info:
        n_frames = load_ingested(layout.ingest_dir).n_frames
        total = 2 * n_frames
        step = on_step or (lambda _d, _t: None)
        early = {k for k in classified if 0 < k < n_frames}
        count = [1 + len(early)]

        def advance(_key: str, _value: object) -> None:
            count[0] += 1
            step(count[0], total)

        step(count[0], total)
        n = len(read_template(layout).points)
        todo = [k for k in range(1, n_frames) if k not in early]
        executor.run([classify_task(layout.root, config, k) for k in todo], advance)
        counts, changed = write_labels_streaming(layout, n_frames, n,
                                                 config.classify.hysteresis_frames)
        with (npz_rows(layout.labels, "labels") as labels,
              npz_rows(layout.labels, "floor_mm") as floors):
            for start in range(0, n_frames, _CLOUD_BLOCK):
                executor.run([Task(str(k), write_labelled_cloud,
                                   (layout.root.absolute(), k, labels.read(k), floors.read(k)))
                              for k in range(start, min(start + _CLOUD_BLOCK, n_frames))],
                             advance)
        shutil.rmtree(layout.classified_dir, ignore_errors=True)
        info.update(frames=n_frames, points=n, counts_frames_1_on=counts,
                    classified_with_register=len(early), changed_by_hysteresis=changed)
        logger.debug("classified %d frames x %d points: %s", n_frames, n, counts)
        result = dict(info)
    return result


def write_labels_streaming(layout: RunLayout, n_frames: int, n: int,
                           hysteresis_frames: int) -> tuple[dict[str, int], int]:
    """labels.npz from the per-frame files, one frame in memory at a time: the hysteresis'
    backward pass (whether each label persists), then its forward pass writing every
    array's rows. Returns the class counts of frames 1.. and how many labels the
    hysteresis changed."""
    layout.classify_dir.mkdir(parents=True, exist_ok=True)  # a 1-frame run classified none
    scratch = {name: layout.classify_dir / f".labels.{name}.tmp"
               for name in ("persists", *_LABEL_DTYPES)}
    rows = {name: RowFile(scratch[name], (n_frames, n), dtype, create=True)
            for name, dtype in (("persists", bool), *_LABEL_DTYPES.items())}
    try:
        ahead = HysteresisAhead(n, hysteresis_frames)
        for k in range(n_frames - 1, 0, -1):
            rows["persists"].write(k, ahead.step(_classified(layout, k)["raw_labels"]))
        first = FrameClasses(labels=np.full(n, STATIC, np.uint8), displacement_mm=np.zeros(n),
                             deformation_mm=np.full(n, np.nan), floor_mm=np.full(n, np.nan))
        current = first.labels.copy()
        counts = dict.fromkeys([*CLASS_NAMES.values(), "unknown"], 0)
        changed = 0
        for k in range(n_frames):
            row = _rows(first, np.full(n, INTRA, np.uint8)) if k == 0 else _classified(layout, k)
            raw = row["raw_labels"]
            labels = raw if k == 0 or hysteresis_frames <= 1 else hysteresis_step(
                current, raw, rows["persists"].read(k))
            for name, value in (("labels", labels), *row.items()):
                rows[name].write(k, value)
            if k:
                found = np.bincount(labels, minlength=256)
                for code, name in [*CLASS_NAMES.items(), (UNKNOWN, "unknown")]:
                    counts[name] += int(found[code])
                changed += int((labels != raw).sum())
        write_npz_rows(layout.labels, {name: rows[name] for name in _LABEL_DTYPES})
    finally:
        for name, path in scratch.items():
            rows[name].close()
            path.unlink(missing_ok=True)
    return counts, changed


def _classified(layout: RunLayout, frame: int) -> dict[str, np.ndarray]:
    """The rows `classify_one_frame` wrote for a frame."""
    path = layout.classified(frame)
    with np.load(path, allow_pickle=False) as z:
        missing = [name for name in _LABEL_DTYPES if name != "labels" and name not in z.files]
        if missing:
            raise RunFolderError(f"{path}: no {', '.join(missing)} (an older surgrecon wrote "
                                 f"it); re-run `surgrecon classify {layout.root}`")
        return {name: z[name] for name in _LABEL_DTYPES if name != "labels"}


def write_labelled_cloud(run_dir: Path, frame: int, labels: np.ndarray,
                         floor_mm: np.ndarray) -> None:
    """Write frame k's labelled cloud (a task): the template for frame 0; else the
    registered positions, or for a frame that failed, the positions of the base it was
    to be registered from (its points are unknown), with each point's deformation floor
    floor_mm (N,) mm (stored in metres, as every length of the cloud)."""
    layout = RunLayout(run_dir)
    template = read_template(layout)
    n = len(template.points)
    if frame == 0:
        write_frame_cloud(layout, 0, template.points, template.rgb, labels,
                          np.full(n, np.nan), template.extra())
        return
    reg = read_registration(layout, frame, n)
    positions, base = reg.registered, reg
    while base.failed and base.base > 0:
        base = read_registration(layout, base.base, n)
    if reg.failed:
        positions = template.points if base.failed else base.registered
    write_frame_cloud(layout, frame, positions, template.rgb, labels, reg.residual,
                      {"status": reg.status.astype(np.uint8), "views": reg.views.astype(np.uint8),
                       "sigma": reg.sigma.astype(np.float32),
                       "deform_floor": (floor_mm * 1e-3).astype(np.float32)})


def pipeline_step(ctx: StageContext, progress: Callable[[float], None]) -> None:
    """The stage within `surgrecon run`: only the frames register did not classify."""
    run_classify(ctx.run_dir, ctx.config, on_step=lambda d, t: progress(d / t),
                 executor=ctx.executor, classified=ctx.classified)
    ctx.classified.clear()
