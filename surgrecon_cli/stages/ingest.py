"""The ingest stage: log -> `RUN/ingest/` (frames, poses, intrinsics, images) + run.json.
Streams the log once (images written to disk as they arrive), synchronises images into
frames, interpolates tracker poses to each image stamp and the robot to each frame stamp
(`core.sync.streams`), and saves `IngestedLog`, built in a hidden staging folder renamed to
`RUN/ingest` only when complete (run.json says `ingest: done` only after that)."""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from ..config import Config
from ..core.geometry.poses import interpolate_poses
from ..core.noise.model import pose_jitter, shared_bodies
from ..core.sync.streams import (
    FrameGrouping,
    PoseStream,
    group_frames,
    interpolate_values,
    poses_at,
    rate_hz,
    select_frames,
)
from ..errors import InputError, RunFolderError, SurgReconError, quoted
from ..io.logs.log_input import resolve_log
from ..io.logs.reader import LogReader
from ..io.run.atomic import is_temporary
from ..io.run.folder import RunFolder
from ..io.run.ingest_store import IngestedLog, save_ingested, save_pose_streams
from ..io.run.layout import INGEST_STAGING_PREFIX, RunLayout
from .ingest_frames import check_clocks, log_span, world_poses
from .ingest_streams import StreamCollector, video_report
from .registry import StageContext
from .staleness import recorded_config

logger = logging.getLogger(__name__)

STAGE = "ingest"


@dataclass(frozen=True)
class IngestResult:
    """Outcome of ingest: sorted camera ids, number of frames, and the report
    ({"cameras": {id: {...}}, "frames": T, ...}, also stored in RUN/ingest/cameras.json)."""

    run_dir: Path
    cameras: tuple[str, ...]
    n_frames: int
    report: dict[str, Any]


def ingest(
    log_path: Path,
    run_dir: Path,
    config: Config,
    allow_truncated: bool = False,
    force: bool = False,
    on_bytes: Callable[[int], None] | None = None,
) -> IngestResult:
    """Ingest `log_path` into `run_dir` (created if needed).

    allow_truncated: use the data before damage instead of failing (complete frames only).
    force: replace an existing completed ingest (later stages must then re-run).
    on_bytes: progress callback, called with the number of bytes read from the log.
    Raises InputError / TopicError on a bad log, RunFolderError if `run_dir` is not usable.
    """
    log_path, run_dir = Path(log_path), Path(run_dir)
    reader = LogReader(log_path, config.topics, config.ingest.time_source, allow_truncated,
                       on_bytes, extra_tools=tuple(t.pose for t in config.tools))
    start = time.perf_counter()
    reader.check_magic()
    run, before = _prepare_run_folder(run_dir, log_path, config, force)
    layout = RunLayout(run_dir)
    for leftover in run_dir.glob(f"{INGEST_STAGING_PREFIX}*"):
        if RunLayout.is_ingest_staging(leftover) and not leftover.is_symlink():
            shutil.rmtree(leftover, ignore_errors=True)
    staging = layout.ingest_staging(uuid.uuid4().hex[:12])
    staging.mkdir()  # (mkdtemp would make it 0700; this respects the umask)
    try:
        with _warnings_kept() as warned:
            collector = StreamCollector(staging, config.topics.rectified)
            for item in reader:
                collector.add(item)
            collector.finish()
            reader.check_roles()
            log, report = _assemble(collector, reader, config, staging, allow_truncated)
        report["warnings"] = warned
        save_ingested(log)
        _swap_in(staging, layout.ingest_dir)
    except BaseException as exc:
        shutil.rmtree(staging, ignore_errors=True)
        message = str(exc) if isinstance(exc, SurgReconError) else type(exc).__name__
        with contextlib.suppress(OSError, RunFolderError):
            run.mark_stage(STAGE, "failed", error=message)
        raise
    if reader.damage:
        logger.warning("%s: %s; used the data before it (--allow-truncated): %d frames, %d "
                       "incomplete ones dropped", log_path, reader.damage, log.n_frames,
                       report["frames_dropped_after_damage"])
    cameras = list(log.cameras)
    run.update(input={"path": str(log_path.resolve()), "sha256": reader.sha256,
                      "bytes": reader.size},
               ingest={"cameras": cameras, "frames": log.n_frames})
    replaced = before.get("folder", "")
    if before.get("sha256") and before["sha256"] != reader.sha256:
        replaced = f"replaced the run of {before.get('path')} (another log) in this folder"
    run.mark_stage(STAGE, "done", cameras=cameras, frames=log.n_frames,
                   truncated=reader.damage, salvaged=reader.salvaged,
                   usable_views=int(log.usable.sum()),
                   seconds=round(time.perf_counter() - start, 3), replaced=replaced,
                   config=recorded_config(config, STAGE))
    return IngestResult(run_dir, log.cameras, log.n_frames, report)


def pipeline_step(ctx: StageContext, progress: Callable[[float], None]) -> None:
    """The stage within `surgrecon run`: progress by bytes read from the log."""
    size = max(resolve_log(ctx.log).size, 1)
    read = [0]

    def on_bytes(n: int) -> None:
        read[0] += n
        progress(read[0] / size)

    ingest(ctx.log, ctx.run_dir, ctx.config, allow_truncated=ctx.allow_truncated,
           force=ctx.force_ingest, on_bytes=on_bytes)
    ctx.force_ingest = False


@contextlib.contextmanager
def _warnings_kept() -> Iterator[list[str]]:
    """The warnings the package logs inside the block, kept (in order) for the ingest
    report, so that the run's report and summary.json list what the terminal showed."""
    kept: list[str] = []

    class Keep(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            kept.append(record.getMessage())

    handler = Keep(logging.WARNING)
    package = logging.getLogger(__name__.split(".")[0])
    package.addHandler(handler)
    try:
        yield kept
    finally:
        package.removeHandler(handler)


def _prepare_run_folder(run_dir: Path, log_path: Path, config: Config,
                        force: bool) -> tuple[RunFolder, dict[str, str]]:
    """The run folder, started afresh, and what was there before (`path`, `sha256` of the
    log of a run it held; `folder`: what --force wrote into), for the run's caveats."""
    run = RunFolder(run_dir)
    before: dict[str, str] = {}
    if run.exists():
        if run.is_done(STAGE) and not force:
            raise RunFolderError(
                f"{run_dir} already holds an ingested log; pass --force to replace it "
                "(later stages will re-run) or use a new run folder")
        before = {k: str(v) for k, v in run.read().get("input", {}).items()
                  if k in ("path", "sha256") and v}
    elif run_dir.exists():
        lock = RunLayout(run_dir).lock_file
        entries = [p for p in run_dir.iterdir() if p != lock]
        others = [p for p in entries if not _leftover(p)]
        if others and force:
            before["folder"] = (f"wrote into {run_dir}, a folder that was not a run folder; "
                                f"its {len(others)} other entries are kept")
            entries = []
        elif others:
            raise RunFolderError(f"{run_dir} exists, is not empty and has no run.json (it holds "
                                 f"{quoted(others[0].name)}, which surgrecon did not write); "
                                 "use a new or empty folder")
        for path in entries:  # of a run killed before it wrote run.json
            if path.is_dir() and not path.is_symlink():
                shutil.rmtree(path)
            else:
                path.unlink()
    run.start(log_path, config)
    run.mark_stage(STAGE, "running")
    return run, before


def _leftover(path: Path) -> bool:
    """A temporary file or staging folder of a run killed before it wrote run.json."""
    return is_temporary(path.name) or RunLayout.is_ingest_staging(path)


def _swap_in(staging: Path, final: Path) -> None:
    """Rename the staging folder to `final`, replacing an older one."""
    if final.exists():
        old = final.with_name(f"{INGEST_STAGING_PREFIX}old-{os.getpid()}")
        final.rename(old)
        staging.rename(final)
        shutil.rmtree(old, ignore_errors=True)
    else:
        staging.rename(final)


def _trim_incomplete_tail(frames: FrameGrouping, usable: np.ndarray) -> int:
    """Number of frames to keep after damage: drop trailing frames missing any camera."""
    keep = frames.n_frames
    while keep > 0 and not usable[keep - 1].all():
        keep -= 1
    return keep


def _assemble(collector: StreamCollector, reader: LogReader, config: Config, staging: Path,
              allow_truncated: bool) -> tuple[IngestedLog, dict[str, Any]]:
    """Sync, interpolate, validate, name the images by frame; returns the log and report."""
    with_images = {cid: cam for cid, cam in collector.cameras.items() if len(cam.stamps)}
    if not with_images:
        raise InputError(f"{reader.path}: no images on the image topics "
                         f"({', '.join(sorted(reader.channels)) or 'no topics'})")
    ids = tuple(sorted(with_images))
    cams = [with_images[c] for c in ids]
    for cid, cam in zip(ids, cams, strict=True):
        if cam.model is None:
            raise InputError(f"camera {cid}: images on {cam.image_topic} but no intrinsics on "
                             f"a topic matching topics.camera_info = {config.topics.camera_info!r}")
    orders = [np.argsort(np.array(cam.stamps, np.int64), kind="stable") for cam in cams]
    stamps = [np.array(cam.stamps, np.int64)[o] for cam, o in zip(cams, orders, strict=True)]
    poses_in_world = world_poses(ids, cams, collector.tool, reader, config, log_span(stamps),
                                 allow_truncated, collector.extra_tools,
                                 collector.cameras[""].poses if "" in collector.cameras else None)
    pose_streams, tool = poses_in_world.cameras, poses_in_world.tool
    gap_ns = round(config.ingest.pose_gap_ms * 1e6)

    tolerance_ns = round(config.ingest.sync_tolerance_ms * 1e6)
    frames = group_frames(stamps, tolerance_ns)
    T, C = frames.image_index.shape
    image_stamps = np.full((T, C), -1, dtype=np.int64)
    poses = np.full((T, C, 4, 4), np.nan)
    usable = np.zeros((T, C), dtype=bool)
    for c in range(C):
        rows = np.flatnonzero(frames.image_index[:, c] >= 0)
        image_stamps[rows, c] = stamps[c][frames.image_index[rows, c]]
        poses[rows, c], usable[rows, c] = poses_at(pose_streams[c], image_stamps[rows, c], gap_ns)
    check_clocks(cams, stamps, pose_streams, usable, reader, config)
    keep = _trim_incomplete_tail(frames, usable) if reader.damage else T
    if keep == 0:
        raise InputError(f"{reader.path}: no complete frame before the damage "
                         f"({reader.damage})")
    trimmed = T - keep
    part = config.ingest
    chosen = select_frames(frames.stamps_ns[:keep], part.start_s, part.duration_s, part.every)
    if not len(chosen):
        span = (frames.stamps_ns[keep - 1] - frames.stamps_ns[0]) / 1e9
        raise InputError(f"{reader.path}: no frame from {part.start_s:g} s for "
                         f"{part.duration_s:g} s (ingest.start_s, ingest.duration_s); its "
                         f"{keep} frames span {span:.3f} s from its first")
    T = len(chosen)
    frame_stamps = frames.stamps_ns[chosen]
    image_index, image_stamps = frames.image_index[chosen], image_stamps[chosen]
    poses, usable = poses[chosen], usable[chosen]

    robot = bool(config.topics.tool_pose)
    tool_poses, tool_valid = poses_at(tool, frame_stamps, gap_ns)
    extra = [poses_at(s, frame_stamps, gap_ns)[0] for s in poses_in_world.extra_tools]
    joint_stamps, joint_values = collector.joints()
    joint_positions = interpolate_values(joint_stamps, joint_values, frame_stamps, gap_ns)

    collector.save_videos(staging, ids)
    image_paths = _place_images(staging, cams, orders, image_index)
    jitter = [pose_jitter(s.stamps_ns, s.positions, s.quats) for s in pose_streams]
    report = _report(ids, cams, stamps, pose_streams, jitter, frames, image_index, usable,
                     trimmed)
    report["frames_in_log"] = keep
    report["start_s"] = float((frame_stamps[0] - frames.stamps_ns[0]) / 1e9)  # frame 0's
    if keep > T:
        report["part"] = {"start_s": part.start_s, "duration_s": part.duration_s,
                          "every": part.every}
    for cid, cam in zip(ids, cams, strict=True):
        report["cameras"][cid].update(video_report(cam, frame_stamps, tolerance_ns),
                                      pixel_max=cam.pixel_max,
                                      pose_source=poses_in_world.sources[cid],
                                      pose_conflicts=poses_in_world.conflicts.get(cid, 0))
    report["tracker_bodies"] = _tracker_bodies(ids, pose_streams, jitter, gap_ns)
    report["tool_pose_source"] = poses_in_world.sources.get("tool", "")
    report.update(robot=robot, tool_pose_topic=collector.tool_topic,
                  tool_rate_hz=rate_hz(tool.stamps_ns),
                  tool_pose_missing=int((~tool_valid).sum()) if robot else 0,
                  joint_rate_hz=rate_hz(joint_stamps), joints=list(collector.joint_names),
                  truncated=reader.damage, log=str(reader.path))
    if not robot:
        logger.warning("%s: no robot kinematics (topics.tool_pose = \"\"): tool removal is "
                       "off", reader.path)
    elif report["tool_pose_missing"]:
        logger.warning("tool pose unknown at %d of %d frames (gap > %g ms or outside the stream)",
                       report["tool_pose_missing"], T, config.ingest.pose_gap_ms)
    save_pose_streams(staging, pose_streams, tool)
    log = IngestedLog(
        root=staging, cameras=ids, models=tuple(cam.model for cam in cams if cam.model),
        stamps_ns=frame_stamps, image_stamps_ns=image_stamps, poses=poses, usable=usable,
        tool_poses=tool_poses, joint_names=collector.joint_names,
        joint_positions=joint_positions.reshape(T, len(collector.joint_names)),
        image_paths=image_paths, report=report,
        extra_tool_poses=np.stack(extra, 1) if extra else np.zeros((T, 0, 4, 4)),
    )
    return log, report


def _place_images(staging: Path, cams: list, orders: list[np.ndarray],
                  image_index: np.ndarray) -> tuple[tuple[str, ...], ...]:
    """Rename staged images to `images/CC/FFFFFF.ext` by frame; delete the unused ones."""
    T, C = image_index.shape
    paths = [["" for _ in range(C)] for _ in range(T)]
    for c, (cam, order) in enumerate(zip(cams, orders, strict=True)):
        for t in np.flatnonzero(image_index[:, c] >= 0):
            staged = cam.files[int(order[image_index[t, c]])]
            rel = RunLayout.image_relpath(c, int(t), staged.rsplit(".", 1)[1])
            (staging / rel).parent.mkdir(parents=True, exist_ok=True)
            os.replace(staging / staged, staging / rel)
            paths[t][c] = rel
    shutil.rmtree(RunLayout.staged_dir(staging), ignore_errors=True)
    return tuple(tuple(row) for row in paths)


def _tracker_bodies(ids: tuple[str, ...], streams: list[PoseStream],
                    own: list[tuple[float, float]], gap_ns: int) -> list[list[str]]:
    """Cameras that share one tracked body (core/noise.shared_bodies), by camera id, from
    each stream's own jitter `own` (σ_pos m, σ_rot rad): j's stream interpolated at i's
    stamps gives the relative pose stream, whose jitter is ~0 when both follow one
    marker."""
    relative = {}
    for i in range(len(streams)):
        for j in range(i + 1, len(streams)):
            a, b = streams[i], streams[j]
            pos_b, quat_b, valid = interpolate_poses(b.stamps_ns, b.positions, b.quats,
                                                     a.stamps_ns, gap_ns)
            if valid.sum() < 3:
                continue
            rot_a = Rotation.from_quat(a.quats[valid])
            rel_rot = rot_a.inv() * Rotation.from_quat(quat_b[valid])
            rel_pos = rot_a.inv().apply(pos_b[valid] - a.positions[valid])
            relative[(i, j)] = pose_jitter(a.stamps_ns[valid], rel_pos, rel_rot.as_quat())
    return [[ids[c] for c in group] for group in shared_bodies(own, relative)]


def _jitter(position: float, rotation: float) -> dict[str, float | None]:
    """A pose stream's measured per-axis noise (m, rad; core/noise/model.py) in mm and degrees."""
    return {"tracker_jitter_mm": float(position * 1e3) if np.isfinite(position) else None,
            "tracker_jitter_deg": float(np.degrees(rotation)) if np.isfinite(rotation) else None}


def _report(ids: tuple[str, ...], cams: list, stamps: list[np.ndarray], pose_streams: list,
            jitter: list[tuple[float, float]], frames: FrameGrouping, image_index: np.ndarray,
            usable: np.ndarray, trimmed: int) -> dict[str, Any]:
    T = image_index.shape[0]
    per_camera = {}
    for c, cid in enumerate(ids):
        present = image_index[:, c] >= 0
        per_camera[cid] = {
            "index": c,
            "image_topic": cams[c].image_topic,
            "camera_info_topic": cams[c].info_topic,
            "pose_topic": cams[c].poses.name if cams[c].poses else "",
            "images": len(stamps[c]),
            "frames": int(present.sum()),
            "dropped": int(T - present.sum()),
            "late": int(frames.late[c]),
            "duplicates": int(frames.duplicates[c]),
            "pose_gaps": int((present & ~usable[:, c]).sum()),
            "usable": int(usable[:, c].sum()),
            "image_rate_hz": rate_hz(stamps[c]),
            "tracker_rate_hz": rate_hz(pose_streams[c].stamps_ns),
            **_jitter(*jitter[c]),
        }
        if per_camera[cid]["pose_gaps"]:
            logger.warning("camera %s: no tracked pose within the gap limit at %d of its images; "
                           "the camera is unusable in those frames", cid,
                           per_camera[cid]["pose_gaps"])
    return {"cameras": per_camera, "frames": T, "frames_all_usable": int(usable.all(axis=1).sum()),
            "frames_dropped_after_damage": trimmed}
