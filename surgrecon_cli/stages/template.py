"""Stage `build-template`: the template cloud P from the run's first frame.

Writes RUN/template.ply (extra vertex properties n_views, reprojection_px and sigma: the
point's 3D position uncertainty, RMS, metres; the labelled frame-0 cloud is written by
classify),
RUN/template/observations.npz (where each template point was seen at frame 0, for tracking;
each point's 3D covariance, m², from image noise, and pose_covariance, from the cameras'
pose errors, including the rigid error of a shared tracker body, core/noise/model.py) and
RUN/template/summary.json (counts, pair plan, pixel_noise_px).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..config import Config
from ..core.noise.model import covariance_sigma, noise_from_report
from ..core.template.build import (
    STEPS,
    BuildOptions,
    TemplateFrame,
    TemplateResult,
    build_template,
)
from ..core.template.sharpness import (
    blurred_cameras,
    decode_reduction,
    first_sharp,
    sharpness,
    typical_sharpness,
)
from ..errors import InputError
from ..executors import Executor, mapper
from ..executors.heap import kept_heap
from ..executors.serial import SerialExecutor
from ..io.run.artefacts import (
    TemplateCloud,
    TemplateObservations,
    write_observations,
    write_template,
    write_template_summary,
)
from ..io.run.ingest_store import IngestedLog, load_ingested
from ..io.run.layout import RunLayout
from .common import stage_run, tools_as_seen
from .registry import StageContext

STAGE = "build-template"
BLUR_FRAMES = 5  # ours: later frames frame 0's sharpness is compared with
logger = logging.getLogger(__name__)


def run_build_template(
    run_dir: Path, config: Config, on_step: Callable[[str], None] | None = None,
    executor: Executor | None = None,
) -> TemplateResult:
    """Build and write the template of frame 0 of an ingested run; the features of each
    camera and the matches of each pair are tasks on `executor` (default: serial)."""
    layout = RunLayout(run_dir)
    with stage_run(layout.root, STAGE, config) as info:
        log = load_ingested(layout.ingest_dir)
        if log.n_frames == 0:
            raise InputError(f"{run_dir}: the ingested log has no frames")
        images, poses = log.frame_images(0), log.usable_poses(0)
        with kept_heap():  # SIFT's scale spaces, ~0.5 GB a 1080p image, reuse the memory
            result = build_template(
                TemplateFrame(images, poses, tools_as_seen(log, config, 0)),
                list(log.models),
                config.template,
                config.tool_configs(),
                BuildOptions(
                    on_step=on_step,
                    map_calls=mapper(executor or SerialExecutor()),
                    noise=noise_from_report(log.report, log.cameras, pixel_px=0.0),
                    names=log.cameras,
                    tracker=config.target,
                ),
            )
        blur = _blurred_start(log)
        for line in (*result.warnings, *blur):
            logger.warning("%s", line)
        n = len(result.points)
        obs = result.observations
        sigma = covariance_sigma(result.covariance + result.pose_covariance) if n else np.zeros(0)
        write_template(layout, TemplateCloud(result.points, result.rgb, result.n_views,
                                             result.reprojection_px, sigma))
        write_observations(layout, TemplateObservations(
            obs.point, obs.camera, obs.pixels, result.covariance, result.pose_covariance,
            result.pixel_noise_px))
        plan = {
            "groups": [[log.cameras[c] for c in g] for g in result.plan.groups],
            "sequence": [
                [[log.cameras[i], log.cameras[j]] for i, j in seq] for seq in result.plan.sequences
            ],
            "predicted_overlap": result.prediction.overlap.round(3).tolist(),
            "view_angle_deg": result.prediction.angle_deg.round(1).tolist(),
            "baseline_ratio": result.prediction.baseline_ratio.round(3).tolist(),
        }
        # the link warnings, for the report (they were printed once, at this stage only)
        stats = {**result.stats, "warnings": [*result.warnings, *blur]}
        write_template_summary(layout, {"stats": stats, "pairs": plan})
        info.update(points=n, groups=plan["groups"], sequence=plan["sequence"], stats=stats,
                    pixel_noise_px=result.pixel_noise_px,
                    tracker_bodies=log.report.get("tracker_bodies", []),
                    sigma_median_mm=float(np.median(sigma) * 1e3) if n else None)
    return result


def _blurred_start(log: IngestedLog) -> list[str]:
    """A warning when frame 0 (the template's) is blurred in some cameras against their next
    BLUR_FRAMES images (core/template/sharpness), naming the first frame sharp in all of
    them to start at (the ingest.start_s that starts there: seconds after the log's first
    frame, where this run's frame 0 is `start_s` of the ingest report)."""
    later = range(1, min(log.n_frames, 1 + BLUR_FRAMES))
    measure = np.full((1 + len(later), len(log.cameras)), np.nan)
    for c, model in enumerate(log.models):
        reduced = decode_reduction(model.width)
        for row, frame in enumerate((0, *later)):
            if log.usable[frame, c]:
                measure[row, c] = sharpness(log.load_image(frame, c, reduced))
    blurred = blurred_cameras(measure[0], measure[1:])
    if not len(blurred):
        return []
    names = ", ".join(log.cameras[c] for c in blurred)
    values = " / ".join(f"{v:.3g}" for v in measure[0, blurred])
    against = " / ".join(f"{v:.3g}" for v in typical_sharpness(measure[1:])[blurred])
    advice = "start at a sharp frame with --set ingest.start_s=SECONDS"
    sharp = first_sharp(measure[1:], blurred)
    if sharp is not None:
        first = 1 + sharp
        since = log.report.get("start_s", 0.0) + (log.stamps_ns[first] - log.stamps_ns[0]) / 1e9
        since = np.floor(since * 1e3) / 1e3  # printed to the ms below it: that frame is kept
        advice = f"start at frame {first}, the first sharp one: --set ingest.start_s={since:.3f}"
    return [f"frame 0, the template's, is blurred in camera(s) {names} (sharpness {values} "
            f"against {against} in the next frames): the template will be sparse and "
            f"imprecise; {advice}"]


def pipeline_step(ctx: StageContext, progress: Callable[[float], None]) -> None:
    """The stage within `surgrecon run`: progress by template-building step."""
    run_build_template(ctx.run_dir, ctx.config, executor=ctx.executor,
                       on_step=lambda name: progress((STEPS.index(name) + 1) / len(STEPS)))
