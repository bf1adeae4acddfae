"""Template point cloud P from the first frame (Su et al. 2019, section II.A, Fig. 3).

features (tool masked) -> pair prediction from poses -> pose-guided matching -> groups and
pair sequence -> tracks -> N-view triangulation -> outlier rejection -> tool point removal.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import cv2
import numpy as np

from ...config import TargetConfig, TemplateConfig
from ...errors import GeometryError
from ..geometry.cameras import CameraModel, project, view_distortion_jacobians
from ..geometry.tool import (
    ToolConfigs,
    flatten_camera_tools,
    points_near_tool,
    tool_image_mask,
)
from ..geometry.triangulate import Observations, reprojection_residuals, triangulate
from ..noise.model import (
    NoiseModel,
    body_pose_covariance,
    covariance_sigma,
    image_noise_sigma,
    localisation_noise_px,
    localisation_variance_px2,
    pixel_noise_from_residuals,
    point_covariances,
    projection_jacobians,
)
from ..target.tracking import tracking_view
from .features import detect_features, no_features
from .gate import group_disagreements, link_warnings, pair_minimums, unlinked_message
from .matching import CameraView, PairGates, build_tracks, match_pair
from .outliers import surface_outliers
from .pairing import PairPlan, PairPrediction, candidate_pairs, predict_pairs
from .refine import refinable_pairs, refine_observations
from .sequencing import (
    RigFeatures,
    SequenceGates,
    all_pairs,
    sequenced,
    track_observations,
)

# ours: the tool mask casts a ray every 4 px of a 640 px wide image, the same angular
# spacing at any width (at 1920 px: every 12 px, 9x fewer rays; the mask is dilated by it)
MASK_STEP_PX, MASK_STEP_WIDTH_PX = 4, 640
LOCALISATION_WINDOW_PX = 21  # ours: the patch a feature is located by (the KLT window)

# What `build_template` reports through `on_step`, in order (for progress bars).
STEPS = ("features", "matches", "points")

MapCalls = Callable[[Callable[..., Any], Sequence[tuple[Any, ...]]], list[Any]]
"""`map_calls(fn, calls)` returns `[fn(*args) for args in calls]`, possibly computed in
parallel (e.g. on an executor); fn is a module-level function, the args plain arrays."""


def map_here(fn: Callable[..., Any], calls: Sequence[tuple[Any, ...]]) -> list[Any]:
    """The default `MapCalls`: one call after another, in this process."""
    return [fn(*args) for args in calls]


@dataclass(frozen=True)
class TemplateResult:
    """Template cloud: points (N, 3) m, rgb (N, 3) uint8, n_views (N,), mean reprojection
    error (N,) px; covariance (N, 3, 3) m² from image noise (pixel_noise_px, px per axis, and
    the localisation bound), pose_covariance (N, 3, 3) m² from the cameras' pose errors
    (including the rigid error of a shared tracker body; core/noise/model.py), and sigma (N,) m
    the triangulation's uncertainty (√trace, per-view errors only: what the max_sigma_mm
    cut uses); the observations of each point at
    frame 0 (`observations.point` indexes points); the pair plan and prediction; counts of
    what each step kept; warnings (lines) on cameras that are not linked (gate.link_warnings)."""

    points: np.ndarray
    rgb: np.ndarray
    n_views: np.ndarray
    reprojection_px: np.ndarray
    covariance: np.ndarray
    pose_covariance: np.ndarray
    sigma: np.ndarray
    pixel_noise_px: float
    observations: Observations
    plan: PairPlan
    prediction: PairPrediction
    stats: dict
    warnings: list[str]


@dataclass(frozen=True)
class TemplateFrame:
    """The frame a template is built from: images[c] (H, W, 3) uint8 RGB or None
    (unusable), poses (C, 4, 4) camera-to-world, tool_pose (4, 4) tool tip in the world, or
    (K, 4, 4) of several tools (NaN = unknown), or (C, K, 4, 4) each camera's view of them
    (`camera_tool_poses`: masked per camera, points dropped near any camera's view)."""

    images: list[np.ndarray | None]
    poses: np.ndarray
    tool_pose: np.ndarray


@dataclass(frozen=True)
class BuildOptions:
    """Optional inputs of `build_template`: `on_step(name)` is called as each of `STEPS` is
    done; `map_calls` makes the independent calls (in parallel when it is an executor's);
    `noise` the tracker's measured jitter and shared bodies (None = not known); `names` (C,)
    name the cameras in messages (None: their indices); `tracker` the target's config, whose
    KLT refines the matches (`TemplateConfig.refine_matches`)."""

    on_step: Callable[[str], None] | None = None
    map_calls: MapCalls = map_here
    noise: NoiseModel | None = None
    names: Sequence[str] | None = None
    tracker: TargetConfig = field(default_factory=TargetConfig)


def build_template(
    frame: TemplateFrame,
    models: list[CameraModel],
    cfg: TemplateConfig,
    tool_cfg: ToolConfigs,
    options: BuildOptions | None = None,
) -> TemplateResult:
    """Build the template from one `frame`; `tool_cfg` has a config for each of its tools.
    `options.noise` (the tracker's measured jitter and shared bodies) makes each view's
    variance at least what the pose error alone projects (`measured_covariances`) and adds a
    shared body's rigid error.

    The feature detection of each camera and the matching of each candidate pair are
    independent calls, made through `options.map_calls` (in parallel when it is an
    executor's)."""
    images, poses, tool_pose = frame.images, frame.poses, frame.tool_pose
    opts = options or BuildOptions()
    map_calls, noise = opts.map_calls, opts.noise
    labels = [str(c) for c in opts.names or range(len(images))]
    step = opts.on_step or (lambda _name: None)
    usable = np.array(
        [im is not None and np.isfinite(p).all() for im, p in zip(images, poses, strict=True)]
    )
    if usable.sum() < 2:
        raise GeometryError(f"frame 0 has {int(usable.sum())} usable camera(s); need >= 2")
    per_camera = np.asarray(tool_pose).ndim == 4
    prediction = predict_pairs(
        models, np.where(usable[:, None, None], poses, np.eye(4)), usable, cfg.working_distance_m
    )
    # a stereo head's cameras (a partner at most 0.18 x the depth away: `refinable_pairs`)
    narrow = refinable_pairs(prediction.baseline_ratio) & usable[:, None] & usable[None, :]
    np.fill_diagonal(narrow, False)
    # corners (template.min_features) only in a camera with a stereo partner: their upright
    # descriptors are for views the same way up, and on a wide rig they only crowd SIFT's
    # matches out of the ratio test (6 cameras at 320x240: 398 -> 387 points, the
    # simulator's indentation error 0.03 -> 0.33 mm)
    masks = {c: tool_image_mask(models[c], poses[c], tool_pose[c] if per_camera else tool_pose,
                                tool_cfg, step=max(MASK_STEP_PX, round(
                                    MASK_STEP_PX * models[c].width / MASK_STEP_WIDTH_PX)))
             for c in np.flatnonzero(usable)}
    detect = [(images[c], models[c], cfg if narrow[c].any() else replace(cfg, min_features=0),
               masks[c]) for c in np.flatnonzero(usable)]
    detected = iter(map_calls(detect_features, detect))
    features = [next(detected) if usable[c] else no_features() for c in range(len(images))]
    minimums = pair_minimums([len(f) for f in features], cfg.min_pair_matches,
                             cfg.min_pair_match_fraction)
    step("features")
    focal = [m.K[0, 0] for m in models]
    views = [CameraView(features[c], poses[c], focal[c]) for c in range(len(features))]
    pairs = candidate_pairs(prediction, cfg.min_view_overlap)

    def match_pairs(todo: list[tuple[int, int]]) -> list[np.ndarray]:
        return map_calls(match_pair, [
            (views[i], views[j], PairGates(cfg.ratio, cfg.epipolar_px,
                                           (cfg.depth_range[0] * prediction.depth[i],
                                            cfg.depth_range[1] * prediction.depth[i])))
            for i, j in todo])

    if cfg.match_all_pairs:
        matched = all_pairs(pairs, match_pairs, prediction.conditioning, minimums)
    else:
        pose_px = (np.zeros(len(models)) if noise is None else
                   np.sqrt(noise.pose_variance_px2(prediction.depth, np.array(focal))))
        matched = sequenced(RigFeatures(features, poses, models), pairs, prediction,
                            match_pairs, SequenceGates(minimums, cfg.ratio, cfg.epipolar_px,
                                                       pose_px, cfg.max_reprojection_px))
    step("matches")
    plan = matched.plan
    track_ids, n_tracks = build_tracks([len(f) for f in features], matched.merges)
    if n_tracks == 0:
        raise GeometryError(unlinked_message(matched.counts, minimums, labels,
                                             cfg.min_pair_matches, cfg.min_pair_match_fraction,
                                             [len(f) for f in features]))
    obs = track_observations(features, track_ids).observations
    unrefined = 0
    if cfg.refine_matches:
        # only the cameras with a refinable partner need their tracking image (a wide rig: none)
        tracking = [tracking_view(im) if narrow[c].any() and im is not None else None
                    for c, im in enumerate(images)]
        obs, kept = refine_observations(obs, tracking, models, opts.tracker, cfg.epipolar_px,
                                        narrow)
        obs, unrefined = obs.subset(kept), int((~kept).sum())
        seen = np.bincount(obs.point, minlength=n_tracks) >= 2
        obs, n_tracks = obs.renumbered(seen), int(seen.sum())
    tri = triangulate(obs, poses, models, n_tracks)
    # Drop single bad observations and re-triangulate what still has >= 2 views.
    obs = obs.subset(tri.error_px <= cfg.max_reprojection_px)
    counts = np.bincount(obs.point, minlength=n_tracks)
    obs = obs.renumbered(counts >= 2)
    n_points = int((counts >= 2).sum())
    tri = triangulate(obs, poses, models, n_points)
    good = (
        np.isfinite(tri.points).all(1)
        & tri.in_front
        & (tri.max_error_px <= cfg.max_reprojection_px)
        & (tri.angle_deg >= cfg.min_angle_deg)
    )
    # The noise is measured on the geometrically good points; a point is then kept when the
    # depth accuracy its rays buy is good enough (not by a fixed triangulation angle).
    measured = measured_covariances(tri.points, obs, frame, models, good, noise)
    pixel_px, cov, image_cov = measured.pixel_px, measured.covariance, measured.image_covariance
    sigma = covariance_sigma(np.nan_to_num(cov, nan=np.inf))
    precise = np.isfinite(sigma) & (sigma <= cfg.max_sigma_mm * 1e-3)
    imprecise = good & ~precise
    good &= precise
    on_tool = points_near_tool(np.nan_to_num(tri.points),
                               *flatten_camera_tools(tool_pose, tool_cfg)) & good
    off_surface = np.zeros_like(good)
    candidates = np.flatnonzero(good & ~on_tool)
    off_surface[candidates] = surface_outliers(tri.points[candidates])
    keep = good & ~on_tool & ~off_surface
    obs_kept = obs.renumbered(keep)
    disagree = group_disagreements(views, plan.groups, pairs, cfg.min_pair_matches,
                                   cfg.epipolar_px)
    # Pose errors: per view (in `cov`), and a shared tracker body's, rigid for the body.
    pose_cov = cov[keep] - image_cov[keep]
    if noise is not None:
        pose_cov += body_pose_covariance(tri.points[keep], obs_kept.point, obs_kept.camera,
                                         np.nan_to_num(poses[:, :3, 3]), noise)
    stats = {
        "features": [len(f) for f in features],
        "candidate_pairs": len(pairs),
        "pairs_matched": matched.pairs_matched,
        "matched_to_template": matched.guided,
        "verified_pairs": len(matched.verified),
        "matches": {f"{i}-{j}": len(m) for (i, j), m in matched.verified.items()},
        "pair_counts": {f"{i}-{j}": n for (i, j), n in matched.counts.items()},
        "pair_minimums": {f"{i}-{j}": int(minimums[i, j]) for i, j in matched.counts},
        "disagreeing_groups": [[a, b, mm] for a, b, mm in disagree],
        "tracks": n_tracks,
        "views_not_refined": unrefined,
        "triangulated": n_points,
        "rejected_geometry": int((~good).sum() - imprecise.sum()),
        "rejected_imprecise": int(imprecise.sum()),
        "pixel_noise_px": pixel_px,
        "localisation_px": measured.localisation_px,
        "calibration_offset_px": [[round(float(v), 4) if np.isfinite(v) else None for v in row]
                                  for row in measured.offsets_px],
        "removed_tool": int(on_tool.sum()),
        "removed_off_surface": int(off_surface.sum()),
        "points": int(keep.sum()),
    }
    step("points")
    return TemplateResult(
        points=tri.points[keep],
        rgb=obs_kept.mean_rgb(int(keep.sum())),
        n_views=tri.n_views[keep],
        reprojection_px=tri.mean_error_px[keep],
        covariance=image_cov[keep],
        pose_covariance=pose_cov,
        sigma=sigma[keep],
        pixel_noise_px=pixel_px,
        observations=obs_kept,
        plan=plan,
        prediction=prediction,
        stats=stats,
        warnings=link_warnings(plan.groups, matched.counts, minimums, labels, disagree),
    )


@dataclass(frozen=True)
class MeasuredNoise:
    """The template's measured pixel noise: pixel_px (px per axis, at least the localisation
    bound), its localisation part localisation_px (the residuals less each camera's median,
    core/noise/model.py `localisation_noise_px`) and those medians offsets_px (C, 2) px; every
    point's covariance (N, 3, 3) m² in all and from image noise alone (image_covariance)."""

    pixel_px: float
    localisation_px: float
    offsets_px: np.ndarray
    covariance: np.ndarray
    image_covariance: np.ndarray


def measured_covariances(points: np.ndarray, obs: Observations, frame: TemplateFrame,
                         models: list[CameraModel], use: np.ndarray,
                         noise: NoiseModel | None = None) -> MeasuredNoise:
    """Pixel noise σ_px (px) measured from the reprojection residuals of the points `use`
    (N,) bool (at least the localisation bound), and every point's covariance (N, 3, 3) m²
    from its views in `frame` (its images and poses), in all and from image noise alone.
    Each view's
    variance is the larger of σ_px² and the Cramér-Rao bound of locating it in its image
    (core/noise/model.py) plus, for a camera not on a shared tracker body, the pose error the
    tracker's measured jitter projects at the point's depth: with two views the residuals
    only see the error across the epipolar line, and the triangulation absorbs much of
    the cameras' pose errors into the points (measured: 0.25 mm of tracker noise left
    0.50 px of residuals and a template 3x less accurate than they implied)."""
    poses, images = frame.poses, frame.images
    residual, _ = reprojection_residuals(points, obs, poses, models)
    sel = use[obs.point]
    pixel_px = pixel_noise_from_residuals(residual[sel], obs.point[sel])
    localisation_px, offsets = localisation_noise_px(residual[sel], obs.point[sel],
                                                     obs.camera[sel], len(models))
    pixel_px = pixel_px if np.isfinite(pixel_px) and pixel_px > 0 else 1.0
    variance = np.full(len(obs.point), pixel_px**2)
    image_variance = variance.copy()
    for c in np.unique(obs.camera):
        image = images[c]
        if image is None:
            continue
        grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
        rows = obs.camera == c
        bound = localisation_variance_px2(grey, obs.pixels[rows], LOCALISATION_WINDOW_PX,
                                          image_noise_sigma(grey))
        bound = np.where(np.isfinite(bound), bound, 0.0)
        image_variance[rows] = np.maximum(variance[rows], bound)
        if noise is not None and not noise.on_shared_body(np.array([c]))[0]:
            _, depth = project(np.nan_to_num(points[obs.point[rows]]), poses[c], models[c])
            bound = bound + noise.pose_variance_px2(depth, np.full(len(depth),
                                                                   models[c].K[0, 0]))
        variance[rows] = np.maximum(variance[rows], bound)
    focal = np.array([m.K[0, 0] for m in models])
    at = np.nan_to_num(points[obs.point])
    J, _ = projection_jacobians(at, poses[obs.camera], focal[obs.camera],
                                view_distortion_jacobians(at, obs.camera, poses, models))
    cov = point_covariances(obs.point, J, variance, len(points))
    image_cov = point_covariances(obs.point, J, image_variance, len(points))
    image_px = float(np.sqrt(np.median(image_variance[sel]))) if sel.any() else pixel_px
    return MeasuredNoise(image_px, localisation_px, offsets, cov, image_cov)
