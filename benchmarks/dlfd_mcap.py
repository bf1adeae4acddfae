"""A few frames of a real 6-camera dVRK recording (imanlab/d-lfd, MIT) as an MCAP log + config.

    python benchmarks/dlfd_mcap.py --repo /path/to/d-lfd.git --trial 1 --frames 3 -o out/

d-lfd trial N: six 310x244 videos (three stereo pairs p1..p3, left/right, 25 fps), the
robot data `Data/N/Data.mat` (scipy-readable MATLAB v5: a 1x160 cell array, per sample the
4x4 poses of arm 1 and arm 2 in their own base frames, metres), the stereo calibrations
`Data/stereoParamsP{1,2,3}.mat` (MATLAB `stereoParameters` objects: NOT readable by
scipy.io.loadmat, which returns an opaque object; read here with the `mat-io` package,
`pip install mat-io`) and the hand-eye results `Data/Eye2HandResult_R{r}_P{k}.mat` (4x4, mm;
scipy-readable).

Conventions found by projecting the arms into the images (see the PNG this writes):
- `Eye2HandResult_R{r}_P{k}` is the pose of pair k's left camera in robot r's base frame
  (its inverse puts the arm 170-235 mm in front of the camera; the other way round puts it
  behind or far outside the image);
- MATLAB's stereo extrinsics map row vectors, x_right = x_left R + t (mm), so in column form
  X_right = R^T X_left + t;
- the calibration was made at 640x480 px; the videos are 310x244, taken as the same view
  scaled (K scaled by 310/640 and 244/480);
- the world is robot 1's base frame; robot 2's base is placed through pair 2's hand-eye
  results (T_world_base2 = Y_r1_p2 inv(Y_r2_p2));
- the 160 robot samples are taken as spread evenly over the video's duration (the data set
  does not give their times); frame f uses the sample nearest its time.

Then `surgrecon run OUT/dlfd_N.mcap -o RUN --config OUT/dlfd_N.toml` and
`python benchmarks/dlfd_mcap.py ... -o OUT --figure RUN` draws the template over one camera
image with both arms' masks.

Measured on trial 1 (3 frames, defaults): each stereo pair links (27, 25 and 18 verified
matches of 270-300 features per image; the former fixed minimum of 40 refused them all), the
pairs do not link to each other (0-4 verified matches). With arm 2's shaft along z (the
first try) pairs 2 and 3 were reported as disagreeing (their pose-free matches 33.6 px off
the epipolar lines of their hand-eye poses); with the -y shaft below, which masks more, no
group pair is reported. Arm 2's kinematic point lands on the forceps' wrist in p2l (video
frames 0, 124 and 248 with samples 0, 80, 159), but its frame's z axis points ~70 degrees
off the shaft (-y, used in the config, is the nearest axis and still 25-40 degrees off); arm
1's kinematic point projects ~100 px (of 310) right of its jaws in frame 0 and near them
only at the end. So both models miss parts of their instruments and template points remain
on both (jaw tips of arm 2, shaft of arm 1: see the PNG), although none is within 9.7 mm
(arm 1) and 11.8 mm (arm 2) of its arm's model. Unresolved: the frame conventions of the
published arm matrices, the timing of the robot samples (logged from when a red cross
appears, which this script does not detect), the videos' crop.

Writes OUT/dlfd_N.mcap (ROS 2: CompressedImage JPEG, CameraInfo, PoseStamped per camera on
/{camera}/pose, arms on /PSM1/measured_cp and /PSM2/measured_cp) and OUT/dlfd_N.toml.
"""

from __future__ import annotations

import argparse
import subprocess
import tempfile
from pathlib import Path

import av
import cv2
import numpy as np
import scipy.io
from scipy.spatial.transform import Rotation

from surgrecon_cli.config import load_config
from surgrecon_cli.core.cameras import project
from surgrecon_cli.core.geometry import point_to_segment_distance
from surgrecon_cli.core.tool import tool_capsules, tool_image_mask
from surgrecon_cli.io.artefacts import read_template
from surgrecon_cli.io.ingest_store import load_ingested
from surgrecon_cli.io.records import CameraInfoRecord, ImageRecord, PoseRecord
from surgrecon_cli.io.run_layout import RunLayout
from surgrecon_cli.sim.log_writer import write_log

PAIRS = (1, 2, 3)
SIDES = ("left", "right")
CALIBRATED_SIZE = (640, 480)
T0 = 1_600_000_000_000_000_000
CONFIG = """[topics]
image = "/{{camera}}/image/compressed"
camera_info = "/{{camera}}/camera_info"
camera_pose = "/{{camera}}/pose"
camera_frame = "{{camera}}"
tool_pose = "/PSM1/measured_cp"
joint_states = ""

[tool]
# dVRK 8 mm instruments; the kinematic point sits at the wrist, the jaws beyond it
shaft_radius_m = 0.004
jaw_offset_m = 0.0
jaw_length_m = {jaw_length}
jaw_width_m = {jaw_width}

[[tools]]
pose = "/PSM2/measured_cp"
# arm 2's matrices: z does not follow the shaft in the images; -y is the nearest axis
shaft_axis = "-y"
shaft_radius_m = 0.004
jaw_offset_m = 0.0
jaw_length_m = {jaw_length}
jaw_width_m = {jaw_width}
"""


def _show(repo: Path, path: str, dest: Path) -> Path:
    out = dest / path.replace("/", "_")
    out.write_bytes(subprocess.run(["git", "--git-dir", str(repo), "show", f"HEAD:{path}"],
                                   check=True, capture_output=True).stdout)
    return out


def _props(obj) -> dict:
    """The properties of a MATLAB object as read by mat-io."""
    p = obj.properties
    any_ = p.get("any")
    if any_ is not None and getattr(any_, "dtype", None) is not None and any_.dtype.names:
        return {n: any_[0, 0][n] for n in any_.dtype.names}
    return dict(p)


def stereo_calibration(path: Path) -> dict:
    """K (3, 3), D (5,) plumb_bob per side at 640x480, and the right camera's pose in the
    left's frame (4, 4, metres)."""
    import matio  # mat-io: reads MATLAB objects (stereoParameters), which scipy cannot

    sp = _props(matio.load_from_mat(str(path))["stereoParams"])
    out = {}
    for side, name in zip(SIDES, ("CameraParameters1", "CameraParameters2"), strict=True):
        cp = _props(sp[name])
        radial = np.asarray(cp["RadialDistortion"], float).ravel()
        tangential = np.asarray(cp["TangentialDistortion"], float).ravel()
        out[f"K_{side}"] = np.asarray(cp["IntrinsicMatrix"], float).T
        out[f"D_{side}"] = np.array([radial[0], radial[1], tangential[0], tangential[1],
                                     radial[2] if len(radial) > 2 else 0.0])
    left_to_right = np.eye(4)
    left_to_right[:3, :3] = np.asarray(sp["RotationOfCamera2"], float).T
    left_to_right[:3, 3] = np.asarray(sp["TranslationOfCamera2"], float).ravel() / 1000
    out["right_in_left"] = np.linalg.inv(left_to_right)
    return out


def _mm_to_m(T: np.ndarray) -> np.ndarray:
    T = np.array(T, float)
    T[:3, 3] /= 1000
    return T


def _pose(t: int, T: np.ndarray) -> PoseRecord:
    return PoseRecord(t, "world", "", T[:3, 3].copy(), Rotation.from_matrix(T[:3, :3]).as_quat())


def build(repo: Path, trial: int, frames: int, out: Path) -> tuple[Path, Path]:
    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        data = scipy.io.loadmat(_show(repo, f"Data/{trial}/Data.mat", work))["Data"]
        arm1 = np.stack([data[0, j][0, 2] for j in range(data.shape[1])])
        arm2 = np.stack([data[0, j][0, 3] for j in range(data.shape[1])])
        hand_eye = {(r, k): _mm_to_m(scipy.io.loadmat(_show(
            repo, f"Data/Eye2HandResult_R{r}_P{k}.mat", work))["Y_"]) for r in (1, 2)
            for k in PAIRS}
        calib = {k: stereo_calibration(_show(repo, f"Data/stereoParamsP{k}.mat", work))
                 for k in PAIRS}
        videos = {(k, s): _show(repo, f"Data/{trial}/p{k}_{s}.mp4", work)
                  for k in PAIRS for s in SIDES}
        base2 = hand_eye[(1, 2)] @ np.linalg.inv(hand_eye[(2, 2)])
        messages: list = []
        duration_s = None
        for (k, side), video in videos.items():
            cam = f"p{k}{side[0]}"  # p1l, p1r, ...: one name token per camera
            with av.open(str(video)) as container:
                stream = container.streams.video[0]
                duration_s = float(stream.duration * stream.time_base)
                for f, frame in enumerate(container.decode(video=0)):
                    if f >= frames:
                        break
                    rgb = frame.to_ndarray(format="rgb24")
                    h, w = rgb.shape[:2]
                    t = T0 + round(f * 1e9 / 25)
                    if f == 0:
                        K = calib[k][f"K_{side}"].copy()
                        K[0] *= w / CALIBRATED_SIZE[0]
                        K[1] *= h / CALIBRATED_SIZE[1]
                        messages.append((f"/{cam}/camera_info", t, CameraInfoRecord(
                            t, cam, w, h, K, calib[k][f"D_{side}"])))
                    _, jpeg = cv2.imencode(".jpg", rgb[:, :, ::-1],
                                           [cv2.IMWRITE_JPEG_QUALITY, 95])
                    messages.append((f"/{cam}/image/compressed", t + 1,
                                     ImageRecord(t, cam, "jpeg", jpeg.tobytes())))
                    T = hand_eye[(1, k)]
                    if side == "right":
                        T = T @ calib[k]["right_in_left"]
                    messages.append((f"/{cam}/pose", t + 2, _pose(t, T)))
        n = len(arm1)
        for f in range(frames):
            t = T0 + round(f * 1e9 / 25)
            j = min(round(f / 25 / duration_s * n), n - 1)
            messages.append(("/PSM1/measured_cp", t + 3, _pose(t, arm1[j])))
            messages.append(("/PSM2/measured_cp", t + 3, _pose(t, base2 @ arm2[j])))
    messages.sort(key=lambda m: m[1])
    log = out / f"dlfd_{trial}.mcap"
    write_log(log, messages, "ros2")
    config = out / f"dlfd_{trial}.toml"
    config.write_text(CONFIG.format(jaw_length=0.015, jaw_width=0.008))
    return log, config


def figure(run: Path, config_path: Path, camera: str, png: Path) -> dict[str, float]:
    """The template (frame 0) over `camera`'s image with every tool's mask (arm 1 red, arm 2
    green); returns per tool the smallest distance (mm) of a template point to its model's
    surface (axis distance - radius; negative = inside)."""
    log = load_ingested(RunLayout(run).ingest_dir)
    config = load_config(config_path)
    c = log.cameras.index(camera)
    image = log.load_image(0, c)[:, :, ::-1].copy()
    tools, cfgs = log.all_tool_poses(0), config.tool_configs()
    for pose, cfg, colour in zip(tools, cfgs, ((0, 0, 255), (0, 255, 0)), strict=False):
        mask = tool_image_mask(log.models[c], log.poses[0, c], pose, cfg, step=1)
        image[mask] = (0.5 * image[mask] + 0.5 * np.array(colour)).astype(np.uint8)
    points = read_template(RunLayout(run)).points
    px, _ = project(points, log.poses[0, c], log.models[c])
    for u, v in px[np.isfinite(px).all(1)]:
        cv2.circle(image, (round(u), round(v)), 2, (255, 255, 0), -1)
    big = cv2.resize(image, None, fx=3, fy=3, interpolation=cv2.INTER_NEAREST)
    cv2.imwrite(str(png), big)
    gaps = {}
    for k, (pose, cfg) in enumerate(zip(tools, cfgs, strict=False)):
        gaps[f"tool {k}"] = min((float((point_to_segment_distance(points, a, b) - r).min()) * 1e3
                                 for a, b, r in tool_capsules(pose, cfg)), default=np.inf)
    return gaps


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repo", type=Path, required=True, help="d-lfd git directory")
    parser.add_argument("--trial", type=int, default=1)
    parser.add_argument("--frames", type=int, default=3)
    parser.add_argument("-o", "--out", type=Path, required=True)
    parser.add_argument("--figure", metavar="RUN", type=Path,
                        help="instead: draw the PNG of run RUN (made from this log and config)")
    parser.add_argument("--camera", default="p2l", help="camera of the figure")
    args = parser.parse_args()
    config = args.out / f"dlfd_{args.trial}.toml"
    if args.figure:
        png = args.out / f"dlfd_{args.trial}_template_{args.camera}.png"
        gaps = figure(args.figure, config, args.camera, png)
        print(f"wrote {png}; closest template point to each tool's model (mm): {gaps}")
        return
    log, config = build(args.repo, args.trial, args.frames, args.out)
    print(f"wrote {log} and {config}")


if __name__ == "__main__":
    main()
