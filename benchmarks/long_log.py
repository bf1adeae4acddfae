"""Ingest scale benchmark: a long synthetic 6-camera MCAP log, written fast, and the peak
RSS / wall time of `surgrecon ingest` on it.

    .venv/bin/python benchmarks/long_log.py /tmp/longlog/long.mcap --gigabytes 2.1 --minutes 30
    .venv/bin/python benchmarks/long_log.py /tmp/longlog/long.mcap --gigabytes 2.1 --measure

Writing: the simulator renders `distinct_frames` frames of all cameras once (`LogBuilder`);
the long log replays their JPEG bytes (order 0 2 4 6 7 5 3 1 0 2 ... for 8 frames) while the
scene clock follows the same schedule, piecewise linearly, so every image still matches its
tracker poses and the robot state (to ~0.1 mm, from the cameras' few-ms clock offsets).
Tracker poses (true poses, no tracker noise), tool pose and joint states are evaluated from
the simulator's `Motion` at its rates (40 Hz, 100 Hz) and everything goes through the
simulator's `write_log` (ROS 2, cdr, zstd chunks of 1 MiB): the same topics, schemas, stamps
and log-time offsets as `surgrecon simulate`, so `configs/default.toml` reads it. Messages
are generated lazily and merged by log time: memory stays bounded whatever the length.

Length: the log spans `minutes` of log time and holds about `target_bytes` (the image frame
rate is chosen to get both, unless given). With 640x480 JPEG at quality 92 (~64 KB an
image), 2.1 GB in 30 minutes means ~3 Hz per camera.

Measuring: `measure_ingest` runs `surgrecon ingest --quiet` in a child process and takes its
peak RSS from the kernel's rusage of that child (ru_maxrss, through a tiny launcher process).
"""

from __future__ import annotations

import argparse
import dataclasses
import heapq
import json
import math
import shutil
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from surgrecon_cli.core.geometry.poses import matrix_to_quat
from surgrecon_cli.io.logs.records import (
    CameraInfoRecord,
    ImageRecord,
    JointStateRecord,
    PoseRecord,
)
from surgrecon_cli.sim.log_writer import write_log
from surgrecon_cli.sim.motion import Motion
from surgrecon_cli.sim.scene import SimConfig
from surgrecon_cli.sim.simulate import JOINTS, T0_NS, WORLD, LogBuilder

Message = tuple[str, int, object]
GB = 1e9
# File bytes per message, measured on these logs: an image adds its CDR payload + ~50 B
# (record header, message index entry; JPEG does not compress); the small messages compress
# (zstd, ~3x) to ~50 B each with their headers, a CameraInfo to ~100 B.
_IMAGE_OVERHEAD = 50
_SMALL_BYTES = 50
_INFO_BYTES = 100
_SIZE_MARGIN = 1.005  # aim 0.5 % above target_bytes: the estimate is within ~1 %


@dataclass(frozen=True)
class LongLogInfo:
    """What `write_long_log` wrote."""

    path: Path
    bytes: int
    minutes: float
    frames: int
    frame_rate: float
    images: int
    messages: int
    seconds: float


@dataclass(frozen=True)
class _Rendered:
    """The rendered frames: images[k][c], intrinsics infos[c], each image's stamp minus its
    frame time (camera clock offset + jitter, s) offsets[k, c], and the simulator state."""

    images: list[list[ImageRecord]]
    infos: list[CameraInfoRecord]
    offsets: np.ndarray
    builder: LogBuilder


def _ns(t: float) -> int:
    return T0_NS + round(t * 1e9)


def _schedule(k: int) -> list[int]:
    """Order in which the k distinct frames are replayed: evens up, odds down (0 2 4 6 7 5 3 1
    for k = 8), so that scene time moves by at most two frames per frame and an image never
    repeats within k frames (zstd would otherwise find repeats inside a chunk)."""
    return list(range(0, k, 2)) + list(range(k - 1 - (k % 2), 0, -2))


def _scene_time(t: float, order: list[int], rate: float) -> float:
    """Scene time at log time t (s): piecewise linear through the replayed frames' times."""
    u = t * rate
    i = math.floor(u)
    a, b = order[i % len(order)], order[(i + 1) % len(order)]
    return (a + (u - i) * (b - a)) / rate


def _render(cfg: SimConfig) -> _Rendered:
    """Render `cfg.frames` frames of all cameras with the simulator (its own message stream)."""
    builder = LogBuilder(cfg)
    images: list[list[ImageRecord | None]] = [[None] * cfg.cameras for _ in range(cfg.frames)]
    infos: list[CameraInfoRecord | None] = [None] * cfg.cameras
    seen = [0] * cfg.cameras
    for topic, _log_ns, record in builder.messages():
        cam_part = topic.split("/")[1]
        if not cam_part.startswith("endoscope_"):
            continue
        cam = int(cam_part.removeprefix("endoscope_"))
        if isinstance(record, ImageRecord):
            images[seen[cam]][cam] = record
            seen[cam] += 1
        elif isinstance(record, CameraInfoRecord):
            infos[cam] = record
    offsets = np.array(
        [[builder.image_stamp(k, c) - builder.frame_times[k] for c in range(cfg.cameras)]
         for k in range(cfg.frames)]
    )
    return _Rendered(images, infos, offsets, builder)  # type: ignore[arg-type]


def _frame_bytes(r: _Rendered) -> float:
    """Estimated file bytes of one frame's images and intrinsics (all cameras)."""
    mean = float(np.mean([[len(i.data) for i in row] for row in r.images]))
    return len(r.infos) * (mean + _IMAGE_OVERHEAD + _INFO_BYTES)


def _image_stream(r: _Rendered, n_frames: int, rate: float) -> Iterator[Message]:
    """CameraInfo + image of every camera per frame, as the simulator lays them out."""
    order = _schedule(len(r.images))
    for f in range(n_frames):
        d = order[f % len(order)]
        batch = []
        for c, image in enumerate(r.images[d]):
            stamp = _ns(f / rate + r.offsets[d, c])
            log_ns = stamp + 3_000_000
            batch.append((f"/endoscope_{c}/calibration", log_ns,
                          dataclasses.replace(r.infos[c], stamp_ns=stamp)))
            batch.append((f"/endoscope_{c}/color/compressed", log_ns,
                          dataclasses.replace(image, stamp_ns=stamp)))
        batch.sort(key=lambda m: (m[1], m[0]))
        yield from batch


def _tracker_stream(motion: Motion, cam: int, phase: float, rate: float, t_end: float,
                    scene_time: Callable[[float], float]) -> Iterator[Message]:
    """Camera `cam`'s tracked pose at `rate` Hz from -0.1 s to `t_end`."""
    topic = f"/navigation/endoscope_{cam}/pose"
    for t in np.arange(-0.1 + phase, t_end, 1 / rate):
        T = motion.camera_pose(cam, scene_time(float(t)))
        yield topic, _ns(t) + 1_000_000, PoseRecord(_ns(t), WORLD, "", T[:3, 3],
                                                    matrix_to_quat(T[:3, :3]))


def _robot_stream(motion: Motion, rate: float, t_end: float,
                  scene_time: Callable[[float], float]) -> Iterator[Message]:
    """Tool tip pose and joint states at `rate` Hz from -0.1 s to `t_end`."""
    for t in np.arange(-0.1, t_end, 1 / rate):
        tau = scene_time(float(t))
        p, q = motion.tool_pose(tau)
        yield "/raven/tool_tip", _ns(t) + 500_000, PoseRecord(_ns(t), WORLD, "", p, q)
        yield ("/raven/joint_states", _ns(t) + 500_000,
               JointStateRecord(_ns(t), JOINTS, motion.joint_positions(tau)))


class _Counter:
    """Counts messages and images passing through."""

    def __init__(self, messages: Iterator[Message]) -> None:
        self._it = messages
        self.messages = 0
        self.images = 0

    def __iter__(self) -> Iterator[Message]:
        for m in self._it:
            self.messages += 1
            self.images += isinstance(m[2], ImageRecord)
            yield m


def write_long_log(path: Path, minutes: float = 30.0, target_bytes: float = 2.1 * GB,
                   seed: int = 7, frame_rate: float | None = None, distinct_frames: int = 8,
                   jpeg_quality: int = 92, cameras: int = 6, width: int = 640,
                   height: int = 480) -> LongLogInfo:
    """Write a long ROS 2 log to `path` (atomically) and return what it holds.

    minutes: least log time; target_bytes: least (estimated) file size; the log ends when
    both are reached (0 drops a condition). frame_rate (Hz per camera): None = chosen so that
    both are reached together. distinct_frames: frames actually rendered, replayed in the
    order of `_schedule`.
    Tracker 40 Hz, robot 100 Hz, images width x height (default 640x480), as in
    `surgrecon simulate`.
    """
    start = time.perf_counter()
    if not (minutes > 0 or target_bytes > 0):
        raise ValueError("give minutes > 0 or target_bytes > 0")
    base = SimConfig(cameras=cameras, frames=max(distinct_frames, 2), seed=seed,
                     jpeg_quality=jpeg_quality, width=width, height=height)
    # Render at the final frame rate, so that the replayed frames' scene times match their
    # stamps; that rate depends on the image size, measured first on one rendered frame.
    stream_bytes = (cameras * base.tracker_rate + 2 * base.robot_rate) * _SMALL_BYTES  # per s
    rate = frame_rate
    if rate is None and minutes > 0 and target_bytes > 0:
        probe = _render(dataclasses.replace(base, frames=1))
        frame_bytes = _frame_bytes(probe)
        per_second = target_bytes * _SIZE_MARGIN / (minutes * 60)
        rate = max((per_second - stream_bytes) / frame_bytes, 0.5)
    rendered = _render(dataclasses.replace(base, frame_rate=rate or base.frame_rate))
    rate = rate or base.frame_rate
    frame_bytes = _frame_bytes(rendered)
    # Frames for each condition: bytes(n) ~ n * frame_bytes + n / rate * stream_bytes.
    by_time = math.ceil(minutes * 60 * rate)
    by_size = math.ceil(target_bytes * _SIZE_MARGIN / (frame_bytes + stream_bytes / rate))
    n_frames = max(by_time, by_size, 1)
    t_end = (n_frames - 1) / rate + 0.1
    order = _schedule(len(rendered.images))

    def scene_time(t: float) -> float:
        return _scene_time(t, order, rate)

    motion = rendered.builder.motion
    streams = [_image_stream(rendered, n_frames, rate)]
    streams += [_tracker_stream(motion, c, float(rendered.builder.tracker_phase[c]),
                                base.tracker_rate, t_end, scene_time) for c in range(cameras)]
    streams.append(_robot_stream(motion, base.robot_rate, t_end, scene_time))
    counted = _Counter(heapq.merge(*streams, key=lambda m: (m[1], m[0])))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_log(path, counted, "ros2")
    return LongLogInfo(path, path.stat().st_size, n_frames / rate / 60, n_frames, rate,
                       counted.images, counted.messages, time.perf_counter() - start)


def surgrecon_executable() -> str:
    """The `surgrecon` executable of this interpreter's environment (else the one on PATH)."""
    beside = Path(sys.executable).with_name("surgrecon")
    found = str(beside) if beside.exists() else shutil.which("surgrecon")
    if not found:
        raise FileNotFoundError("no surgrecon executable beside the interpreter or on PATH")
    return found


# Runs the command given in argv and prints its wall time and peak RSS. A tiny interpreter
# (no site, ~10 MB) sits between the caller and the ingest because Linux carries the RSS of
# the process that forks/vforks over into the child's ru_maxrss: measured straight from a
# big caller (this script after rendering holds ~600 MB) it would report the caller's size.
_LAUNCHER = """
import json, resource, subprocess, sys, time
start = time.perf_counter()
rc = subprocess.call(sys.argv[1:], stdout=subprocess.DEVNULL)
seconds = time.perf_counter() - start
usage = resource.getrusage(resource.RUSAGE_CHILDREN)
print(json.dumps({"rc": rc, "seconds": seconds, "maxrss_kib": usage.ru_maxrss}))
"""


def measure_ingest(log_path: Path, run_dir: Path, extra_args: tuple[str, ...] = ()) -> dict:
    """Run `surgrecon ingest LOG -o RUN --quiet` in a child process and measure it.

    Returns {peak_rss_mb, seconds, log_gb, frames, mb_per_s}: the child's peak RSS (its
    ru_maxrss, MiB), wall time (s), log size (GB), frames formed, log MB read per second.
    An existing `run_dir` is replaced. RuntimeError (with the child's stderr) if ingest fails.
    """
    log_path, run_dir = Path(log_path), Path(run_dir)
    if run_dir.exists():
        shutil.rmtree(run_dir)
    cmd = [surgrecon_executable(), "ingest", str(log_path), "-o", str(run_dir), "--quiet",
           *extra_args]
    done = subprocess.run([sys.executable, "-S", "-c", _LAUNCHER, *cmd],
                          capture_output=True, text=True, check=False)
    try:
        result = json.loads(done.stdout.strip().splitlines()[-1])
    except (IndexError, ValueError):
        result = {"rc": done.returncode}
    if done.returncode != 0 or result["rc"] != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({result['rc']}): "
                           f"{done.stderr.strip()[-2000:]}")
    size = log_path.stat().st_size
    run = json.loads((run_dir / "run.json").read_text())
    return {
        "peak_rss_mb": result["maxrss_kib"] / 1024,
        "seconds": result["seconds"],
        "log_gb": size / GB,
        "frames": int(run["ingest"]["frames"]),
        "mb_per_s": size / 1e6 / result["seconds"],
    }


def _table(rows: list[tuple[str, str]]) -> str:
    width = max(len(k) for k, _ in rows)
    return "\n".join(f"{k.ljust(width)}  {v}" for k, v in rows)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("out", type=Path, help="log to write (put it under /tmp)")
    parser.add_argument("--gigabytes", type=float, default=2.1, help="least size (GB, 1e9 B)")
    parser.add_argument("--minutes", type=float, default=30.0, help="least log time")
    parser.add_argument("--frame-rate", type=float, default=None,
                        help="image rate per camera (Hz); default: chosen from size and time")
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--measure", action="store_true",
                        help="then run `surgrecon ingest` on it and report peak RSS and time")
    parser.add_argument("--run-dir", type=Path, default=None,
                        help="run folder for --measure (default: OUT without .mcap + '_run')")
    parser.add_argument("--keep", action="store_true",
                        help="keep the log and run folder after --measure")
    args = parser.parse_args(argv)
    info = write_long_log(args.out, minutes=args.minutes, target_bytes=args.gigabytes * GB,
                          seed=args.seed, frame_rate=args.frame_rate)
    rows = [
        ("log", str(info.path)),
        ("size", f"{info.bytes / GB:.3f} GB"),
        ("log time", f"{info.minutes:.1f} min"),
        ("frames", f"{info.frames} x 6 cameras at {info.frame_rate:.2f} Hz"),
        ("images", str(info.images)),
        ("messages", str(info.messages)),
        ("write time", f"{info.seconds:.0f} s ({info.bytes / 1e6 / info.seconds:.0f} MB/s)"),
    ]
    if args.measure:
        run_dir = args.run_dir or args.out.with_name(args.out.name.removesuffix(".mcap") + "_run")
        try:
            m = measure_ingest(args.out, run_dir)
        finally:
            if not args.keep:
                shutil.rmtree(run_dir, ignore_errors=True)
                args.out.unlink(missing_ok=True)
        rows += [
            ("ingest frames", str(m["frames"])),
            ("ingest peak RSS", f"{m['peak_rss_mb']:.0f} MiB"),
            ("ingest wall time", f"{m['seconds']:.0f} s"),
            ("ingest throughput", f"{m['mb_per_s']:.0f} MB/s"),
        ]
    print(_table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
