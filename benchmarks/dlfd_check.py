"""The d-lfd goal of issue 23: no template point within 1 mm of either arm's model in any
camera, and the PNG of the template over one camera image with both arms' masks.

    python benchmarks/dlfd_mcap.py --repo /path/to/d-lfd.git -o OUT
    surgrecon run OUT/dlfd_1.mcap -o RUN --config OUT/dlfd_1.toml
    python benchmarks/dlfd_check.py RUN --config OUT/dlfd_1.toml --camera p2l --png FILE

Prints, per camera, how many frame-0 template points it observed and the smallest distance
from one of them to each arm's model surface; exit 1 when one is under 1 mm.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np

from surgrecon_cli.config import load_config
from surgrecon_cli.core.geometry.cameras import project
from surgrecon_cli.core.geometry.poses import point_to_segment_distance
from surgrecon_cli.core.geometry.tool import camera_tool_poses, tool_capsules, tool_image_mask
from surgrecon_cli.io.run.artefacts import read_observations, read_template
from surgrecon_cli.io.run.ingest_store import load_ingested
from surgrecon_cli.io.run.layout import RunLayout


def _as_seen(log, cfgs) -> np.ndarray:
    """(C, K, 4, 4): each camera's view of the tools at frame 0 (with `camera_offsets`)."""
    tools = log.all_tool_poses(0)
    per_camera = camera_tool_poses(tools, cfgs, list(log.cameras))
    return np.repeat(tools[None], len(log.cameras), 0) if per_camera is None else per_camera


def clearance(run: Path, config_path: Path) -> dict[str, tuple[int, list[float]]]:
    """Per camera: how many frame-0 template points it observed, and per tool the smallest
    distance (mm) from one of them to the tool model's surface as that camera sees it
    (`camera_offsets`) (negative = inside; inf =
    none observed)."""
    layout = RunLayout(run)
    log = load_ingested(layout.ingest_dir)
    cfgs = load_config(config_path).tool_configs()
    points = read_template(layout).points
    obs = read_observations(layout, len(points))
    tools = _as_seen(log, cfgs)
    out = {}
    for c, cam in enumerate(log.cameras):
        seen = points[np.unique(obs.point[obs.camera == c])]
        out[cam] = (len(seen), [
            min((float((point_to_segment_distance(seen, a, b) - r).min()) * 1e3
                 for a, b, r in tool_capsules(pose, cfg) if len(seen)), default=np.inf)
            for pose, cfg in zip(tools[c], cfgs, strict=True)])
    return out


def figure(run: Path, config_path: Path, camera: str, png: Path) -> None:
    """The template (frame 0) over `camera`'s image, 3x enlarged, with every tool's mask (arm 1
    red, arm 2 green): points this camera observed filled, the other pairs' points as rings."""
    layout = RunLayout(run)
    log = load_ingested(layout.ingest_dir)
    cfgs = load_config(config_path).tool_configs()
    c = log.cameras.index(camera)
    image = log.load_image(0, c)[:, :, ::-1].copy()
    for pose, cfg, colour in zip(_as_seen(log, cfgs)[c], cfgs, ((0, 0, 255), (0, 255, 0)),
                                 strict=False):
        mask = tool_image_mask(log.models[c], log.poses[0, c], pose, cfg, step=1)
        image[mask] = (0.5 * image[mask] + 0.5 * np.array(colour)).astype(np.uint8)
    points = read_template(layout).points
    obs = read_observations(layout, len(points))
    seen = np.isin(np.arange(len(points)), obs.point[obs.camera == c])
    px, _ = project(points, log.poses[0, c], log.models[c])
    big = cv2.resize(image, None, fx=3, fy=3, interpolation=cv2.INTER_NEAREST)
    for (u, v), own in zip(px, seen, strict=True):
        if np.isfinite([u, v]).all():
            centre = (round(3 * u + 1), round(3 * v + 1))
            cv2.circle(big, centre, 4, (255, 255, 0), -1 if own else 1)
    cv2.imwrite(str(png), big)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path, help="run folder of a dlfd_mcap.py log")
    parser.add_argument("--config", type=Path, required=True, help="the log's config")
    parser.add_argument("--camera", default="p2l", help="camera of the figure")
    parser.add_argument("--png", type=Path, help="write the figure here")
    args = parser.parse_args()
    if args.png:
        figure(args.run, args.config, args.camera, args.png)
        print(f"wrote {args.png}")
    stats = json.loads(RunLayout(args.run).template_summary.read_text())["stats"]
    print(f"template: {stats['points']} points; {stats['removed_tool']} dropped in 3D for lying "
          "within radius + margin_m of a tool")
    worst = np.inf
    for cam, (n, gaps) in clearance(args.run, args.config).items():
        print(f"{cam}: {n} template points observed; closest to arm 1 / arm 2 model: "
              + " / ".join(f"{g:.1f} mm" for g in gaps))
        worst = min(worst, *gaps)
    print(f"{'PASS' if worst >= 1.0 else 'FAIL'}: no template point within 1 mm of either "
          f"arm's model in any camera (closest {worst:.1f} mm)")
    sys.exit(0 if worst >= 1.0 else 1)


if __name__ == "__main__":
    main()
