"""SurgT through `convert` against a hand-built log (issue 23 goals): the template of the real
stereo clip in tests/data/surgt (a) converted from its side-by-side video, (b) converted from
the same frames as left/right PNG folders, (c) written by hand in the simulator's topic layout
with the default config (PoseStamped per camera: the left camera at the origin, the right at
-R^T T from the OpenCV file, T in mm; CameraInfo from `cv2.FileStorage`; the video's frames
as JPEG q95), none of it through the `convert` package.

    .venv/bin/python benchmarks/convert_surgt.py [--frames 3] [--workdir DIR]

Each log is ingested and its template built with the CLI at defaults; printed: template
points, their depth (median, mm), and the median / 95th percentile distance (mm) from each
template's points to the nearest point of the hand-built one's. Goal (issue 23): the
converted templates within 10 % of the hand-built one, the video's within 10 % of the
folder's.
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
from pathlib import Path

import cv2
import numpy as np

HERE = Path(__file__).resolve()
SURGT = HERE.parents[1] / "tests" / "data" / "surgt"


def decoded_frames(count: int) -> list[np.ndarray]:
    import av

    with av.open(str(SURGT / "video.mp4")) as container:
        return [f.to_ndarray(format="bgr24")
                for _, f in zip(range(count), container.decode(video=0), strict=False)]


def hand_built(path: Path, frames: list[np.ndarray]) -> None:
    """The clip as the simulator lays out a log (its default topics), written by hand."""
    from surgrecon_cli.core.geometry.poses import matrix_to_quat, nearest_rotation
    from surgrecon_cli.io.logs.records import CameraInfoRecord, ImageRecord, PoseRecord
    from surgrecon_cli.sim.log_writer import write_log

    fs = cv2.FileStorage(str(SURGT / "calibration.yaml"), cv2.FILE_STORAGE_READ)
    K = [fs.getNode("M1").mat(), fs.getNode("M2").mat()]
    D = [fs.getNode("D1").mat().ravel(), fs.getNode("D2").mat().ravel()]
    R = nearest_rotation(fs.getNode("R").mat().astype(float))
    T = fs.getNode("T").mat().astype(float).ravel() / 1000.0  # mm -> m
    fs.release()
    positions = [np.zeros(3), -R.T @ T]  # x_right = R x_left + T: centre -R^T T, axes R^T
    quats = [np.array([0.0, 0.0, 0.0, 1.0]), matrix_to_quat(R.T)]
    messages = []
    for i, frame in enumerate(frames):
        t = 10**9 + i * 40_000_000
        for c, view in enumerate((frame[:, :1280], frame[:, 1280:])):
            ok, jpeg = cv2.imencode(".jpg", view, [cv2.IMWRITE_JPEG_QUALITY, 95])
            assert ok
            cam = f"{c:02d}"
            messages += [
                (f"/navigation/endoscope_{cam}/pose", t,
                 PoseRecord(t, "world", "", positions[c], quats[c])),
                (f"/endoscope_{cam}/calibration", t,
                 CameraInfoRecord(t, f"endoscope_{cam}", 1280, 1024, K[c], D[c])),
                (f"/endoscope_{cam}/color/compressed", t,
                 ImageRecord(t, f"endoscope_{cam}", "jpeg", jpeg.tobytes())),
            ]
    write_log(path, messages, "ros2")


def template(log: Path, run: Path, config: list[str]) -> np.ndarray:
    """Ingest + build-template at defaults; the template's points (N, 3) m."""
    from surgrecon_cli.cli.main import main
    from surgrecon_cli.io.run.ply import read_ply

    assert main(["ingest", str(log), "-o", str(run), "-q", *config]) == 0
    assert main(["build-template", str(run), "-q", *config]) == 0
    cloud = read_ply(run / "template.ply")
    return np.column_stack([cloud["x"], cloud["y"], cloud["z"]])


def main() -> None:
    from scipy.spatial import cKDTree

    from surgrecon_cli.cli.main import main as cli

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=3)
    parser.add_argument("--workdir", type=Path)
    args = parser.parse_args()
    root = Path(tempfile.mkdtemp(prefix="convert_surgt_", dir=args.workdir))
    try:
        frames = decoded_frames(args.frames)
        for i, frame in enumerate(frames):
            for side, view in (("left", frame[:, :1280]), ("right", frame[:, 1280:])):
                (root / "folder" / side).mkdir(parents=True, exist_ok=True)
                cv2.imwrite(str(root / "folder" / side / f"{i:06d}.png"), view)
        hand_built(root / "hand.mcap", frames)
        no_robot = ["--set", "topics.tool_pose=", "--set", "topics.joint_states="]
        clouds = {"hand-built (default topics)": template(root / "hand.mcap", root / "run_hand",
                                                          no_robot)}
        for name, src in (("convert: video", SURGT / "video.mp4"),
                          ("convert: PNG folders", root / "folder")):
            out = root / f"{name.split()[-1]}.mcap"
            assert cli(["convert", str(src), "-o", str(out), "--calibration",
                        str(SURGT / "calibration.yaml"), "--frames", f"0:{args.frames}",
                        "-q"]) == 0
            clouds[name] = template(out, root / f"run_{out.stem}",
                                    ["--config", str(out.with_suffix(".toml"))])
        reference = cKDTree(clouds["hand-built (default topics)"])
        n_ref = len(clouds["hand-built (default topics)"])
        print(f"{'log':<28} {'points':>7} {'vs hand':>8} {'depth mm':>9} {'NN med mm':>10} "
              f"{'NN p95 mm':>10}")
        for name, pts in clouds.items():
            gaps, _ = reference.query(pts)
            print(f"{name:<28} {len(pts):>7} {100 * (len(pts) / n_ref - 1):>+7.1f}% "
                  f"{1000 * np.median(pts[:, 2]):>9.1f} {1000 * np.median(gaps):>10.3f} "
                  f"{1000 * np.percentile(gaps, 95):>10.3f}")
    finally:
        shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":
    main()
