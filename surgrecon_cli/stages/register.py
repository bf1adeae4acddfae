"""Stage `register`: target cloud and non-rigid registration of every frame k >= 1.

Per frame k, one task (`register_frame`): the frame step of core/registration/frame_step.py (target
cloud G_k tracked from the base frame's images, points lost there re-acquired from the
template's frame-0 images, gated by the run's measured noise; registration of
the base's cloud to G_k; per-point uncertainty). The base is frame 0, or with re-basing
every N_T frames the last multiple of N_T before k: frames depend on their base only, so
they run in parallel on an executor, as a dependency chain over the bases. A frame that
cannot be registered is recorded as failed (its points unknown) and the run goes on; a
frame whose base failed is registered from that base's own base. Output, written
atomically frame by frame so a killed run resumes: RUN/registration/FFFFFF.npz, one
`io/artefacts.FrameRegistration` per frame (the clouds are written once, by classify).
"""

from __future__ import annotations

import functools
import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from ..config import Config
from ..core.noise.model import noise_from_report
from ..core.registration.frame_step import BaseState, FrameRegistrar, FrameResult, unregistered
from ..core.target.frame_inputs import FrameInput, Sighting, TemplateData
from ..core.target.tracking import TrackingView, tracking_view
from ..errors import GeometryError
from ..executors import Executor, Task
from ..executors.heap import adapted_heap
from ..executors.serial import SerialExecutor
from ..io.run.artefacts import (
    FrameRegistration,
    read_observations,
    read_registration,
    read_template,
    write_registration,
)
from ..io.run.atomic import file_identity
from ..io.run.folder import FrameProgress, RunFolder
from ..io.run.ingest_store import IngestedLog, ingest_identity, load_ingested
from ..io.run.layout import RunLayout
from .common import stage_run, tool_poses, tools_per_camera
from .registry import CLASSIFY_FRAME_TASK, StageContext, resolve
from .staleness import recorded_config, same_config

logger = logging.getLogger(__name__)

STAGE = "register"


def base_frame(frame: int, update_every: int) -> int:
    """The template base of `frame`: 0, or with re-basing every N_T frames the last
    multiple of N_T before it. Frame k is tracked from its base's images and registered
    from its base's registered cloud, so frames only depend on their base."""
    return ((frame - 1) // update_every) * update_every if update_every else 0


def tracks_locked(frame: int, base: int, update_every: int) -> bool:
    """Whether `frame`'s tracks are locked to the template (`FrameInput.lock`): all but
    those of a frame one step from its base (the registered frame it is tracked from) that
    is no later frame's base (the next frame's base is the latest: `base_frame`)."""
    return frame - 1 != base or base_frame(frame + 1, update_every) == frame


def _load_base(layout: RunLayout, log: IngestedLog, frame: int, update_every: int,
               template: TemplateData) -> BaseState:
    """The base state of `frame` with its views; a failed base frame is replaced by its own
    base."""
    n = len(template.points)
    while frame > 0:
        reg = read_registration(layout, frame, n)
        if not reg.failed:
            seen = Sighting(frame_views(log, frame), log.usable_poses(frame),
                            reg.pixels.astype(float))
            return BaseState(frame, reg.transforms.astype(float), reg.registered,
                             np.where(np.isfinite(reg.target), reg.target, reg.registered),
                             seen)
        frame = base_frame(frame, update_every)
    seen = Sighting(frame_views(log, 0), log.usable_poses(0), template.pixels)
    return BaseState(0, np.tile(np.eye(3, 4), (n, 1, 1)), template.points, template.points,
                     seen)


_VIEWS: OrderedDict[tuple, tuple[TrackingView | None, ...]] = OrderedDict()
_VIEWS_LOCK = threading.Lock()
VIEW_FRAMES = 4  # frames whose views a process keeps: the template's, the base's, the
# previous one's (tracked through) and the frame's


def frame_views(log: IngestedLog, frame: int) -> list[TrackingView | None]:
    """A frame's images prepared for tracking (decoded, grey, noise level), built once per
    process: the frames of one base are tracked from the same views, and a frame that is
    itself a base (re-basing) is tracked into and then from; a worker often registers
    them in turn. Keyed by the ingest folder, its files' identity and the frame."""
    key = (str(Path(log.root).absolute()), ingest_identity(log.root), frame)
    with _VIEWS_LOCK:  # a Dask worker may run tasks on several threads
        if key not in _VIEWS:
            _VIEWS[key] = tuple(None if image is None else tracking_view(image)
                                for image in log.frame_images(frame))
            while len(_VIEWS) > VIEW_FRAMES:
                _VIEWS.popitem(last=False)
        _VIEWS.move_to_end(key)
        return list(_VIEWS[key])


@functools.lru_cache(maxsize=1)
def _registrar(run_dir: str, _identity: tuple, config: Config) -> FrameRegistrar:
    """The run's frame step, built once per process (a worker registers many frames);
    keyed by the run folder, its ingest and template files' identity and the config. The
    process's heap keeps the frames' image-sized buffers (`executors.heap.adapted_heap`)."""
    adapted_heap()
    layout = RunLayout(Path(run_dir))
    log = load_ingested(layout.ingest_dir)
    cloud = read_template(layout)
    n, models = len(cloud.points), list(log.models)
    obs = read_observations(layout, n)
    template = TemplateData(cloud.points, cloud.rgb, obs.total_covariance, obs.pose_covariance,
                            obs.pixels_by_camera(n, len(models)))
    noise = noise_from_report(log.report, log.cameras, obs.pixel_noise_px)
    return FrameRegistrar(template, models, noise, config, anchor=frame_views(log, 0))


def _frame_input(log: IngestedLog, config: Config, frame: int,
                 images: list[np.ndarray | None] | None = None,
                 previous: FrameInput | None = None, lock: bool = True) -> FrameInput:
    """A frame's tracking views, usable poses and tools (with each camera's view of them
    where `tool.camera_offsets` moves them), its RGB images when new points are to be
    triangulated, the frame tracked through on the way from the base, and whether its
    tracks are locked to the template (`FrameInput.lock`)."""
    tools = tool_poses(log, config, frame)
    return FrameInput(frame, frame_views(log, frame), log.usable_poses(frame), tools, images,
                      camera_tool_pose=tools_per_camera(tools, log, config),
                      previous=previous, lock=lock)


def register_frame(run_dir: Path, frame: int, config: Config) -> dict:
    """Target cloud and registration of one frame k >= 1 against its base (a task: reads
    the run folder, writes RUN/registration/k.npz atomically). Returns the frame's timings
    and counts, or its failure."""
    layout = RunLayout(run_dir)
    log = load_ingested(layout.ingest_dir)
    identity = (ingest_identity(layout.ingest_dir),
                file_identity(layout.template_ply, layout.observations))
    registrar = _registrar(str(layout.root.absolute()), identity, config)
    template = registrar.template
    every = config.registration.template_update_every
    start = time.perf_counter()
    base = _load_base(layout, log, base_frame(frame, every), every, template)
    new_every = config.target.new_points_every
    images = log.frame_images(frame) if new_every and frame % new_every == 0 else None
    # the previous frame, when it lies after the base, is tracked through
    # (core/target/track_points._via)
    previous = _frame_input(log, config, frame - 1) if frame - 1 > base.frame else None
    inputs = _frame_input(log, config, frame, images, previous,
                          lock=tracks_locked(frame, base.frame, every))
    seconds_views = time.perf_counter() - start  # counted with the target: its images
    try:
        result = registrar.step(inputs, base)
    except GeometryError as exc:
        why = str(exc) + _unusable_cameras(log, frame)
        write_registration(layout, frame, _artefact(
            unregistered(len(template.points), len(registrar.rig.models)), base.frame, why))
        return {"frame": frame, "failed": why, "base": base.frame}
    result = replace(result, seconds_target=result.seconds_target + seconds_views)
    write_registration(layout, frame, _artefact(result, base.frame))
    return {"frame": frame, "base": base.frame, "seconds_target": result.seconds_target,
            "seconds_register": result.seconds_register, "converged": result.converged,
            "tracking_px": result.target.noise.tracking_px, **result.target.counts()}


def _unusable_cameras(log: IngestedLog, frame: int) -> str:
    """"; camera 'right' had no usable image ..." for the cameras a failed frame lacked (a
    dropped or late image, no pose), else "": one eye missing from a stereo frame leaves
    nothing to triangulate, and the counts alone did not say why."""
    missing = [repr(c) for c, ok in zip(log.cameras, log.usable[frame], strict=True) if not ok]
    if not missing:
        return ""
    which = f"camera {missing[0]}" if len(missing) == 1 else f"cameras {', '.join(missing)}"
    return (f"; {which} had no usable image in this frame (dropped, late or without a pose: "
            "see ingest's table)")


def _artefact(result: FrameResult, base: int, error: str = "") -> FrameRegistration:
    """The frame's registration as stored; `error` marks a frame that could not be
    registered."""
    target = result.target
    return FrameRegistration(
        transforms=result.transforms, registered=result.registered, target=target.positions,
        status=target.status, views=target.views, residual=result.residual,
        sigma=result.sigma, target_sigma=target.sigma, target_covariance=target.covariance,
        target_pose_covariance=target.pose_covariance, support_mm=result.support_mm,
        pixels=target.pixels, tracking_px=float(target.noise.tracking_px),
        tracking_shared_px=float(target.noise.tracking_shared_px), base=base,
        converged=bool(result.converged), failed=bool(error), error=error,
        seconds_target=float(result.seconds_target),
        seconds_register=float(result.seconds_register), new_points=int(result.new_points),
        contact_points=int(result.contact_points))


def run_register(
    run_dir: Path, config: Config, on_frame: Callable[[int, int], None] | None = None,
    executor: Executor | None = None, after_frame: Callable[[int], Task] | None = None,
    on_after: Callable[[int, Any], None] | None = None,
) -> list[int]:
    """Register every frame not yet done; returns the frames processed by this call.

    Frames are independent tasks except for their base (`base_frame`): with re-basing
    every N_T frames, a frame waits for its base frame, a dependency chain over the bases.
    `executor` runs the tasks (default: serial); `on_frame(frame, n_frames)` is called as
    each frame finishes (progress); the progress record (RUN/registration/progress.jsonl)
    records every finished frame at once, run.json their counts.
    `after_frame(frame)` may give a task to run on each frame once it is registered (e.g.
    its classification): in the same graph, such tasks fill the workers that the chain
    leaves idle; their results go to `on_after(frame, value)`.
    """
    layout = RunLayout(run_dir)
    run = RunFolder(layout.root)
    made_with = recorded_config(config, STAGE)
    progress = FrameProgress(layout.register_progress)
    recorded = progress.read() if same_config(run, STAGE, config) else {}
    with stage_run(layout.root, STAGE, config,
                   keep=("frames_done", "frames_failed", "config")) as info:
        n_frames = load_ingested(layout.ingest_dir).n_frames
        recorded = {k: why for k, why in recorded.items()
                    if 0 < k < n_frames and layout.registration(k).is_file()}
        done = set(recorded)
        failed = {str(k): why for k, why in recorded.items() if why}
        _warn_failed(failed, resumed=True)
        layout.registration_dir.mkdir(parents=True, exist_ok=True)
        progress.restart(recorded)
        record = _throttled(lambda: run.mark_stage(
            STAGE, "running", frames_done=len(done), frames_failed=failed, config=made_with))
        record(force=True)
        every = config.registration.template_update_every
        frames = [k for k in range(1, n_frames) if k not in done]
        tasks = []
        for frame in frames:
            base = base_frame(frame, every)
            deps = (str(base),) if base and base not in done else ()
            tasks.append(Task(str(frame), register_frame,
                              (layout.root.absolute(), frame, config), deps))
        followers: dict[str, int] = {}
        if after_frame is not None:
            for frame in frames:
                task = after_frame(frame)
                followers[task.key] = frame
                tasks.append(replace(task, deps=(*task.deps, str(frame))))

        def on_done(key: str, value: Any) -> None:
            if key in followers:
                if on_after is not None:
                    on_after(followers[key], value)
                return
            done.add(int(key))
            why = value["failed"] if isinstance(value, dict) and "failed" in value else ""
            progress.append(int(key), why)
            if why:
                failed[key] = why
                _warn_failed({key: why}, resumed=False)
            record(force=len(done) == 1)
            if on_frame is not None:
                on_frame(int(key), n_frames)

        try:
            (executor or SerialExecutor()).run(tasks, on_done)
        finally:
            record(force=True)
        info.update(frames_done=len(done), frames_failed=failed)
    return frames


def _throttled(write: Callable[[], None], seconds: float = 1.0) -> Callable[..., None]:
    """`write` as a function that does it at most every `seconds` s unless forced: run.json
    holds the progress counts, the frames themselves are in the progress record."""
    last = [-np.inf]

    def maybe(force: bool = False) -> None:
        now = time.monotonic()
        if force or now - last[0] >= seconds:
            write()
            last[0] = now
    return maybe


def pipeline_step(ctx: StageContext, progress: Callable[[float], None]) -> None:
    """The stage within `surgrecon run`: frames are classified as they are registered, on
    workers the chain of base frames leaves idle; classify then has only the rest to do."""
    classify_task = resolve(CLASSIFY_FRAME_TASK)
    count = [0]

    def on_frame(_frame: int, n: int) -> None:
        count[0] += 1
        progress(count[0] / max(n - 1, 1))

    run_register(ctx.run_dir, ctx.config, on_frame=on_frame, executor=ctx.executor,
                 after_frame=functools.partial(classify_task, ctx.run_dir, ctx.config),
                 on_after=ctx.classified.__setitem__)


def _warn_failed(failed: dict[str, str], resumed: bool) -> None:
    """One warning line per failed frame (on a resume: the frames that failed before and
    are not retried with the same config)."""
    for key in sorted(failed, key=int):
        when = "failed in an earlier run (same config, not retried)" if resumed else "failed"
        logger.warning("frame %s %s: %s; its points are unknown", key, when, failed[key])
