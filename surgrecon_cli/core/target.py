"""Target cloud G of a frame (Su et al. 2019, section II.B, Fig. 4).

Template points are projected at their latest positions into the new images (visibility:
in front, inside the image, not occluded, outside the tool mask), found there by pyramidal
KLT from the same camera's image at a reference frame (the pipeline uses the template's
base frame, so that frames do not depend on each other; forward-backward checked), then
sorted by the reprojection-error check (CoSLAM's form):
- intra-camera inlier: the point's frame-0 position still reprojects within `gate_px` in
  every camera that sees it -> static evidence, target = frame-0 position;
- inter-camera inlier: seen by >= 2 cameras and re-triangulated with every view within the
  gate -> dynamic, target = new position;
- outlier: anything else (a point seen by one camera cannot be confirmed dynamic);
- unobserved: not visible now -> kept at its latest position, no data weight.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

from ..config import TargetConfig, ToolConfig
from .cameras import CameraModel, in_image, project, undistort_pixels
from .labels import INTER, INTRA, OUTLIER, STATUS_NAMES, UNOBSERVED
from .tool import points_near_tool, tool_pixel_mask
from .triangulate import Observations, triangulate


@dataclass(frozen=True)
class TargetCloud:
    """Per template point (N): target position (N, 3) m (latest position if unobserved, NaN
    for outliers), status (N,) uint8 (INTRA/INTER/OUTLIER/UNOBSERVED), views (N,) cameras
    that found it; pixels (N, C, 2) where it was found in each camera (NaN = not found)."""

    positions: np.ndarray
    status: np.ndarray
    views: np.ndarray
    pixels: np.ndarray

    def counts(self) -> dict[str, int]:
        return {name: int((self.status == code).sum()) for code, name in STATUS_NAMES.items()}


def visible_points(
    points: np.ndarray,
    camera: CameraModel,
    pose: np.ndarray,
    occlusion_depth: float,
    cell_px: int = 8,
    border: float = 8.0,
):
    """Predicted pixels (N, 2) and visibility (N,) of points in one camera: in front, inside
    the image (with a KLT border), and not behind other points of the cloud (a z-buffer on
    `cell_px` cells, tolerance `occlusion_depth` m)."""
    uv, z = project(points, pose, camera)
    ok = (z > 0) & in_image(uv, camera, border) & np.isfinite(points).all(1)
    cells_x = camera.width // cell_px + 1
    cell = np.full(len(points), -1)
    cell[ok] = (uv[ok, 1] // cell_px).astype(int) * cells_x + (uv[ok, 0] // cell_px).astype(int)
    zbuf = np.full(cells_x * (camera.height // cell_px + 1), np.inf)
    np.minimum.at(zbuf, cell[ok], z[ok])
    ok[ok] &= z[ok] <= zbuf[cell[ok]] + occlusion_depth
    return uv, ok


def _gray(image: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)


def klt_track(
    prev_gray: np.ndarray,
    cur_gray: np.ndarray,
    start: np.ndarray,
    guess: np.ndarray,
    cfg: TargetConfig,
) -> tuple[np.ndarray, np.ndarray]:
    """Track pixels (M, 2) from prev to cur starting from `guess`; forward-backward checked.
    Returns tracked pixels (M, 2) and ok (M,)."""
    if len(start) == 0:
        return np.zeros((0, 2)), np.zeros(0, bool)
    params = dict(
        winSize=(cfg.klt_window_px, cfg.klt_window_px),
        maxLevel=cfg.klt_levels,
        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01),
    )
    p0 = start.astype(np.float32).reshape(-1, 1, 2)
    p1 = guess.astype(np.float32).reshape(-1, 1, 2).copy()
    p1, st1, _ = cv2.calcOpticalFlowPyrLK(
        prev_gray, cur_gray, p0, p1, flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **params
    )
    back = p0.copy()
    back, st2, _ = cv2.calcOpticalFlowPyrLK(
        cur_gray, prev_gray, p1, back, flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **params
    )
    fb = np.linalg.norm((back - p0).reshape(-1, 2), axis=1)
    ok = (st1.ravel() == 1) & (st2.ravel() == 1) & (fb <= cfg.klt_fb_px)
    return p1.reshape(-1, 2).astype(np.float64), ok


def _reprojection_errors(
    points: np.ndarray,
    found: np.ndarray,
    pixels: np.ndarray,
    models: list[CameraModel],
    poses: np.ndarray,
) -> np.ndarray:
    """Error (N, C) px of points (N, 3) against found pixels (N, C, 2); inf where not found."""
    err = np.full(found.shape, np.inf)
    for c in range(found.shape[1]):
        sel = found[:, c]
        if sel.any():
            uv, z = project(points[sel], poses[c], models[c])
            e = np.linalg.norm(uv - pixels[sel, c], axis=1)
            err[sel, c] = np.where(z > 0, e, np.inf)
    return err


def reprojection_check(
    template: np.ndarray,
    found: np.ndarray,
    pixels: np.ndarray,
    models: list[CameraModel],
    poses: np.ndarray,
    gate_px: float,
):
    """Split points by the reprojection-error check. found (N, C) bool, pixels (N, C, 2).

    Returns status (N,) and positions (N, 3) (template position for intra, re-triangulated
    for inter, NaN otherwise).
    """
    n, _n_cams = found.shape
    views = found.sum(1)
    status = np.full(n, OUTLIER, np.uint8)
    status[views == 0] = UNOBSERVED
    positions = np.full((n, 3), np.nan)
    err0 = _reprojection_errors(template, found, pixels, models, poses)
    intra = (views > 0) & np.all(np.where(found, err0 <= gate_px, True), axis=1)
    status[intra] = INTRA
    positions[intra] = template[intra]
    candidates = np.flatnonzero(~intra & (views >= 2))
    use = found[candidates].copy()
    for _attempt in range(2):  # second attempt without each point's worst view
        keep = use.sum(1) >= 2
        idx, use = candidates[keep], use[keep]
        if len(idx) == 0:
            break
        rows, cams = np.nonzero(use)
        px = pixels[idx[rows], cams]
        normalized = np.zeros_like(px)
        for c in np.unique(cams):
            normalized[cams == c] = undistort_pixels(px[cams == c], models[c])
        obs = Observations(rows, cams, px, normalized, np.zeros((len(rows), 3), np.uint8))
        tri = triangulate(obs, poses, models, len(idx))
        err = np.full(use.shape, -np.inf)
        err[rows, cams] = tri.error_px
        good = tri.in_front & (tri.max_error_px <= gate_px) & np.isfinite(tri.points).all(1)
        status[idx[good]] = INTER
        positions[idx[good]] = tri.points[good]
        worst = np.argmax(err, axis=1)
        use[np.arange(len(idx)), worst] = False
        candidates, use = idx[~good], use[~good]
    return status, positions


def build_target(
    template: np.ndarray,
    latest: np.ndarray,
    prev_images: list[np.ndarray | None],
    cur_images: list[np.ndarray | None],
    prev_poses: np.ndarray,
    cur_poses: np.ndarray,
    prev_pixels: np.ndarray,
    models: list[CameraModel],
    tool_pose: np.ndarray,
    cfg: TargetConfig,
    tool_cfg: ToolConfig,
) -> TargetCloud:
    """Target cloud of a frame for template points (N, 3) at frame 0 and latest positions.

    prev_images/cur_images: per camera RGB (H, W, 3) uint8 or None, "prev" being the frame
    tracked from (any earlier frame: the pipeline passes the template base); poses (C, 4, 4)
    with NaN where unusable; prev_pixels (N, C, 2): where each point was found in that frame
    (NaN = not found; then its projection is tracked instead); latest (N, 3) m: positions
    at that frame.
    """
    n, n_cams = len(template), len(models)
    pixels = np.full((n, n_cams, 2), np.nan)
    found = np.zeros((n, n_cams), bool)
    for c in range(n_cams):
        if cur_images[c] is None or prev_images[c] is None:
            continue
        guess, visible = visible_points(latest, models[c], cur_poses[c], cfg.occlusion_depth)
        start = prev_pixels[:, c].copy()
        missing = ~np.isfinite(start).all(1)
        if missing.any() and np.isfinite(prev_poses[c]).all():
            start[missing] = project(latest[missing], prev_poses[c], models[c])[0]
        visible &= np.isfinite(start).all(1) & in_image(start, models[c], 8.0)
        idx = np.flatnonzero(visible)
        tracked, ok = klt_track(
            _gray(prev_images[c]), _gray(cur_images[c]), start[idx], guess[idx], cfg
        )
        ok &= in_image(tracked, models[c], 2.0)
        ok &= ~tool_pixel_mask(tracked, models[c], cur_poses[c], tool_pose, tool_cfg)
        pixels[idx[ok], c] = tracked[ok]
        found[idx[ok], c] = True
    status, positions = reprojection_check(template, found, pixels, models, cur_poses, cfg.gate_px)
    # Tissue is pushed away by the tool, so visibility is judged in the images (mask);
    # a re-triangulated point inside the tool's capsule is a tool point, not tissue.
    on_tool = (status == INTER) & points_near_tool(np.nan_to_num(positions), tool_pose, tool_cfg)
    status[on_tool] = OUTLIER
    positions[on_tool] = np.nan
    unobserved = status == UNOBSERVED
    positions[unobserved] = latest[unobserved]
    return TargetCloud(positions, status, found.sum(1), pixels)


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
