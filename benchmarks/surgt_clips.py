"""Harder clips from the real SurgT sample (tests/data/surgt): the camera's motion per frame
grows with a frame step, shrinks in pixels with a downscale, and JPEG re-encoding adds real
compression noise. Used by benchmarks/real.py (`--surgt SPEC ...`).

A SPEC is comma-separated `key=value` (any order, all optional):
    step=2      every 2nd source frame (0, 2, 4, ...)
    scale=0.5   each eye resized (1280x1024 -> 640x512), intrinsics scaled with it
    reverse=1   frames in reverse order
    jpeg=70     frames re-encoded as JPEG at this quality (else lossless PNG)
    frames=10   source frames read from the video (default: all 10)
    length=16   frames in the clip: the selection played forward, back, forward, ...
                (ping-pong, without repeating the turning frame) until this many
    pitch=2     the rig also turns about its baseline (the cameras' x axis) by this many
                degrees per frame, out and back (0, 1, 2, 3, 2, 1, 0, -1, ... steps): each
                eye warped by K R K⁻¹ (a pure rotation about the baseline keeps the stereo
                geometry exact; lens distortion, ~0.1 px here, is ignored), so a rigid scene
                seen by an endoscope turning 1-3.5° a frame
    breathe=2   the first selected frame's tissue breathes with this amplitude (mm), its
                motion known (benchmarks/surgt_breathing.py); writes clip.gt.npz
    period=39   frames of one breath (default: the clip's length)
    ripple=0.1  bumps of this share of the amplitude over the whole tissue as it breathes
                (surgt_breathing.py): deforming nearly everywhere at the breath's peak
    gain=0.2    both eyes' brightness scaled by 1 + gain · (0, 1/3, 2/3, 1, 2/3, ...) of the
                pitch's triangle wave: an endoscope's auto-exposure following its light
    shade=0.3   a brightness ramp across each image whose slope follows the same wave
                (1 ± shade/2 at the left and right edges at its peaks): the scope's light
                moving with it, lighting the tissue from another side
e.g. `step=3,scale=0.5` -> frames 0, 3, 6, 9 at 640x512. The clip is written as left/right
image folders with its calibration (intrinsics scaled) and converted with `surgrecon
convert` (the rig is fixed in the world, so the scene moves rigidly in the rig frame).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from surgt_breathing import breathing_frames, spec_labels

SURGT = Path(__file__).resolve().parents[1] / "tests" / "data" / "surgt"
CLIP_FPS = 5  # frames a second the clips are converted at


def parse_spec(spec: str) -> dict[str, float]:
    out = {"step": 1.0, "scale": 1.0, "reverse": 0.0, "jpeg": 0.0, "frames": 10.0,
           "length": 0.0, "pitch": 0.0, "breathe": 0.0, "period": 0.0, "ripple": 0.0,
           "gain": 0.0, "shade": 0.0}
    for item in filter(None, spec.split(",")):
        key, _, value = item.partition("=")
        if key not in out:
            raise ValueError(f"unknown clip key {key!r} in {spec!r}")
        out[key] = float(value)
    return out


def clip_name(spec: str) -> str:
    return "surgt" + ("-" + spec.replace(",", "-").replace("=", "") if spec else "")


def decoded_frames(count: int) -> list[np.ndarray]:
    """The first `count` side-by-side frames of the sample video (BGR, 1024 x 2560)."""
    import av

    with av.open(str(SURGT / "video.mp4")) as container:
        return [f.to_ndarray(format="bgr24")
                for _, f in zip(range(count), container.decode(video=0), strict=False)]


def calibration() -> dict[str, np.ndarray]:
    """The sample's OpenCV stereo calibration (M1 D1 M2 D2 R T; T in mm)."""
    fs = cv2.FileStorage(str(SURGT / "calibration.yaml"), cv2.FILE_STORAGE_READ)
    out = {k: fs.getNode(k).mat().astype(np.float64) for k in ("M1", "D1", "M2", "D2", "R", "T")}
    fs.release()
    return out


def scaled_calibration(path: Path, scale: float) -> Path:
    """The sample's calibration for its images resized by `scale`, written to path (the
    file states no image size, so `convert --scale-calibration` cannot scale it): pixel
    centres map as u' = (u + 0.5) s - 0.5."""
    dst = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for key, value in calibration().items():
        if key in ("M1", "M2"):
            value[:2, :] *= scale
            value[:2, 2] += 0.5 * scale - 0.5
        dst.write(key, value)
    dst.release()
    return path


def breathing_clip(frame: np.ndarray, opts: dict[str, float], out_dir: Path
                   ) -> list[np.ndarray]:
    """`length` side-by-side frames of `frame`'s tissue breathing; its truth written to
    out_dir/clip.gt.npz (stamps at CLIP_FPS, as the clip is converted)."""
    length = int(opts["length"] or 39)
    pairs, truth = breathing_frames(frame[:, :1280], frame[:, 1280:], calibration(),
                                    opts["breathe"], length, opts["period"] or length,
                                    opts["ripple"])
    truth["stamps_ns"] = np.round(np.arange(length) * 1e9 / CLIP_FPS).astype(np.int64)
    if opts["pitch"]:  # the turning rig sees the tissue turn the other way about its eye
        rots = np.stack([pitch_rotation(opts["pitch"], i) for i in range(length)])
        truth["vertices"] = np.einsum("tij,tvj->tvi", rots, truth["vertices"])
        truth["labels"] = spec_labels(truth["vertices"])
    np.savez_compressed(out_dir / "clip.gt.npz", **truth)
    return [np.hstack(pair) for pair in pairs]


PITCH_WAVE = np.array([0, 1, 2, 3, 2, 1, 0, -1, -2, -3, -2, -1])  # `pitch` steps by frame


def pitch_rotation(pitch_deg: float, frame: int) -> np.ndarray:
    """(3, 3) the rotation about the left eye's x axis (the baseline) by which `pitch`'s
    rig has turned at `frame`: each eye's image is warped by K R K⁻¹ (R for the left eye),
    so a tissue point X of the left camera's frame-0 coordinates is seen at R X."""
    angle = np.radians(pitch_deg * PITCH_WAVE[frame % len(PITCH_WAVE)])
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def relit(view: np.ndarray, wave: float, gain: float, shade: float) -> np.ndarray:
    """view (H, W, 3) uint8 with its brightness scaled by 1 + gain · wave and a ramp across
    it of slope shade · wave (wave in [-1, 1]), rounded and clipped to 8 bits."""
    ramp = np.linspace(-0.5, 0.5, view.shape[1]) * shade * wave
    scale = (1.0 + gain * wave + ramp)[None, :, None]
    return np.clip(np.rint(view * scale), 0, 255).astype(np.uint8)


def make_clip(spec: str, out_dir: Path) -> tuple[Path, Path]:
    """Build the clip of `spec` under out_dir; returns (log.mcap, config.toml)."""
    from surgrecon_cli.cli.main import main as cli

    opts = parse_spec(spec)
    frames = decoded_frames(int(opts["frames"]))[::max(int(opts["step"]), 1)]
    if opts["reverse"]:
        frames = frames[::-1]
    if opts["breathe"]:
        frames = breathing_clip(frames[0], opts, out_dir)
    elif opts["length"]:
        cycle = frames + frames[-2:0:-1]
        frames = [cycle[i % len(cycle)] for i in range(int(opts["length"]))]
    folder = out_dir / "images"
    calib = calibration()
    K = {"left": calib["M1"], "right": calib["M2"]}
    r_rel = calib["R"]  # x_right = R x_left + T
    for i, frame in enumerate(frames):
        rot = pitch_rotation(opts["pitch"], i)
        for side, view in (("left", frame[:, :1280]), ("right", frame[:, 1280:])):
            if opts["pitch"]:
                r = rot if side == "left" else r_rel @ rot @ r_rel.T
                h = K[side] @ r @ np.linalg.inv(K[side])
                view = cv2.warpPerspective(view, h, (1280, 1024), flags=cv2.INTER_LINEAR)
            if opts["gain"] or opts["shade"]:
                view = relit(view, PITCH_WAVE[i % len(PITCH_WAVE)] / 3.0, opts["gain"],
                             opts["shade"])
            if opts["scale"] != 1.0:
                size = (round(1280 * opts["scale"]), round(1024 * opts["scale"]))
                view = cv2.resize(view, size, interpolation=cv2.INTER_AREA)
            (folder / side).mkdir(parents=True, exist_ok=True)
            if opts["jpeg"]:
                ok, data = cv2.imencode(".jpg", view, [cv2.IMWRITE_JPEG_QUALITY,
                                                       int(opts["jpeg"])])
                assert ok
                (folder / side / f"{i:06d}.jpg").write_bytes(data.tobytes())
            else:
                cv2.imwrite(str(folder / side / f"{i:06d}.png"), view)
    log = out_dir / "clip.mcap"
    argv = ["convert", str(folder), "-o", str(log), "--calibration",
            str(scaled_calibration(out_dir / "calibration.yaml", opts["scale"])),
            "--fps", str(CLIP_FPS), "-q"]
    if cli(argv) != 0:
        raise RuntimeError(f"convert failed for clip {spec!r}")
    return log, log.with_suffix(".toml")
