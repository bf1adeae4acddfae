"""Stage `build-template`: the template cloud P from the run's first frame.

Writes RUN/template.ply, RUN/clouds/000000.ply (all points static; extra vertex properties
n_views, reprojection_px and sigma: the point's 3D position uncertainty, RMS, metres),
RUN/template/observations.npz (where each template point was seen at frame 0, for tracking;
each point's 3D covariance, m², from image noise, and pose_covariance, from the cameras'
pose errors, including the rigid error of a shared tracker body, core/noise.py) and
RUN/template/summary.json (counts, pair plan, pixel_noise_px).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..config import Config
from ..core.labels import STATIC
from ..core.noise import covariance_sigma, noise_from_report
from ..core.template import TemplateResult, build_template
from ..core.tool import tool_pose_in_world
from ..errors import InputError
from ..executors import Executor, mapper
from ..executors.serial import SerialExecutor
from ..io.atomic import write_json, write_npz
from ..io.ingest_store import load_ingested
from ..io.ply import write_cloud_ply
from .common import stage_run

STAGE = "build-template"


def cloud_path(run_dir: Path, frame: int) -> Path:
    return Path(run_dir) / "clouds" / f"{frame:06d}.ply"


def run_build_template(
    run_dir: Path, config: Config, on_step: Callable[[str], None] | None = None,
    executor: Executor | None = None,
) -> TemplateResult:
    """Build and write the template of frame 0 of an ingested run; the features of each
    camera and the matches of each pair are tasks on `executor` (default: serial)."""
    run_dir = Path(run_dir)
    with stage_run(run_dir, STAGE, config, config_sections=("topics", "ingest")) as info:
        log = load_ingested(run_dir / "ingest")
        if log.n_frames == 0:
            raise InputError(f"{run_dir}: the ingested log has no frames")
        images, poses = log.frame_images(0), log.usable_poses(0)
        tool_pose = tool_pose_in_world(log.tool_poses[0], config.tool)
        result = build_template(
            images,
            list(log.models),
            poses,
            tool_pose,
            config.template,
            config.tool,
            on_step=on_step,
            map_calls=mapper(executor or SerialExecutor()),
            noise=noise_from_report(log.report, log.cameras, pixel_px=0.0),
        )
        n = len(result.points)
        obs = result.observations
        sigma = covariance_sigma(result.covariance + result.pose_covariance) if n else np.zeros(0)
        extra = {
            "n_views": result.n_views.astype(np.uint8),
            "reprojection_px": result.reprojection_px.astype(np.float32),
            "sigma": sigma.astype(np.float32),
        }
        for path in (run_dir / "template.ply", cloud_path(run_dir, 0)):
            write_cloud_ply(
                path,
                result.points,
                rgb=result.rgb,
                point_id=np.arange(n, dtype=np.int32),
                label=np.full(n, STATIC, np.uint8),
                residual=np.zeros(n, np.float32),
                extra=extra,
            )
        write_npz(
            run_dir / "template" / "observations.npz",
            point=obs.point.astype(np.int32),
            camera=obs.camera.astype(np.int16),
            pixels=obs.pixels.astype(np.float32),
            covariance=result.covariance.astype(np.float64),
            pose_covariance=result.pose_covariance.astype(np.float64),
            pixel_noise_px=np.float64(result.pixel_noise_px),
        )
        plan = {
            "groups": [[log.cameras[c] for c in g] for g in result.plan.groups],
            "sequence": [
                [[log.cameras[i], log.cameras[j]] for i, j in seq] for seq in result.plan.sequences
            ],
            "predicted_overlap": result.prediction.overlap.round(3).tolist(),
            "view_angle_deg": result.prediction.angle_deg.round(1).tolist(),
            "baseline_ratio": result.prediction.baseline_ratio.round(3).tolist(),
        }
        write_json(run_dir / "template" / "summary.json", {"stats": result.stats, "pairs": plan})
        info.update(points=n, groups=plan["groups"], sequence=plan["sequence"], stats=result.stats,
                    pixel_noise_px=result.pixel_noise_px,
                    tracker_bodies=log.report.get("tracker_bodies", []),
                    sigma_median_mm=float(np.median(sigma) * 1e3) if n else None)
    return result
