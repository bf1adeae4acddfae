"""Target cloud G of a frame (Su et al. 2019, section II.B, Fig. 4).

Template points are projected at their latest positions into the new images (visibility:
in front, inside the image, not occluded, outside the tool mask), found there by pyramidal
KLT from the same camera's image at a reference frame (the pipeline uses the template's
base frame, so that frames do not depend on each other; forward-backward checked), then
sorted by the reprojection-error check in CoSLAM's form (Zou & Tan 2013): residuals are
gated in units of the run's measured noise (core/noise/model.py), as a Mahalanobis distance with
a chi-square bound at `target.significance`, so that a narrow baseline or a noisy tracker
moves the gate with the noise instead of a fixed pixel count:
- intra-camera inlier: seen by >= 2 cameras, and its frame-0 position still reprojects into
  every camera that sees it, with d² = eᵀ (J Σ_p Jᵀ + s² I)⁻¹ e within the bound (Σ_p the
  template point's covariance, s² the view's pixel variance: pixel + tracking + pose
  noise) -> static
  evidence, target = frame-0 position, covariance Σ_p;
- inter-camera inlier: seen by >= 2 cameras and re-triangulated with every view's
  ‖e‖² / s² within the bound -> dynamic, target = new position, covariance from its views;
- outlier: anything else (a point seen by one camera cannot be confirmed dynamic);
- unobserved: not visible now -> kept at its latest position, no data weight.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import cKDTree
from scipy.stats import chi2

from ..classify.labels import INTER, INTRA, OUTLIER, STATUS_NAMES, UNOBSERVED
from ..classify.rules import displacement_covariance, significant_motion
from ..geometry.cameras import project, view_distortion_jacobians
from ..geometry.tool import flatten_camera_tools, points_near_tool
from ..geometry.triangulate import triangulate
from ..noise.frame_noise import (
    MultiView,
    local_motion_noise_px,
    tracking_excess_px2,
    triangulate_found,
)
from ..noise.model import (
    NoiseModel,
    body_pose_covariance,
    covariance_sigma,
    point_covariances,
    projection_jacobians,
)
from .frame_inputs import FrameInput, Rig, Sighting, TemplateData
from .track_points import find_points
from .tracking import TrackingView


@dataclass(frozen=True)
class TargetCloud:
    """Per template point (N): target position (N, 3) m (latest position if unobserved, NaN
    for outliers), status (N,) uint8 (INTRA/INTER/OUTLIER/UNOBSERVED), views (N,) cameras
    that found it; pixels (N, C, 2) where it was found in each camera (NaN = not found);
    covariance (N, 3, 3) m² of the target position from image noise, pose_covariance
    (N, 3, 3) m² from the cameras' pose errors (per view, or the rigid error of a shared
    tracker body; core/noise/model.py), common to nearby points, and sigma (N,) m = √trace of
    their sum (NaN without a target); the frame's noise model (its tracking_px measured in
    this frame)."""

    positions: np.ndarray
    status: np.ndarray
    views: np.ndarray
    pixels: np.ndarray
    covariance: np.ndarray
    pose_covariance: np.ndarray
    sigma: np.ndarray
    noise: NoiseModel

    def counts(self) -> dict[str, int]:
        return {name: int((self.status == code).sum()) for code, name in STATUS_NAMES.items()}


def gate_chi2(significance: float, dof: int = 2) -> float:
    """Chi-square bound a noise-only residual of `dof` dimensions exceeds with probability
    `significance`."""
    return float(chi2.isf(significance, dof))


@dataclass(frozen=True)
class Tracks:
    """Where the template points were found in a frame: pixels (N, C, 2) (NaN = not
    found), found (N, C) bool, and each found pixel's localisation variance (N, C) px²."""

    pixels: np.ndarray
    found: np.ndarray
    localisation: np.ndarray


def _view_terms(points: np.ndarray, rows: np.ndarray, camera: int, tracks: Tracks, rig: Rig,
                poses: np.ndarray):
    """Residual e (M, 2) px, Jacobian (M, 2, 3) and pixel variance (M,) of points (M, 3)
    found at tracks.pixels[rows, camera] in `camera` (posed by poses (C, 4, 4))."""
    models = rig.models
    uv, _ = project(points, poses[camera], models[camera])
    focal = np.full(len(points), models[camera].K[0, 0])
    cams = np.full(len(points), camera)
    J, z = projection_jacobians(points, np.broadcast_to(poses[camera], (len(points), 4, 4)),
                                focal, view_distortion_jacobians(points, cams, poses, models))
    variance = rig.noise.tracked_view_variance_px2(z, focal,
                                                   tracks.localisation[rows, camera])
    e = uv - tracks.pixels[rows, camera]
    e[~(z > 0)] = np.inf
    return e, J, variance


def intra_distances(template: TemplateData, tracks: Tracks, rig: Rig,
                    poses: np.ndarray) -> np.ndarray:
    """Squared Mahalanobis distance (N, C) of each found pixel from the projection of the
    point's frame-0 position, with covariance J Σ_p Jᵀ + s² I (s² without the tracking
    error the views share); inf where not found."""
    found = tracks.found
    d2 = np.full(found.shape, np.inf)
    for c in range(found.shape[1]):
        rows = np.flatnonzero(found[:, c])
        if len(rows) == 0:
            continue
        e, J, variance = _view_terms(template.points[rows], rows, c, tracks, rig, poses)
        # Without the tracking error a point's views share: a shared error fails the test
        # and the point is re-triangulated (it moves across the line of sight only), while
        # with it each view alone lets motion along the line of sight pass as static.
        variance = rig.noise.independent_view_variance_px2(variance)
        cov = np.nan_to_num(template.covariance[rows], nan=0.0)
        S = (J @ cov) @ np.swapaxes(J, 1, 2) + variance[:, None, None] * np.eye(2)
        det = S[:, 0, 0] * S[:, 1, 1] - S[:, 0, 1] * S[:, 1, 0]
        quad = (S[:, 1, 1] * e[:, 0] ** 2 - 2 * S[:, 0, 1] * e[:, 0] * e[:, 1]
                + S[:, 0, 0] * e[:, 1] ** 2) / np.maximum(det, 1e-300)
        d2[rows, c] = np.where(np.isfinite(quad), quad, np.inf)
    return d2


def reprojection_check(template: TemplateData, tracks: Tracks, rig: Rig, poses: np.ndarray,
                       multi: MultiView | None = None):
    """Split points by the reprojection-error check (gate at `rig.cfg.significance`, the
    frame's noise in `rig.noise`), cameras posed by poses (C, 4, 4). `multi`: the points
    found by >= 2 cameras already triangulated from `tracks` (`triangulate_found`; None:
    triangulated here).

    Returns status (N,), positions (N, 3) (re-triangulated for inter; for intra the template
    position when the re-triangulation agrees with it in 3D, `_at_rest`, else
    re-triangulated; NaN otherwise) and the covariances (N, 3, 3) m² of those positions from
    image noise alone and from the cameras' pose errors (NaN otherwise; the pose part of
    views of a shared tracker body is its rigid error: `body_pose_covariance`).
    """
    found, pixels, localisation = tracks.found, tracks.pixels, tracks.localisation
    models, noise = rig.models, rig.noise
    n = len(found)
    bound = gate_chi2(rig.cfg.significance)
    views = found.sum(1)
    status = np.full(n, OUTLIER, np.uint8)
    status[views == 0] = UNOBSERVED
    positions = np.full((n, 3), np.nan)
    covariances = np.full((n, 3, 3), np.nan)
    pose_part = np.full((n, 3, 3), np.nan)
    template_pose = template.pose_covariance
    d2 = intra_distances(template, tracks, rig, poses)
    # One view cannot confirm a point static (it may move along that camera's ray), just as
    # it cannot confirm it dynamic.
    intra = (views >= 2) & np.all(np.where(found, d2 <= bound, True), axis=1)
    status[intra] = INTRA
    positions[intra] = template.points[intra]
    covariances[intra] = template.covariance[intra] - template_pose[intra]
    pose_part[intra] = template_pose[intra]
    # intra points too: each view alone misses motion along a narrow baseline's lines of sight
    candidates = np.flatnonzero(views >= 2)
    use = found[candidates].copy()
    focal = np.array([m.K[0, 0] for m in models])
    for attempt in range(2):  # second attempt without each point's worst view
        keep = use.sum(1) >= 2
        idx, use = candidates[keep], use[keep]
        if len(idx) == 0:
            break
        if multi is None:
            multi = triangulate_found(found, pixels, models, poses)
        if attempt == 0:  # every view of each point: the frame's triangulation of them
            obs, tri = multi.of_rows(idx)
        else:
            obs = multi.views_of(idx, use)
            tri = triangulate(obs, poses, models, len(idx))
        rows, cams = obs.point, obs.camera
        at = np.nan_to_num(tri.points[rows])
        J, z = projection_jacobians(at, poses[cams], focal[cams],
                                    view_distortion_jacobians(at, cams, poses, models))
        # Image noise alone; with each view's pose error (gating); and with the pose error of
        # views not on a shared tracker body (whose error is rigid for the body instead).
        image_only = noise.tracked_view_variance_px2(
            z, focal[cams], localisation[idx[rows], cams], pose=False)
        pose_variance = noise.pose_variance_px2(z, focal[cams])
        variance = image_only + pose_variance
        own_pose = np.where(noise.on_shared_body(cams), 0.0, pose_variance)
        scaled = np.full(use.shape, -np.inf)
        scaled[rows, cams] = tri.error_px**2 / variance
        worst_scaled = np.max(scaled, axis=1)
        good = tri.in_front & (worst_scaled <= bound) & np.isfinite(tri.points).all(1)
        # The tracking error the views share moves the point across its line of sight.
        lateral = noise.lateral_covariance(np.nan_to_num(tri.points), rows, cams,
                                           poses[:, :3, 3], focal)
        image_independent = noise.independent_view_variance_px2(image_only)
        cov = point_covariances(rows, J, image_independent, len(idx)) + lateral
        cov_all = point_covariances(rows, J, image_independent + own_pose, len(idx)) + lateral
        rest = good & intra[idx]
        rest[rest] = _at_rest(template, idx[rest], tri.points[rest], cov[rest],
                              cov_all[rest] - cov[rest], rig.cfg.significance)
        moved = good & ~rest
        status[idx[moved & ~intra[idx]]] = INTER
        positions[idx[moved]] = tri.points[moved]
        covariances[idx[moved]] = cov[moved]
        pose_part[idx[moved]] = cov_all[moved] - cov[moved]
        worst = np.argmax(scaled, axis=1)
        use[np.arange(len(idx)), worst] = False
        candidates, use = idx[~good], use[~good]
    return status, positions, covariances, pose_part


def _at_rest(template: TemplateData, rows: np.ndarray, points: np.ndarray,
             covariance: np.ndarray, pose_cov: np.ndarray, significance: float) -> np.ndarray:
    """(M,) bool: intra-camera inliers (template rows (M,)) whose re-triangulated points
    (M, 3) m lie where their noise puts their frame-0 positions: the displacement's
    Mahalanobis² below the chi-square bound (3 dof) at `significance`, its covariance the
    image parts (`covariance` (M, 3, 3) m² and the template's, net of the error tracking
    carries from one into the other: `displacement_covariance`) plus both pose parts
    (`pose_cov` (M, 3, 3) m² and the template's). The per-view check passes motion along
    the lines of sight of a narrow baseline (1 mm at 50 mm: ~0.4 px a view under ~0.75 px of
    pose noise, ~0.8 px of disparity); pinned at frame 0, such points registered 0.2-0.3 mm
    off in depth on the stereo simulator."""
    template_pose = template.pose_covariance[rows]
    cov = (displacement_covariance(covariance, template.covariance[rows] - template_pose)
           + pose_cov + template_pose)
    return ~significant_motion(points - template.points[rows], cov, significance)


def build_target(template: TemplateData, rig: Rig, latest: np.ndarray, base: Sighting,
                 frame: FrameInput, anchor: list[TrackingView | None] | None = None
                 ) -> TargetCloud:
    """Target cloud of `frame` for the template points (frame-0 positions and covariances),
    gated with the run's noise model `rig.noise` and each tracked pixel's localisation
    variance (core/noise/model.py; its median is the frame's tracking_px).

    latest (N, 3) m: the points' positions at the base frame, whose images, poses and
    pixels `base` holds (NaN pixel = not found there; then the projection of its latest
    position is tracked instead); `anchor`: the template's frame-0 views, against which
    the tracks are corrected and lost points re-acquired at `template.pixels`
    (core/track_points.find_points; None: tracks from the base only).
    """
    n = len(template.points)
    tracks = Tracks(*find_points(latest, base, frame, rig, anchor, template))
    found, poses = tracks.found, frame.poses
    # The bound is a floor: what the frame's re-triangulated residuals show beyond the
    # model is localisation error too (core/noise/frame_noise.py). One triangulation of the
    # points seen twice serves that and the reprojection check.
    multi = triangulate_found(found, tracks.pixels, rig.models, poses)
    excess, _ = tracking_excess_px2(multi, tracks.localisation, rig.models, rig.noise)
    # Two views see only the error that differs between them; each camera's tracks against
    # their neighbours' motion measure all of it (core/noise/frame_noise.py).
    tracking, shared = local_motion_noise_px(template.pixels, tracks.pixels, found,
                                             candidates=template.neighbours)
    if found.any() and np.isfinite(tracking):
        excess = max(excess, tracking**2 - float(np.median(tracks.localisation[found])))
    tracks.localisation[found] += excess
    if found.any():
        rig = replace(rig, noise=replace(
            rig.noise, tracking_px=float(np.sqrt(np.median(tracks.localisation[found]))),
            tracking_shared_px=shared if np.isfinite(tracking) else 0.0))
    status, positions, covariances, pose_part = reprojection_check(template, tracks, rig, poses,
                                                                   multi)
    # Tissue is pushed away by the tool, so visibility is judged in the images (mask);
    # a re-triangulated point inside the tool's capsule is a tool point, not tissue.
    on_tool = (status == INTER) & points_near_tool(
        np.nan_to_num(positions), *flatten_camera_tools(frame.seen_tools, rig.tools))
    status[on_tool] = OUTLIER
    positions[on_tool] = np.nan
    covariances[on_tool] = np.nan
    unobserved = status == UNOBSERVED
    positions[unobserved] = latest[unobserved]
    has = (status == INTRA) | (status == INTER)
    rows, cams = np.nonzero(found & (status == INTER)[:, None])
    pose_cov = body_pose_covariance(np.nan_to_num(positions), rows, cams, poses[:, :3, 3],
                                    rig.noise) + np.nan_to_num(pose_part)
    sigma = np.full(n, np.nan)
    sigma[has] = covariance_sigma(covariances[has] + pose_cov[has])
    covariances[~has] = np.nan
    return TargetCloud(positions, status, found.sum(1), tracks.pixels, covariances, pose_cov,
                       sigma, rig.noise)


def new_target_points(candidates: np.ndarray, candidate_rgb: np.ndarray, tracked: np.ndarray,
                      min_spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """New features of this frame (Su et al. 2019, Fig. 4: "feature points ... not yet
    associated with a 3D point are triangulated"): candidates (M, 3) m triangulated from the
    current images (e.g. by core/template.build_template) that lie farther than
    `min_spacing` m from every tracked template point (K, 3). Returns points and colours."""
    if len(candidates) == 0 or len(tracked) == 0:
        return candidates, candidate_rgb
    distance, _ = cKDTree(tracked).query(candidates)
    keep = distance > min_spacing
    return candidates[keep], candidate_rgb[keep]
