"""`surgrecon export RUN --tum DIR`: the run's synchronised poses as TUM trajectories (evo).

One file per camera (DIR/camera_CC.tum: the camera-to-world pose in the optical frame at
each of its images' stamps) and one for the tool (DIR/tool.tum: the tool tip in the world at
each frame's stamp), from RUN/ingest/frames.npz; and the streams as recorded, in the world
frame at their own stamps (DIR/camera_CC_tracker.tum, DIR/tool_robot.tum), from
RUN/ingest/streams.npz. Each line is `t tx ty tz qx qy qz qw`: t in
seconds since the epoch (all nine decimals of the nanosecond stamp), the translation in
metres and the unit quaternion (w >= 0) written with 17 significant digits, so that they
read back to the same doubles. Frames without a pose (NaN) are left out, and a trajectory
without any pose (tool.tum of a run without a robot) is not written: evo refuses a file
without a pose line, so `evo_traj tum DIR/*.tum` would fail on it. `#` lines say what the
file holds. These are the files `evo_traj tum` and `evo_ape tum` read.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...core.geometry.poses import make_pose, matrix_to_quat
from ..run.atomic import write_text
from ..run.ingest_store import load_ingested, load_pose_streams
from ..run.layout import RunLayout


@dataclass(frozen=True)
class Trajectory:
    """One TUM file: what it holds and how many poses (0: not written, nothing to hold)."""

    path: Path
    name: str
    poses: int


def tum_lines(stamps_ns: np.ndarray, poses: np.ndarray) -> list[str]:
    """`t tx ty tz qx qy qz qw` lines of the poses (M, 4, 4) with a finite matrix and a stamp
    >= 0 (M,) ns."""
    stamps_ns = np.asarray(stamps_ns, np.int64)
    poses = np.asarray(poses, float)
    keep = np.isfinite(poses).all((1, 2)) & (stamps_ns >= 0)
    if not keep.any():
        return []
    t = stamps_ns[keep]
    xyz = poses[keep, :3, 3]
    q = matrix_to_quat(poses[keep, :3, :3])
    values = np.column_stack([xyz, q])
    return [f"{s // 1_000_000_000}.{s % 1_000_000_000:09d} "
            + " ".join(format(v, ".17g") for v in row)
            for s, row in zip(t.tolist(), values.tolist(), strict=True)]


def write_tum(path: Path, stamps_ns: np.ndarray, poses: np.ndarray, header: list[str]) -> int:
    """Write one TUM file atomically (header lines become `#` comments); returns its poses.
    Without any pose nothing is written (evo reads no file without a pose line)."""
    lines = tum_lines(stamps_ns, poses)
    if not lines:
        return 0
    comments = [f"# {line}" for line in header] + ["# t tx ty tz qx qy qz qw"]
    write_text(path, "\n".join(comments + lines) + "\n")
    return len(lines)


def export_tum(run_dir: Path, out_dir: Path) -> list[Trajectory]:
    """Write every camera's and the tool's trajectory of an ingested run into `out_dir`."""
    layout = RunLayout(run_dir)
    log = load_ingested(layout.ingest_dir)
    out_dir = Path(out_dir)
    source = f"from {layout.root.resolve()} (ingest/frames.npz), written by surgrecon export"
    written = []
    for c, camera in enumerate(log.cameras):
        path = RunLayout.tum_camera(out_dir, c)
        count = write_tum(path, log.image_stamps_ns[:, c], log.poses[:, c], [
            f"camera {camera!r} (index {c}): camera-to-world pose, optical frame (x right, "
            "y down, z forward), at its images' stamps", source])
        written.append(Trajectory(path, f"camera {camera}", count))
    path = RunLayout.tum_tool(out_dir)
    count = write_tum(path, log.stamps_ns, log.tool_poses, [
        "tool tip in the world (shaft along +z), at the frames' stamps", source])
    written.append(Trajectory(path, "tool", count))
    raw = load_pose_streams(layout.ingest_dir)
    recorded = f"from {layout.root.resolve()} (ingest/streams.npz), written by surgrecon export"
    for c, camera in enumerate(log.cameras):
        stream = raw.get(f"camera_{c:02d}")
        if stream is not None:
            path = RunLayout.tum_tracker(out_dir, c)
            count = write_tum(path, stream.stamps_ns, make_pose(stream.positions, stream.quats),
                              [f"camera {camera!r} (index {c}): its pose stream as recorded "
                               "(tracker stamps), in the world frame", recorded])
            written.append(Trajectory(path, f"camera {camera} (tracker)", count))
    if "tool" in raw and len(raw["tool"].stamps_ns):
        stream = raw["tool"]
        path = RunLayout.tum_robot(out_dir)
        count = write_tum(path, stream.stamps_ns, make_pose(stream.positions, stream.quats),
                          ["tool tip as the robot reported it (robot stamps), in the world",
                           recorded])
        written.append(Trajectory(path, "tool (robot)", count))
    return written
