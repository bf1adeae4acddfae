"""Stage `classify`: label every template point at every frame (core/classify.py).

Reads RUN/template.ply and RUN/registration/NNNNNN.npz, writes
  RUN/classify/labels.npz   labels (T, N) uint8 (after hysteresis), raw_labels (T, N) uint8,
                            displacement_mm (T, N) f32, deformation_mm (T, N) f32,
                            status (T, N) u8 (reprojection check; frame 0: intra)
and rewrites every RUN/clouds/NNNNNN.ply with its labels (atomically; the other properties
the registration wrote are kept). Frame 0 is the reference: all static.
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..config import Config, to_dict
from ..core.classify import (
    Evidence,
    FrameClasses,
    Neighbourhoods,
    apply_hysteresis,
    classify_frame,
    template_neighbourhoods,
)
from ..core.labels import CLASS_NAMES, INTRA, STATIC, UNKNOWN
from ..core.noise import covariance_sigma
from ..errors import RunFolderError
from ..executors import Executor, Task
from ..executors.serial import SerialExecutor
from ..io.atomic import write_npz
from ..io.ingest_store import load_ingested
from ..io.ply import read_ply, write_cloud_ply
from .common import stage_run
from .register import load_template, registration_path
from .template import cloud_path

logger = logging.getLogger(__name__)

STAGE = "classify"
_CLOUD_COLUMNS = ("x", "y", "z", "red", "green", "blue", "point_id", "label", "residual")


def labels_path(run_dir: Path) -> Path:
    return Path(run_dir) / "classify" / "labels.npz"


def load_registration_frame(run_dir: Path, frame: int, n_points: int) -> dict[str, np.ndarray]:
    """Registration arrays of one frame >= 1 (see stages/register.py); RunFolderError if the
    file is missing or does not match the template's N points."""
    path = registration_path(run_dir, frame)
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except FileNotFoundError as exc:
        raise RunFolderError(f"{path}: frame {frame} is not registered; run "
                             f"`surgrecon register {run_dir}`") from exc
    except (OSError, ValueError) as exc:
        raise RunFolderError(f"{path}: unreadable ({exc}); re-run register") from exc
    for key, shape in (("registered", (n_points, 3)), ("transforms", (n_points, 3, 4)),
                       ("status", (n_points,)), ("sigma", (n_points,)),
                       ("target", (n_points, 3)), ("target_sigma", (n_points,)),
                       ("target_covariance", (n_points, 3, 3)),
                       ("target_pose_covariance", (n_points, 3, 3))):
        if key not in data or data[key].shape != shape:
            got = data[key].shape if key in data else "missing"
            raise RunFolderError(f"{path}: {key} should be {shape} for the {n_points}-point "
                                 f"template, got {got}; re-run register")
    return data


@dataclass(frozen=True)
class TemplateNoise:
    """The template points' uncertainty: covariance (N, 3, 3) m² from image noise,
    pose_covariance (N, 3, 3) m² from the cameras' pose errors (common to nearby points),
    sigma (N,) m = √trace of their sum."""

    covariance: np.ndarray
    pose_covariance: np.ndarray
    sigma: np.ndarray


# template (N, 3) m, its neighbourhoods, its points' uncertainty
TemplateInputs = tuple[np.ndarray, Neighbourhoods, TemplateNoise]


@functools.lru_cache(maxsize=4)
def _cached_template(run_dir: str, _stamp: tuple[int, ...], neighbourhood_mm: float,
                     min_neighbours: int, max_neighbours: int) -> TemplateInputs:
    template, _ = load_template(Path(run_dir))
    nb = template_neighbourhoods(template, neighbourhood_mm, min_neighbours, max_neighbours)
    with np.load(Path(run_dir) / "template" / "observations.npz", allow_pickle=False) as z:
        cov = z["covariance"].astype(float)
        pose_cov = z["pose_covariance"].astype(float)
    noise = TemplateNoise(cov, pose_cov, covariance_sigma(cov + pose_cov))
    for array in (template, nb.index, nb.mask, cov, pose_cov, noise.sigma):
        array.flags.writeable = False  # shared by every frame this process classifies
    return template, nb, noise


def template_and_neighbourhoods(run_dir: Path, config: Config) -> TemplateInputs:
    """The run's template (N, 3) m and its classify neighbourhoods, built once per process
    and template file (~30 ms on the sample; a worker classifies many frames). The file is
    replaced, never rewritten in place, so its device, inode, times and size identify it."""
    path = Path(run_dir).absolute()
    st = (path / "template.ply").stat()
    cfg = config.classify
    stamp = (st.st_dev, st.st_ino, st.st_mtime_ns, st.st_ctime_ns, st.st_size)
    return _cached_template(str(path), stamp,
                            cfg.neighbourhood_mm, cfg.min_neighbours, cfg.max_neighbours)


def classify_one_frame(run_dir: Path, frame: int,
                       config: Config) -> tuple[FrameClasses, np.ndarray]:
    """Labels of one frame k >= 1 from its registration (a task), and its reprojection
    check status (N,) uint8."""
    template, nb, template_noise = template_and_neighbourhoods(run_dir, config)
    reg = load_registration_frame(run_dir, frame, len(template))
    cfg = config.classify
    transforms = reg["transforms"].astype(float) if cfg.measure == "transform_diff" else None
    registered = reg["registered"].astype(float)
    classes = classify_frame(template, registered, nb, cfg, transforms=transforms,
                             status=reg["status"],
                             evidence=frame_evidence(reg, registered, template_noise))
    return classes, reg["status"].astype(np.uint8)


def frame_evidence(reg: dict[str, np.ndarray], registered: np.ndarray,
                   template: TemplateNoise) -> Evidence:
    """The classifier's uncertainties of one registered frame: measured positions are the
    targets where the reprojection check gave one, else the registered positions; the
    displacement's covariance is the target's plus the template point's where there is a
    target (a narrow baseline knows depth far worse than the other directions), else
    isotropic from σ. The rigid-motion test leaves out the pose errors (common to nearby
    points, so the neighbourhood's rigid fit absorbs them)."""
    sigma = reg["sigma"].astype(float)
    target = reg["target"].astype(float)
    target_sigma = reg["target_sigma"].astype(float)
    has = np.isfinite(target_sigma) & np.isfinite(target).all(1)
    iso = (np.nan_to_num(sigma, posinf=1e3) ** 2 + template.sigma**2) / 3.0
    departure = iso[:, None, None] * np.eye(3)
    departure[has] = reg["target_covariance"][has].astype(float) + template.covariance[has]
    displacement = departure.copy()
    displacement[has] += (reg["target_pose_covariance"][has].astype(float)
                          + template.pose_covariance[has])
    return Evidence(sigma=sigma, template_sigma=template.sigma,
                    measured=np.where(has[:, None], target, registered),
                    measured_sigma=np.where(has, target_sigma, sigma),
                    displacement_cov=displacement, departure_cov=departure)


def classify_task(run_dir: Path, config: Config, frame: int) -> Task:
    """The task classifying frame k (e.g. for run_register's `after_frame`, to classify
    frames as they are registered)."""
    return Task(f"classify-{frame}", classify_one_frame, (Path(run_dir).absolute(), frame,
                                                          config))


def run_classify(run_dir: Path, config: Config,
                 on_step: Callable[[int, int], None] | None = None,
                 executor: Executor | None = None,
                 classified: dict[int, tuple[FrameClasses, np.ndarray]] | None = None) -> dict:
    """Classify every frame of a registered run; returns the stage info (class counts etc.).

    Frames are classified as independent tasks on `executor` (default: serial), then the
    hysteresis runs over time and every cloud is relabelled (tasks again). `classified`
    holds the `classify_one_frame` results of frames already classified with this config
    and the current registration (e.g. alongside register); only the others are computed.
    `on_step(done, total)` reports progress over 2T steps (T frames classified, T clouds
    written)."""
    run_dir = Path(run_dir)
    executor = executor or SerialExecutor()
    classified = dict(classified or {})
    with stage_run(run_dir, STAGE, config, needs=("ingest", "build-template", "register")) as info:
        n_frames = load_ingested(run_dir / "ingest").n_frames
        total = 2 * n_frames
        step = on_step or (lambda _d, _t: None)
        count = [1 + len(classified)]

        def advance(_key: str, _value: object) -> None:
            count[0] += 1
            step(count[0], total)

        step(count[0], total)
        n = len(load_template(run_dir)[0])
        todo = [k for k in range(1, n_frames) if k not in classified]
        tasks = [classify_task(run_dir, config, k) for k in todo]
        done = executor.run(tasks, advance)
        classified.update({k: done[t.key] for k, t in zip(todo, tasks, strict=True)})
        frames = [FrameClasses(labels=np.full(n, STATIC, np.uint8),
                               displacement_mm=np.zeros(n), deformation_mm=np.full(n, np.nan))]
        status = [np.full(n, INTRA, np.uint8)]
        for k in range(1, n_frames):
            frames.append(classified[k][0])
            status.append(classified[k][1])
        raw = np.stack([f.labels for f in frames])
        labels = apply_hysteresis(raw, config.classify.hysteresis_frames)
        write_npz(labels_path(run_dir), labels=labels, raw_labels=raw,
                  displacement_mm=np.stack([f.displacement_mm for f in frames]).astype(np.float32),
                  deformation_mm=np.stack([f.deformation_mm for f in frames]).astype(np.float32),
                  status=np.stack(status))
        executor.run([Task(str(k), relabel_cloud, (cloud_path(run_dir, k), labels[k]))
                      for k in range(n_frames)], advance)
        later = labels[1:]
        counts = {name: int((later == code).sum()) for code, name in CLASS_NAMES.items()}
        counts["unknown"] = int((later == UNKNOWN).sum())
        info.update(frames=n_frames, points=n, counts_frames_1_on=counts,
                    classified_with_register=n_frames - 1 - len(todo),
                    changed_by_hysteresis=int((labels != raw).sum()),
                    config={"classify": to_dict(config)["classify"]})
        logger.debug("classified %d frames x %d points: %s", n_frames, n, counts)
        result = dict(info)
    return result


def relabel_cloud(path: Path, labels: np.ndarray) -> None:
    """Rewrite one per-frame cloud with `labels` (N,) indexed by point_id, keeping every
    other property; atomic."""
    if not path.is_file():
        raise RunFolderError(f"{path}: cloud missing; re-run register")
    cloud = read_ply(path)
    ids = cloud["point_id"].astype(np.int64)
    if ids.size and (ids.min() < 0 or ids.max() >= len(labels)):
        raise RunFolderError(f"{path}: point_id outside the template (0..{len(labels) - 1}); "
                             "re-run register")
    extra = {k: v for k, v in cloud.items() if k not in _CLOUD_COLUMNS}
    write_cloud_ply(path, np.column_stack([cloud["x"], cloud["y"], cloud["z"]]),
                    rgb=np.column_stack([cloud["red"], cloud["green"], cloud["blue"]]),
                    point_id=ids.astype(np.int32), label=labels[ids].astype(np.uint8),
                    residual=cloud.get("residual"), extra=extra)
