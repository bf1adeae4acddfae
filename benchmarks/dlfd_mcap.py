"""A few frames of a real 6-camera dVRK recording (imanlab/d-lfd, MIT) as an MCAP log + config.

    python benchmarks/dlfd_mcap.py --repo /path/to/d-lfd.git --trial 1 --frames 3 -o out/
    surgrecon run out/dlfd_1.mcap -o RUN --config out/dlfd_1.toml
    python benchmarks/dlfd_check.py RUN --config out/dlfd_1.toml    # 1 mm check + PNG

d-lfd trial N: six 310x244 videos (three stereo pairs p1..p3, left/right, 25 fps), the robot
data `Data/N/Data.mat` (per sample the 4x4 poses of arm 1 and arm 2 in their own base frames,
metres), the stereo calibrations `Data/stereoParamsP{1,2,3}.mat` (MATLAB objects, read with
`mat-io`) and the hand-eye results `Data/Eye2HandResult_R{r}_P{k}.mat` (4x4, mm).

Conventions (`benchmarks/dlfd_conventions.py` scores each against hand-marked instruments;
details and figures in docs/dlfd.md):
- `Eye2HandResult_R{r}_P{k}` is pair k's left camera in robot r's base frame (camera to
  base); each camera is placed by the mean of its pair's two results (robot 1's, and robot
  2's through robot 2's base, itself the mean over the pairs of Y_r1 inv(Y_r2));
- MATLAB's stereo extrinsics map row vectors: in column form X_right = R^T X_left + t;
- the videos are the 640x480 calibration images scaled to 310x244;
- the robot samples run evenly from d-lfd's `start_imaging` (preprocessing/vid2Imgcut.py;
  3.7 s in trial 1, when the red cross appears) to the end; earlier frames get sample 0;
- the arm matrices are a dVRK PSM's jaw frame in its remote-centre-of-motion frame: the
  shaft runs from the kinematic point through the base origin, while the frame's axes are up
  to 80 degrees off it when the wrist bends. The log carries a shaft frame per arm (z
  towards the base origin), so the default `shaft_axis = "+z"` holds;
- arm 1 is the blunt instrument from the right of the p2/p3 images, arm 2 the needle driver
  from the top left; both kinematic points sit 20-50 mm short of the jaw tips (jaw part).

Writes OUT/dlfd_N.mcap (ROS 2: CompressedImage JPEG, CameraInfo, `/tf_static` world ->
PSM1_base -> each camera and world -> PSM2_base, the arms' shaft frames as PoseStamped in
their base frames on /PSM{1,2}/shaft_pose) and OUT/dlfd_N.toml.
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import tempfile
from pathlib import Path

import av
import cv2
import numpy as np
import scipy.io

from surgrecon_cli.config import ToolConfig
from surgrecon_cli.core.geometry.cameras import CameraModel
from surgrecon_cli.core.geometry.poses import matrix_to_quat, nearest_rotation
from surgrecon_cli.core.geometry.tool_fit import ShaftFit, fit_tool_offset
from surgrecon_cli.io.logs.records import CameraInfoRecord, ImageRecord, PoseRecord
from surgrecon_cli.sim.log_writer import write_log

PAIRS = (1, 2, 3)
SIDES = ("left", "right")
CAMERAS = tuple(f"p{k}{s[0]}" for k in PAIRS for s in SIDES)  # p1l, p1r, ...
CALIBRATED_SIZE, VIDEO_SIZE = (640, 480), (310, 244)
FPS = 25
T0 = 1_600_000_000_000_000_000
CONFIG = """[topics]
image = "/{{camera}}/image/compressed"
camera_info = "/{{camera}}/camera_info"
camera_pose = "/tf_static"
camera_frame = "{{camera}}"
world_frame = "world"
tool_pose = "/PSM1/shaft_pose"
joint_states = ""

[tool]
# the shaft from the kinematic point up to the RCM, the jaws beyond it; each camera sees the
# arm moved by its pair's camera_offsets (the shaft fitted to the images: the pairs' hand-eye
# results disagree by 12-26 mm); radius = the 4 mm instrument + 4 mm, about the worst lateral
# error left after that fit (10 px, 4.7 mm), plus the 6 px margin; margin_m at its default:
# the masks, not the 3D drop, keep the template off the instruments
shaft_radius_m = {radius_m}
jaw_offset_m = 0.0
jaw_length_m = {jaw_length_m}
jaw_width_m = {jaw_width_m}
mask_margin_px = {mask_margin_px}
margin_m = {margin_m}
camera_offsets = {offsets_1}

[[tools]]
pose = "/PSM2/shaft_pose"
shaft_radius_m = {radius_m}
jaw_offset_m = 0.0
jaw_length_m = {jaw_length_m}
jaw_width_m = {jaw_width_m}
mask_margin_px = {mask_margin_px}
margin_m = {margin_m}
camera_offsets = {offsets_2}
"""
INSTRUMENT_RADIUS_M = 0.004  # dVRK's 8 mm instruments
MIN_CONTRAST = 40.0  # grey levels summed over a pair's two images: the shaft was found
GEOMETRY = {"radius_m": 0.008, "jaw_length_m": 0.05, "jaw_width_m": 0.02, "mask_margin_px": 6,
            "margin_m": 0.0015}


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
    """K (3, 3) 0-based, D (5,) plumb_bob per side at 640x480, and the right camera's pose in
    the left's frame (4, 4, metres)."""
    import matio  # mat-io: reads MATLAB objects (stereoParameters), which scipy cannot

    sp = _props(matio.load_from_mat(str(path))["stereoParams"])
    out = {}
    for side, name in zip(SIDES, ("CameraParameters1", "CameraParameters2"), strict=True):
        cp = _props(sp[name])
        radial = np.asarray(cp["RadialDistortion"], float).ravel()
        tangential = np.asarray(cp["TangentialDistortion"], float).ravel()
        K = np.asarray(cp["IntrinsicMatrix"], float).T.copy()
        K[:2, 2] -= 1.0  # MATLAB's first pixel centre is (1, 1)
        out[f"K_{side}"] = K
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


def start_seconds(repo: Path, trial: int) -> float:
    """When trial `trial`'s robot samples start in its videos: d-lfd's `start_imaging`."""
    text = subprocess.run(["git", "--git-dir", str(repo), "show",
                           "HEAD:preprocessing/vid2Imgcut.py"], check=True,
                          capture_output=True, text=True).stdout
    table = re.search(r"start_imaging\s*=\s*np\.array\(\[([^\]]*)\]", text)
    if table is None:
        raise SystemExit("preprocessing/vid2Imgcut.py has no start_imaging table")
    return float(table.group(1).replace("\\", "").split(",")[trial - 1])


def load(repo: Path, trial: int, work: Path) -> dict:
    """Everything of trial `trial`: arms (2, n, 4, 4) m in their bases, hand_eye {(r, k):
    camera-to-base (4, 4) m}, calib {k: stereo_calibration}, videos {(k, side): path},
    start_s and duration_s of the robot samples in the videos."""
    data = scipy.io.loadmat(_show(repo, f"Data/{trial}/Data.mat", work))["Data"]
    arms = np.stack([np.stack([data[0, j][0, c] for j in range(data.shape[1])]) for c in (2, 3)])
    hand_eye = {(r, k): _mm_to_m(scipy.io.loadmat(_show(
        repo, f"Data/Eye2HandResult_R{r}_P{k}.mat", work))["Y_"]) for r in (1, 2) for k in PAIRS}
    calib = {k: stereo_calibration(_show(repo, f"Data/stereoParamsP{k}.mat", work)) for k in PAIRS}
    videos = {(k, s): _show(repo, f"Data/{trial}/p{k}_{s}.mp4", work) for k in PAIRS for s in SIDES}
    with av.open(str(videos[(1, "left")])) as container:
        stream = container.streams.video[0]
        duration_s = float(stream.duration * stream.time_base)
    return {"arms": arms, "hand_eye": hand_eye, "calib": calib, "videos": videos,
            "start_s": start_seconds(repo, trial), "duration_s": duration_s}


def load_shipped(folder: Path) -> dict:
    """`load`'s dict from the pieces shipped in tests/data/dlfd: calibration.json (cameras,
    mm), robot.json (arms, hand-eye results, sample timing) and the frames' JPEGs (`images`
    instead of `videos`)."""
    cams = json.loads((folder / "calibration.json").read_text(encoding="utf-8"))["cameras"]
    robot = json.loads((folder / "robot.json").read_text(encoding="utf-8"))
    calib = {}
    for k in PAIRS:
        left, right = (_mm_to_m(np.array(cams[f"p{k}_{s}"]["pose"])) for s in SIDES)
        calib[k] = {"right_in_left": np.linalg.inv(left) @ right}
        for s in SIDES:
            calib[k][f"K_{s}"] = np.array(cams[f"p{k}_{s}"]["K"], float)
            calib[k][f"D_{s}"] = np.array(cams[f"p{k}_{s}"]["D"], float)
    hand_eye = {(r, k): _mm_to_m(np.array(robot["hand_eye_mm"][f"R{r}_P{k}"])) for r in (1, 2)
                for k in PAIRS}
    return {"arms": np.array(robot["arms"], float), "hand_eye": hand_eye, "calib": calib,
            "images": folder, "start_s": robot["start_s"], "duration_s": robot["duration_s"]}


def sample_at(t_s: float, d: dict) -> int:
    """The robot sample nearest video time t_s (s); before the first, the first."""
    n = d["arms"].shape[1]
    s = (t_s - d["start_s"]) / (d["duration_s"] - d["start_s"]) * n
    return int(np.clip(round(s), 0, n - 1))


def _mean_pose(Ts: list[np.ndarray]) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = nearest_rotation(np.mean([t[:3, :3] for t in Ts], axis=0))
    T[:3, 3] = np.mean([t[:3, 3] for t in Ts], axis=0)
    return T


def base2_in_base1(hand_eye: dict) -> np.ndarray:
    """Robot 2's base in robot 1's (4, 4): the mean over the pairs of Y_r1 inv(Y_r2)."""
    return _mean_pose([hand_eye[(1, k)] @ np.linalg.inv(hand_eye[(2, k)]) for k in PAIRS])


def shaft_pose(tip: np.ndarray) -> np.ndarray:
    """A dVRK jaw pose (4, 4) in its arm's RCM frame -> the shaft frame at the same point: z
    towards the RCM (the base origin), x the jaw frame's x made orthogonal to it."""
    z = -tip[:3, 3] / np.linalg.norm(tip[:3, 3])
    x = tip[:3, 0] - (tip[:3, 0] @ z) * z
    if np.linalg.norm(x) < 1e-6:  # jaw x along the shaft: take its y
        x = tip[:3, 1] - (tip[:3, 1] @ z) * z
    x /= np.linalg.norm(x)
    out = np.eye(4)
    out[:3, :3] = np.column_stack([x, np.cross(z, x), z])
    out[:3, 3] = tip[:3, 3]
    return out


def camera_in_base1(d: dict, cam: str, fuse: bool = True) -> np.ndarray:
    """Camera `cam` (p1l ...) in robot 1's base (4, 4) m: its pair's left camera by the mean
    of the pair's two hand-eye results (robot 1's, and robot 2's through `base2_in_base1`;
    `fuse=False`: robot 1's only), the right one through the stereo extrinsics."""
    k = int(cam[1])
    he = d["hand_eye"]
    T = _mean_pose([he[(1, k)], base2_in_base1(he) @ he[(2, k)]]) if fuse else he[(1, k)]
    return T @ d["calib"][k]["right_in_left"] if cam.endswith("r") else T


def arms_in_world(d: dict, frame: int) -> np.ndarray:
    """Both arms' shaft frames (2, 4, 4) in the world (robot 1's base) at video frame `frame`."""
    world = {1: np.eye(4), 2: base2_in_base1(d["hand_eye"])}
    return np.stack([world[r] @ shaft_pose(d["arms"][r - 1, sample_at(frame / FPS, d)])
                     for r in (1, 2)])


def arm_corrections(d: dict, frame: int, pairs: tuple[int, ...] = PAIRS,
                    radius_m: float = INSTRUMENT_RADIUS_M) -> dict:
    """{(pair k, arm r): ToolOffsetFit}: per pair and arm, the translation (world, m) that lays
    the arm's shaft on the dark instrument in the pair's two images at video frame `frame`
    (`fit_tool_offset`, translation only): that pair's and arm's hand-eye error as the images
    measure it. One move per pair for both arms does not fit (docs/dlfd.md)."""
    tools = arms_in_world(d, frame)
    out = {}
    for k in pairs:
        cams = [f"p{k}{s[0]}" for s in SIDES]
        grays = [cv2.imdecode(np.frombuffer(next(_jpegs(d, k, s, frame, 1))[1], np.uint8),
                              cv2.IMREAD_GRAYSCALE) for s in SIDES]
        models = [camera_model(d, c) for c in cams]
        poses = np.stack([camera_in_base1(d, c) for c in cams])
        for r in (1, 2):
            out[(k, r)] = fit_tool_offset(grays, models, poses, tools[r - 1:r], [ToolConfig()],
                                          ShaftFit(radius_m=radius_m, max_turn_deg=0.0))
    return out


def _tf(t: int, parent: str, child: str, T: np.ndarray) -> PoseRecord:
    return PoseRecord(t, parent, child, T[:3, 3].copy(), matrix_to_quat(T[:3, :3]))


def camera_model(d: dict, cam: str) -> CameraModel:
    """Camera `cam` (p1l ...) for the 310x244 videos: its 640x480 calibration scaled (pixel
    centres map as u' = (u + 0.5) s - 0.5)."""
    k, side = int(cam[1]), "left" if cam.endswith("l") else "right"
    K = d["calib"][k][f"K_{side}"].copy()
    for i, (size, new) in enumerate(zip(CALIBRATED_SIZE, VIDEO_SIZE, strict=True)):
        K[i, :2] *= new / size
        K[i, 2] = (K[i, 2] + 0.5) * new / size - 0.5
    return CameraModel(K=K, dist=d["calib"][k][f"D_{side}"], width=VIDEO_SIZE[0],
                       height=VIDEO_SIZE[1])


def _jpegs(d: dict, k: int, side: str, first: int, frames: int):
    """(frame, JPEG bytes) of camera p{k}_{side}: the shipped JPEGs as they are (`images`),
    else the video's frames encoded at quality 95."""
    if "images" in d:
        for f in range(first, first + frames):
            yield f, (d["images"] / f"p{k}_{side}" / f"{f:06d}.jpg").read_bytes()
        return
    with av.open(str(d["videos"][(k, side)])) as container:
        for f, frame in enumerate(container.decode(video=0)):
            if f >= first + frames:
                break
            if f >= first:
                _, jpeg = cv2.imencode(".jpg", frame.to_ndarray(format="bgr24"),
                                       [cv2.IMWRITE_JPEG_QUALITY, 95])
                yield f, jpeg.tobytes()


def config_text(fits: dict, geometry: dict | None = None) -> str:
    """The log's config: tool geometry (`GEOMETRY`) and, per arm, each pair's cameras'
    `camera_offsets` from `arm_corrections` fits (those that found the shaft: contrast at
    least `MIN_CONTRAST`)."""
    offsets = {r: [f"{cam} {' '.join(f'{v:.4f}' for v in fit.move[:3, 3])}"
                   for (k, arm), fit in sorted(fits.items()) if arm == r
                   and fit.contrast >= MIN_CONTRAST for cam in (f"p{k}l", f"p{k}r")]
               for r in (1, 2)}
    return CONFIG.format(**(geometry or GEOMETRY),
                         **{f"offsets_{r}": json.dumps(v) for r, v in offsets.items()})


def build(d: dict, name: str, frames: int, first: int, out: Path, fit_shafts: bool = True
          ) -> tuple[Path, Path]:
    """Write OUT/NAME.mcap (video frames first .. first + frames - 1) and OUT/NAME.toml (with
    the arms' per-camera offsets fitted to frame `first`'s images unless not `fit_shafts`)."""
    out.mkdir(parents=True, exist_ok=True)
    messages: list = [("/tf_static", T0, _tf(T0, "world", "PSM1_base", np.eye(4))),
                      ("/tf_static", T0, _tf(T0, "world", "PSM2_base",
                                             base2_in_base1(d["hand_eye"])))]
    for k, side in ((k, s) for k in PAIRS for s in SIDES):
        cam = f"p{k}{side[0]}"
        model = camera_model(d, cam)
        messages.append(("/tf_static", T0, _tf(T0, "PSM1_base", cam, camera_in_base1(d, cam))))
        for f, jpeg in _jpegs(d, k, side, first, frames):
            t = T0 + round(f * 1e9 / FPS)
            messages.append((f"/{cam}/camera_info", t, CameraInfoRecord(
                t, cam, model.width, model.height, model.K, model.dist)))
            messages.append((f"/{cam}/image/compressed", t + 1, ImageRecord(t, cam, "jpeg", jpeg)))
    for f in range(first, first + frames):
        t = T0 + round(f * 1e9 / FPS)
        j = sample_at(f / FPS, d)
        for r in (1, 2):
            messages.append((f"/PSM{r}/shaft_pose", t + 3,
                             _tf(t, f"PSM{r}_base", "", shaft_pose(d["arms"][r - 1, j]))))
    messages.sort(key=lambda m: m[1])
    log = out / f"{name}.mcap"
    write_log(log, messages, "ros2")
    config = out / f"{name}.toml"
    config.write_text(config_text(arm_corrections(d, first) if fit_shafts else {}))
    return log, config


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repo", type=Path, required=True, help="d-lfd git directory")
    parser.add_argument("--trial", type=int, default=1)
    parser.add_argument("--frames", type=int, default=3)
    parser.add_argument("--first", type=int, default=0, help="first video frame")
    parser.add_argument("-o", "--out", type=Path, required=True)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        d = load(args.repo, args.trial, Path(tmp))
        log, config = build(d, f"dlfd_{args.trial}", args.frames, args.first, args.out)
    print(f"wrote {log} and {config}")


if __name__ == "__main__":
    main()
