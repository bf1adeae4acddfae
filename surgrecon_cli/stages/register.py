"""Stage `register`: target cloud and non-rigid registration of every frame k >= 1.

Per frame k, one task (`register_frame`): the target cloud G_k (template points tracked
from the base frame's images into frame k's and sorted by the reprojection-error check,
core/target.py), then the base's cloud registered to G_k (core/registration). The base is
frame 0, or with re-basing every N_T frames the last multiple of N_T before k: frames depend
on their base only, so they run in parallel on an executor, as a dependency chain over the
bases. Measured on the shipped sample (frames 1..19): N_T = 2 (default) registration p95
0.43 mm, max 1.94 mm, 99.7 % within 1 mm, macro-F1 0.917; N_T = 3: 0.47 / 2.84 mm, 99.3 %,
0.919; N_T = 0 (all tracked from frame 0): 0.71 / 4.71 mm, 96.5 %, 0.884 (the dent moves too
far for KLT from frame 0). Outputs, written atomically frame by frame so a killed run
resumes:
  RUN/registration/NNNNNN.npz   transforms (N,3,4) f32, registered (N,3), target (N,3),
                                status (N,) u8, residual (N,) f32, pixels (N,C,2) f64,
                                seconds_target, seconds_register
  RUN/clouds/NNNNNN.ply         registered positions, template colours, point_id,
                                label 255 (until classified), residual
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..config import Config, to_dict
from ..core.labels import INTER, INTRA, UNOBSERVED
from ..core.registration import register
from ..core.target import build_target, new_target_points
from ..core.template import build_template
from ..core.tool import push_out_of_tool, tool_pose_in_world
from ..errors import GeometryError, RunFolderError
from ..executors import Executor, Task
from ..executors.serial import SerialExecutor
from ..io.atomic import write_npz
from ..io.ingest_store import load_ingested
from ..io.ply import read_ply, write_cloud_ply
from ..io.run_folder import RunFolder
from .common import stage_run
from .template import cloud_path

STAGE = "register"
UNKNOWN_LABEL = 255


def registration_path(run_dir: Path, frame: int) -> Path:
    return Path(run_dir) / "registration" / f"{frame:06d}.npz"


def compose(outer: np.ndarray, inner: np.ndarray) -> np.ndarray:
    """Affine composition (N, 3, 4): x -> outer(inner(x))."""
    A = outer[:, :, :3] @ inner[:, :, :3]
    b = np.einsum("nij,nj->ni", outer[:, :, :3], inner[:, :, 3]) + outer[:, :, 3]
    return np.concatenate([A, b[:, :, None]], axis=2)


def load_template(run_dir: Path) -> tuple[np.ndarray, np.ndarray]:
    """Template points (N, 3) m and colours (N, 3) uint8 from RUN/template.ply."""
    cloud = read_ply(Path(run_dir) / "template.ply")
    order = np.argsort(cloud["point_id"])
    xyz = np.column_stack([cloud["x"], cloud["y"], cloud["z"]]).astype(float)[order]
    rgb = np.column_stack([cloud["red"], cloud["green"], cloud["blue"]]).astype(np.uint8)[order]
    return xyz, rgb


def _initial_pixels(run_dir: Path, n_points: int, n_cams: int) -> np.ndarray:
    """Where each template point was seen at frame 0 (N, C, 2), NaN where not."""
    with np.load(Path(run_dir) / "template" / "observations.npz", allow_pickle=False) as z:
        pixels = np.full((n_points, n_cams, 2), np.nan)
        pixels[z["point"], z["camera"]] = z["pixels"]
    return pixels


def base_frame(frame: int, update_every: int) -> int:
    """The template base of `frame`: 0, or with re-basing every N_T frames the last
    multiple of N_T before it. Frame k is tracked from its base's images and registered
    from its base's registered cloud, so frames only depend on their base."""
    return ((frame - 1) // update_every) * update_every if update_every else 0


@dataclass(frozen=True)
class _Base:
    """What frames are registered against: the base frame's index, its transforms from
    the frame-0 template (N, 3, 4), registered points (N, 3) m, latest positions (N, 3) m
    (target where observed, else registered) and where points were seen (N, C, 2) px."""

    frame: int
    transforms: np.ndarray
    source: np.ndarray
    latest: np.ndarray
    pixels: np.ndarray


def _load_base(run_dir: Path, frame: int, template: np.ndarray, n_cams: int) -> _Base:
    n = len(template)
    if frame == 0:
        return _Base(0, np.tile(np.eye(3, 4), (n, 1, 1)), template, template,
                     _initial_pixels(run_dir, n, n_cams))
    with np.load(registration_path(run_dir, frame), allow_pickle=False) as z:
        registered, target = z["registered"], z["target"]
        return _Base(frame, z["transforms"].astype(float), registered,
                     np.where(np.isfinite(target), target, registered), z["pixels"].astype(float))


def register_frame(run_dir: Path, frame: int, config: Config) -> dict:
    """Target cloud and registration of one frame k >= 1 against its base (a task: reads
    the run folder, writes RUN/registration/k.npz and RUN/clouds/k.ply atomically).
    Returns the frame's timings and counts."""
    run_dir = Path(run_dir)
    log = load_ingested(run_dir / "ingest")
    template, rgb = load_template(run_dir)
    n, models = len(template), list(log.models)
    base = _load_base(run_dir, base_frame(frame, config.registration.template_update_every),
                      template, len(models))
    cur_images = log.frame_images(frame)
    cur_poses = log.usable_poses(frame)
    tool_pose = tool_pose_in_world(log.tool_poses[frame], config.tool)
    start = time.perf_counter()
    target = build_target(template, base.latest, log.frame_images(base.frame), cur_images,
                          log.usable_poses(base.frame), cur_poses, base.pixels, models,
                          tool_pose, config.target, config.tool)
    has_target = (target.status == INTRA) | (target.status == INTER)
    ids = np.flatnonzero(has_target)
    target_xyz, target_rgb = target.positions[ids], rgb[ids]
    n_new = 0
    every = config.target.new_points_every
    if every and frame % every == 0:
        new_xyz, new_rgb = _new_points(cur_images, cur_poses, models, tool_pose, target_xyz,
                                       config)
        n_new = len(new_xyz)
        target_xyz = np.concatenate([target_xyz, new_xyz])
        target_rgb = np.concatenate([target_rgb, new_rgb])
        ids = np.concatenate([ids, np.full(n_new, -1)])
    seconds_target = time.perf_counter() - start
    start = time.perf_counter()
    result, n_contact = register_with_contact(
        base.source, rgb, target_xyz, target_rgb, ids,
        _data_weights(target.status, has_new=n_new > 0), tool_pose, config)
    seconds_register = time.perf_counter() - start
    residual = np.nan_to_num(result.residuals, nan=0.0).astype(np.float32)
    write_npz(
        registration_path(run_dir, frame),
        transforms=compose(result.transforms, base.transforms).astype(np.float32),
        registered=result.registered,
        target=target.positions,
        status=target.status,
        residual=residual,
        pixels=target.pixels,
        seconds_target=np.float64(seconds_target),
        seconds_register=np.float64(seconds_register),
        new_points=np.int64(n_new),
        contact_points=np.int64(n_contact),
    )
    write_cloud_ply(
        cloud_path(run_dir, frame),
        result.registered,
        rgb=rgb,
        point_id=np.arange(n, dtype=np.int32),
        label=np.full(n, UNKNOWN_LABEL, np.uint8),
        residual=residual,
        extra={"status": target.status.astype(np.uint8), "views": target.views.astype(np.uint8)},
    )
    return {"frame": frame, "seconds_target": seconds_target,
            "seconds_register": seconds_register, **target.counts()}


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
    done_before = (
        set(previous.get("frames_done", [])) if previous.get("config") == fingerprint else set()
    )
    with stage_run(
        run_dir,
        STAGE,
        config,
        needs=("ingest", "build-template"),
        config_sections=("topics", "ingest", "tool", "template"),
        keep=("frames_done", "config"),
    ) as info:
        n_frames = load_ingested(run_dir / "ingest").n_frames
        done = {k for k in done_before if 0 < k < n_frames
                and registration_path(run_dir, k).is_file() and cloud_path(run_dir, k).is_file()}
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
            run.mark_stage(STAGE, "running", frames_done=sorted(done), config=fingerprint)
            if on_frame is not None:
                on_frame(int(key), n_frames)

        (executor or SerialExecutor()).run(tasks, on_done)
        info.update(frames_done=sorted(done), config=fingerprint)
    return frames


def register_with_contact(source: np.ndarray, source_rgb: np.ndarray, target_xyz: np.ndarray,
                          target_rgb: np.ndarray, target_ids: np.ndarray, weights: np.ndarray,
                          tool_pose: np.ndarray, config: Config, passes: int = 2):
    """Register, then keep the tissue out of the tool (robot kinematics, Su et al. 2019
    section II.C): points without data (unobserved: under the tool, hidden by it) that the
    registration leaves inside the tool's capsule get a target on the capsule's surface,
    pushed along the shaft, and the registration is run again (up to `passes` times).
    Returns the result and the number of such contact points."""
    result = register(source, target_xyz, source_rgb=source_rgb, target_rgb=target_rgb,
                      config=config.registration, target_ids=target_ids, weights=weights)
    contact = np.zeros(len(source), bool)
    for _ in range(passes):
        inside, pushed = push_out_of_tool(result.registered, tool_pose, config.tool)
        new = inside & (weights == 0) & ~contact
        if not new.any():
            break
        contact |= new
        fresh = np.flatnonzero(new)
        target_xyz = np.concatenate([target_xyz, pushed[fresh]])
        target_rgb = np.concatenate([target_rgb, source_rgb[fresh]])
        target_ids = np.concatenate([target_ids, fresh])
        weights = np.where(new, 1.0, weights)
        result = register(source, target_xyz, source_rgb=source_rgb, target_rgb=target_rgb,
                          config=config.registration, target_ids=target_ids, weights=weights)
    return result, int(contact.sum())


def _data_weights(status: np.ndarray, has_new: bool) -> np.ndarray:
    """Data weight per template point: tracked points (intra/inter) 1; unobserved points 0,
    so they follow their neighbours, unless new points were triangulated this frame: then
    they may match one by nearest neighbour (gated). Outliers always 0."""
    tracked = (status == INTRA) | (status == INTER)
    if has_new:
        tracked |= status == UNOBSERVED
    return tracked.astype(float)


def _new_points(images: list[np.ndarray | None], poses: np.ndarray, models: list,
                tool_pose: np.ndarray, tracked: np.ndarray, config: Config):
    """New features of the frame triangulated as in the template build, away from the
    tracked points: (M, 3) m and colours (M, 3) uint8."""
    try:
        fresh = build_template(images, models, poses, tool_pose, config.template, config.tool)
    except GeometryError:
        return np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
    return new_target_points(fresh.points, fresh.rgb, tracked,
                             config.target.new_point_spacing_mm * 1e-3)


def _fingerprint(config: Config) -> dict:
    """The config sections whose change invalidates registered frames."""
    d = json.loads(json.dumps(to_dict(config)))
    return {k: d[k] for k in ("target", "registration", "tool")}


def require_registered(run_dir: Path) -> None:
    if not RunFolder(run_dir).is_done(STAGE):
        raise RunFolderError(
            f"{run_dir}: frames are not registered; run `surgrecon register {run_dir}`"
        )
