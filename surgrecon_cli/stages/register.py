"""Stage `register`: target cloud and non-rigid registration of every frame k >= 1.

Per frame k, one task (`register_frame`): the frame step of core/frame_step.py (target
cloud G_k from the base frame's images, gated by the run's measured noise; registration of
the base's cloud to G_k; per-point uncertainty). The base is frame 0, or with re-basing
every N_T frames the last multiple of N_T before k: frames depend on their base only, so
they run in parallel on an executor, as a dependency chain over the bases. A frame that
cannot be registered is recorded as failed (its points unknown) and the run goes on; a
frame whose base failed is registered from that base's own base. Outputs, written
atomically frame by frame so a killed run resumes:
  RUN/registration/NNNNNN.npz   transforms (N,3,4) f32, registered (N,3), target (N,3),
                                status (N,) u8, residual (N,) f32 (to the point's target, m,
                                NaN without one), sigma (N,) f32 (RMS 3D uncertainty of the
                                registered position, m), target_sigma (N,) f32,
                                target_covariance (N,3,3) f32 m² (from image noise),
                                target_pose_covariance (N,3,3) f32 m² (from pose
                                errors, common to nearby points),
                                support_mm (N,) f32, pixels (N,C,2) f64, tracking_px,
                                converged, seconds_target, seconds_register, failed, error
  RUN/clouds/NNNNNN.ply         registered positions, template colours, point_id,
                                label 255 (until classified), residual, sigma
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from ..config import Config, to_dict
from ..core.frame_step import BaseState, FrameResult, register_frame_step, unregistered
from ..core.labels import UNKNOWN
from ..core.noise import noise_from_report
from ..core.tool import tool_pose_in_world
from ..errors import GeometryError, RunFolderError
from ..executors import Executor, Task
from ..executors.serial import SerialExecutor
from ..io.atomic import write_npz
from ..io.ingest_store import load_ingested
from ..io.ply import read_ply, write_cloud_ply
from ..io.run_folder import RunFolder
from .common import stage_run
from .template import cloud_path

logger = logging.getLogger(__name__)

STAGE = "register"


def registration_path(run_dir: Path, frame: int) -> Path:
    return Path(run_dir) / "registration" / f"{frame:06d}.npz"


def load_template(run_dir: Path) -> tuple[np.ndarray, np.ndarray]:
    """Template points (N, 3) m and colours (N, 3) uint8 from RUN/template.ply."""
    cloud = read_ply(Path(run_dir) / "template.ply")
    order = np.argsort(cloud["point_id"])
    xyz = np.column_stack([cloud["x"], cloud["y"], cloud["z"]]).astype(float)[order]
    rgb = np.column_stack([cloud["red"], cloud["green"], cloud["blue"]]).astype(np.uint8)[order]
    return xyz, rgb


def _template_observations(run_dir: Path, n_points: int,
                           n_cams: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Where each template point was seen at frame 0 (N, C, 2) px (NaN where not), its
    covariance (N, 3, 3) m² (image and pose errors), its pose part (N, 3, 3) m² and the
    measured pixel noise (px)."""
    with np.load(Path(run_dir) / "template" / "observations.npz", allow_pickle=False) as z:
        pixels = np.full((n_points, n_cams, 2), np.nan)
        pixels[z["point"], z["camera"]] = z["pixels"]
        pose = z["pose_covariance"].astype(float)
        return pixels, z["covariance"].astype(float) + pose, pose, float(z["pixel_noise_px"])


def base_frame(frame: int, update_every: int) -> int:
    """The template base of `frame`: 0, or with re-basing every N_T frames the last
    multiple of N_T before it. Frame k is tracked from its base's images and registered
    from its base's registered cloud, so frames only depend on their base."""
    return ((frame - 1) // update_every) * update_every if update_every else 0


def _load_base(run_dir: Path, frame: int, update_every: int, template: np.ndarray,
               pixels0: np.ndarray) -> BaseState:
    """The base state of `frame`; a failed base frame is replaced by its own base."""
    n = len(template)
    while frame > 0:
        with np.load(registration_path(run_dir, frame), allow_pickle=False) as z:
            if not bool(z["failed"]):
                registered, target = z["registered"], z["target"]
                return BaseState(frame, z["transforms"].astype(float), registered,
                                 np.where(np.isfinite(target), target, registered),
                                 z["pixels"].astype(float))
        frame = base_frame(frame, update_every)
    return BaseState(0, np.tile(np.eye(3, 4), (n, 1, 1)), template, template, pixels0)


def register_frame(run_dir: Path, frame: int, config: Config) -> dict:
    """Target cloud and registration of one frame k >= 1 against its base (a task: reads
    the run folder, writes RUN/registration/k.npz and RUN/clouds/k.ply atomically).
    Returns the frame's timings and counts, or its failure."""
    run_dir = Path(run_dir)
    log = load_ingested(run_dir / "ingest")
    template, rgb = load_template(run_dir)
    n, models = len(template), list(log.models)
    pixels0, template_cov, template_pose_cov, pixel_px = _template_observations(
        run_dir, n, len(models))
    base = _load_base(run_dir, base_frame(frame, config.registration.template_update_every),
                      config.registration.template_update_every, template, pixels0)
    every = config.target.new_points_every
    try:
        result = register_frame_step(
            template, rgb, template_cov, base, log.frame_images(base.frame),
            log.usable_poses(base.frame), log.frame_images(frame), log.usable_poses(frame),
            models, tool_pose_in_world(log.tool_poses[frame], config.tool),
            noise_from_report(log.report, log.cameras, pixel_px), config,
            add_new_points=bool(every and frame % every == 0),
            template_pose_cov=template_pose_cov)
    except GeometryError as exc:
        # Its cloud shows the base's positions, every point unknown.
        _write_frame(run_dir, frame, unregistered(n, len(models)), rgb, cloud_xyz=base.source,
                     error=str(exc))
        return {"frame": frame, "failed": str(exc), "base": base.frame}
    _write_frame(run_dir, frame, result, rgb)
    return {"frame": frame, "base": base.frame, "seconds_target": result.seconds_target,
            "seconds_register": result.seconds_register, "converged": result.converged,
            "tracking_px": result.target.noise.tracking_px, **result.target.counts()}


def _write_frame(run_dir: Path, frame: int, result: FrameResult, rgb: np.ndarray,
                 cloud_xyz: np.ndarray | None = None, error: str = "") -> None:
    """The frame's registration arrays and its cloud (at `cloud_xyz`, default the registered
    positions), atomically; `error` marks a frame that could not be registered."""
    n = len(rgb)
    target = result.target
    residual = result.residual.astype(np.float32)
    sigma = result.sigma.astype(np.float32)
    write_npz(
        registration_path(run_dir, frame),
        transforms=result.transforms.astype(np.float32),
        registered=result.registered,
        target=target.positions,
        status=target.status,
        residual=residual,
        sigma=sigma,
        target_sigma=target.sigma.astype(np.float32),
        target_covariance=target.covariance.astype(np.float32),
        target_pose_covariance=target.pose_covariance.astype(np.float32),
        support_mm=result.support_mm.astype(np.float32),
        pixels=target.pixels,
        tracking_px=np.float64(target.noise.tracking_px),
        converged=np.bool_(result.converged),
        seconds_target=np.float64(result.seconds_target),
        seconds_register=np.float64(result.seconds_register),
        new_points=np.int64(result.new_points),
        contact_points=np.int64(result.contact_points),
        failed=np.bool_(bool(error)),
        error=np.array(error),
    )
    write_cloud_ply(
        cloud_path(run_dir, frame),
        result.registered if cloud_xyz is None else cloud_xyz,
        rgb=rgb,
        point_id=np.arange(n, dtype=np.int32),
        label=np.full(n, UNKNOWN, np.uint8),
        residual=residual,
        extra={"status": target.status.astype(np.uint8), "views": target.views.astype(np.uint8),
               "sigma": sigma},
    )


def run_register(
    run_dir: Path, config: Config, on_frame: Callable[[int, int], None] | None = None,
    executor: Executor | None = None, after_frame: Callable[[int], Task] | None = None,
    on_after: Callable[[int, Any], None] | None = None,
) -> list[int]:
    """Register every frame not yet done; returns the frames processed by this call.

    Frames are independent tasks except for their base (`base_frame`): with re-basing
    every N_T frames, a frame waits for its base frame, a dependency chain over the bases.
    `executor` runs the tasks (default: serial); `on_frame(frame, n_frames)` is called as
    each frame finishes (progress), and run.json records every finished frame at once.
    `after_frame(frame)` may give a task to run on each frame once it is registered (e.g.
    its classification): in the same graph, such tasks fill the workers that the chain
    leaves idle; their results go to `on_after(frame, value)`.
    """
    run_dir = Path(run_dir)
    run = RunFolder(run_dir)
    previous = run.stage(STAGE)
    fingerprint = _fingerprint(config)
    same = previous.get("config") == fingerprint
    done_before = set(previous.get("frames_done", [])) if same else set()
    failed: dict[str, str] = dict(previous.get("frames_failed", {})) if same else {}
    with stage_run(
        run_dir,
        STAGE,
        config,
        needs=("ingest", "build-template"),
        config_sections=("topics", "ingest", "tool", "template"),
        keep=("frames_done", "frames_failed", "config"),
    ) as info:
        n_frames = load_ingested(run_dir / "ingest").n_frames
        done = {k for k in done_before if 0 < k < n_frames
                and registration_path(run_dir, k).is_file() and cloud_path(run_dir, k).is_file()}
        failed = {k: v for k, v in failed.items() if int(k) in done}
        _warn_failed(failed, resumed=True)
        every = config.registration.template_update_every
        frames = [k for k in range(1, n_frames) if k not in done]
        tasks = []
        for frame in frames:
            base = base_frame(frame, every)
            deps = (str(base),) if base and base not in done else ()
            tasks.append(Task(str(frame), register_frame, (run_dir.absolute(), frame, config),
                              deps))
        followers: dict[str, int] = {}
        for frame in frames if after_frame is not None else ():
            task = after_frame(frame)
            followers[task.key] = frame
            tasks.append(replace(task, deps=(*task.deps, str(frame))))

        def on_done(key: str, value: Any) -> None:
            if key in followers:
                if on_after is not None:
                    on_after(followers[key], value)
                return
            done.add(int(key))
            if isinstance(value, dict) and "failed" in value:
                failed[key] = value["failed"]
                _warn_failed({key: value["failed"]}, resumed=False)
            run.mark_stage(STAGE, "running", frames_done=sorted(done), frames_failed=failed,
                           config=fingerprint)
            if on_frame is not None:
                on_frame(int(key), n_frames)

        (executor or SerialExecutor()).run(tasks, on_done)
        info.update(frames_done=sorted(done), frames_failed=failed, config=fingerprint)
    return frames


def _warn_failed(failed: dict[str, str], resumed: bool) -> None:
    """One warning line per failed frame (on a resume: the frames that failed before and
    are not retried with the same config)."""
    for key in sorted(failed, key=int):
        when = "failed in an earlier run (same config, not retried)" if resumed else "failed"
        logger.warning("frame %s %s: %s; its points are unknown", key, when, failed[key])


def _fingerprint(config: Config) -> dict:
    """The config sections whose change invalidates registered frames."""
    d = json.loads(json.dumps(to_dict(config)))
    return {k: d[k] for k in ("target", "registration", "tool")}


def require_registered(run_dir: Path) -> None:
    if not RunFolder(run_dir).is_done(STAGE):
        raise RunFolderError(
            f"{run_dir}: frames are not registered; run `surgrecon register {run_dir}`"
        )
