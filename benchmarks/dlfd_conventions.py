"""Which frame conventions put d-lfd's arms on its instruments: pixel errors against hand marks.

    python benchmarks/dlfd_conventions.py [--repo /path/to/d-lfd.git]

The reference is independent of the kinematics: tests/data/dlfd/marks.json, jaw tips and
shaft centre lines marked by eye in trial 1's videos. For each convention (one factor
changed at a time from the one `dlfd_mcap.py` uses) it prints, over the marks, the median
and worst of: the tip error (px from the projected kinematic point to the marked tip), the
lateral error (px from the kinematic point to the marked shaft line, extended) and the
shaft-angle error (degrees between the projected model shaft and the marked one). Images
are 310x244 px; 1 px is about 0.45 mm at the instruments.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from dlfd_mcap import (
    CAMERAS,
    FPS,
    PAIRS,
    arm_corrections,
    arms_in_world,
    base2_in_base1,
    camera_in_base1,
    camera_model,
    config_text,
    load,
    load_shipped,
    sample_at,
    shaft_pose,
)

from surgrecon_cli.config import load_config
from surgrecon_cli.core.geometry.cameras import project
from surgrecon_cli.core.geometry.tool import camera_tool_poses, tool_image_mask, tool_pixel_mask

MARKS = Path(__file__).resolve().parents[1] / "tests" / "data" / "dlfd" / "marks.json"


@dataclass(frozen=True)
class Convention:
    name: str
    hand_eye: str = "camera-to-base"  # or "base-to-camera"
    timing: str = "from start_imaging"  # or "over the whole video"
    labels: str = "arm 1 = right"  # or "arm 1 = left" (the README's roles)
    shaft: str = "through the RCM"  # or a jaw-frame axis "+z", "-y", ...
    base2: str = "mean of pairs"  # or "pair 1", "pair 2", "pair 3"
    cameras: str = "both robots' hand-eye"  # or "robot 1's hand-eye"


CHOSEN = Convention("chosen")
TRIED = [
    CHOSEN,
    replace(CHOSEN, name="hand-eye inverted", hand_eye="base-to-camera"),
    replace(CHOSEN, name="cameras by robot 1's hand-eye only", cameras="robot 1's hand-eye"),
    replace(CHOSEN, name="samples over whole video", timing="over the whole video"),
    replace(CHOSEN, name="README's arm roles", labels="arm 1 = left"),
    *(replace(CHOSEN, name=f"shaft along jaw {a}", shaft=a) for a in ("+z", "-z", "-y", "+y")),
    *(replace(CHOSEN, name=f"robot 2 base from pair {k}", base2=f"pair {k}") for k in PAIRS),
    Convention("previous importer, shafts along jaw -y", timing="over the whole video",
               shaft="-y", base2="pair 2", cameras="robot 1's hand-eye"),
]


def _arm_world(d: dict, conv: Convention, arm: int, frame: int) -> tuple[np.ndarray, np.ndarray]:
    """The arm's kinematic point (3,) and unit shaft direction (3,) (towards the RCM) in the
    world (robot 1's base, as the convention places it)."""
    n = d["arms"].shape[1]
    j = (sample_at(frame / FPS, d) if conv.timing == "from start_imaging"
         else min(round(frame / FPS / d["duration_s"] * n), n - 1))
    tip = d["arms"][arm - 1, j]
    if conv.shaft == "through the RCM":
        pose = shaft_pose(tip)
        axis = pose[:3, 2]
    else:
        pose = tip
        axis = (-1 if conv.shaft[0] == "-" else 1) * tip[:3, "xyz".index(conv.shaft[1])]
    base = np.eye(4)
    if arm == 2:
        he = _hand_eye(d, conv)
        base = (base2_in_base1(he) if conv.base2 == "mean of pairs"
                else he[(1, int(conv.base2[-1]))] @ np.linalg.inv(he[(2, int(conv.base2[-1]))]))
    return base[:3, :3] @ pose[:3, 3] + base[:3, 3], base[:3, :3] @ axis


def _hand_eye(d: dict, conv: Convention) -> dict:
    if conv.hand_eye == "camera-to-base":
        return d["hand_eye"]
    return {key: np.linalg.inv(T) for key, T in d["hand_eye"].items()}


def errors(d: dict, conv: Convention, marks: list[dict]) -> np.ndarray:
    """(M, 3): tip px, lateral px, shaft angle (deg) per mark; inf when behind the camera."""
    dd = {**d, "hand_eye": _hand_eye(d, conv)}
    out = []
    for m in marks:
        right_is_1 = conv.labels == "arm 1 = right"
        arm = 1 if (m["instrument"] == "right") == right_is_1 else 2
        p, axis = _arm_world(d, conv, arm, m["frame"])
        fuse = conv.cameras == "both robots' hand-eye"
        uv, z = project(np.array([p, p + 0.03 * axis]), camera_in_base1(dd, m["camera"], fuse),
                        camera_model(d, m["camera"]))
        if not (np.isfinite(uv).all() and (z > 0).all()):
            out.append([np.inf] * 3)
            continue
        tip, (s0, s1) = np.array(m["tip"], float), np.array(m["shaft"], float)
        u = (s1 - s0) / np.linalg.norm(s1 - s0)
        lateral = abs(u[0] * (uv[0] - s0)[1] - u[1] * (uv[0] - s0)[0])
        model = uv[1] - uv[0]
        angle = np.degrees(np.arccos(np.clip(model @ u / np.linalg.norm(model), -1, 1)))
        out.append([np.linalg.norm(uv[0] - tip), lateral, angle])
    return np.array(out)


def corrected_lateral(d: dict, marks: list[dict], fits: dict) -> np.ndarray:
    """(M, 2): lateral px of each mark (as `errors`, chosen convention) without and with its
    pair's and arm's image-fitted translation (`dlfd_mcap.arm_corrections`); NaN for a
    mark whose pair was not fitted."""
    out = np.full((len(marks), 2), np.nan)
    for i, m in enumerate(marks):
        k, arm = int(m["camera"][1]), 1 if m["instrument"] == "right" else 2
        if (k, arm) not in fits:
            continue
        pose = arms_in_world(d, m["frame"])[arm - 1]
        s0, s1 = np.array(m["shaft"], float)
        u = (s1 - s0) / np.linalg.norm(s1 - s0)
        for j, move in enumerate((np.eye(4), fits[(k, arm)].move)):
            p = move @ pose
            uv, _ = project(p[None, :3, 3], camera_in_base1(d, m["camera"]),
                            camera_model(d, m["camera"]))
            out[i, j] = abs(u[0] * (uv[0] - s0)[1] - u[1] * (uv[0] - s0)[0])
    return out


def coverage(d: dict, marks: list[dict], config: Path) -> tuple[int, int, dict[str, float]]:
    """With the chosen convention and `config`'s tool geometry: how many of the marked points
    (tips and shaft points) lie in their instrument's mask, of how many, and the share of each
    marked camera's image that the masks take at frame 93."""
    cfgs = load_config(config).tool_configs()
    he = d["hand_eye"]
    world = {1: np.eye(4), 2: base2_in_base1(he)}

    def poses(frame: int) -> np.ndarray:
        return np.stack([world[r] @ shaft_pose(d["arms"][r - 1, sample_at(frame / FPS, d)])
                         for r in (1, 2)])

    def seen(frame: int, cam: str) -> np.ndarray:  # with the config's camera_offsets
        per_camera = camera_tool_poses(poses(frame), cfgs, CAMERAS)
        return poses(frame) if per_camera is None else per_camera[CAMERAS.index(cam)]

    hit = total = 0
    for m in marks:
        k = 0 if m["instrument"] == "right" else 1
        pixels = np.array([m["tip"], *m["shaft"]], float)
        pose = seen(m["frame"], m["camera"])[k]
        inside = tool_pixel_mask(pixels, camera_model(d, m["camera"]),
                                 camera_in_base1(d, m["camera"]), pose, cfgs[k])
        hit, total = hit + int(inside.sum()), total + len(pixels)
    share = {}
    for cam in sorted({m["camera"] for m in marks}):
        mask = tool_image_mask(camera_model(d, cam), camera_in_base1(d, cam), seen(93, cam), cfgs)
        share[cam] = float(mask.mean())
    return hit, total, share


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repo", type=Path, help="d-lfd git directory (default: the pieces "
                        "shipped in tests/data/dlfd)")
    args = parser.parse_args()
    marks = json.loads(MARKS.read_text(encoding="utf-8"))["marks"]
    if args.repo is None:
        d = load_shipped(MARKS.parent)
    else:
        with tempfile.TemporaryDirectory() as tmp:
            d = load(args.repo, 1, Path(tmp))
    print(f"{len(marks)} marks; median / worst over them")
    print(f"{'convention':40s} {'tip px':>13s} {'lateral px':>13s} {'angle deg':>13s}")
    for conv in TRIED:
        e = errors(d, conv, marks)
        cells = [f"{np.median(e[:, i]):6.1f} /{np.max(e[:, i]):6.1f}" for i in range(3)]
        print(f"{conv.name:40s} " + " ".join(f"{c:>13s}" for c in cells))
    fits = arm_corrections(d, 0)
    lateral = corrected_lateral(d, marks, fits)
    print("per pair and arm, the shaft fitted to the frame-0 images (translation mm; contrast "
          "grey levels, without -> with): "
          + ", ".join(f"p{k} arm {r} {np.round(f.move[:3, 3] * 1e3, 1).tolist()} "
                      f"({f.contrast_at_zero:.0f} -> {f.contrast:.0f})"
                      for (k, r), f in fits.items()))
    for m, (before, after) in zip(marks, lateral, strict=True):
        print(f"  {m['camera']} frame {m['frame']} {m['instrument']:5s} instrument: lateral "
              f"{before:5.1f} -> {after:5.1f} px")
    print(f"lateral px median / worst: {np.median(lateral[:, 0]):.1f} / "
          f"{lateral[:, 0].max():.1f} -> {np.median(lateral[:, 1]):.1f} / "
          f"{lateral[:, 1].max():.1f}")
    with tempfile.TemporaryDirectory() as tmp:
        config = Path(tmp) / "dlfd.toml"
        for name, fitted in (("without camera_offsets", {}), ("of the written config", fits)):
            config.write_text(config_text(fitted))
            hit, total, share = coverage(d, marks, config)
            print(f"masks {name}: {hit} of {total} marked tip and shaft points inside; share "
                  "of the image masked at frame 93: "
                  + ", ".join(f"{c} {100 * v:.0f} %" for c, v in share.items()))


if __name__ == "__main__":
    main()
