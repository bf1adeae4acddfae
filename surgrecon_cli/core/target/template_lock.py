"""Tracks locked to the template's own images: each track's drift is taken out by aligning
the point's frame-0 patch, warped by the local image motion, with the current image.

Tracks chained from frame to frame, or tracked straight from a base, follow a
translation-only KLT window whose patch changes with the view (perspective, rotation, scale)
and with the tissue's deformation; its error grows with every frame (measured on the
simulator against the truth, median per axis: 0.05 px at frame 1, 0.3-0.6 px at frame 11
on the `stereo` and `default` variants), and two views of a point drift alike (the same
texture changes the same way), so a stereo pair's re-triangulation cannot see it. Here the
frame-0 patch of camera c around the template pixel is resampled through the local affine
map its LOCK_NEIGHBOURS nearest tracks show (core/noise/frame_noise.LocalFits.jacobians:
the patch as the current view should see it), and the point is moved to where that patch
matches the current image best, with a gain and offset of the intensities (Gauss-Newton
on the window's sum of squares, all tracks at once). A correction is kept only where it
converged within a quarter of the window and matches the warped patch better (NCC) than
the track did. Pure OpenCV/numpy on arrays.
"""

from __future__ import annotations

import cv2
import numpy as np

from ..geometry.triangulate import spd_solve
from ..noise.frame_noise import LocalFits, PixelNeighbours
from .tracking import TrackingView, correlation

LOCK_NEIGHBOURS = 12  # ours: tracks whose affine fit gives a track's local map (patch warp)
LOCK_ITERATIONS = 8  # ours: Gauss-Newton steps at most (a drifted track converges in 3-5)
LOCK_STEP_PX = 0.05  # ours: a track whose last step is below this has converged (px)
LOCK_REACH = 0.25  # ours: a correction beyond this share of the window is not kept
MIN_AREA_RATIO = 0.25  # ours: a local map shrinking the patch more than this is not used
SHARED_BASELINE_RATIO = 0.18  # ours: cameras this close (baseline / depth) share a correction
MIN_GAIN = 0.2  # ours: a fit whose gain falls below this matched no patch (not kept)
LOCK_STRIDE = 2  # ours: every 2nd pixel of the window is compared (a quarter of the cost)
REMAP_ROWS = 16_384  # cv2.remap takes maps of fewer than 32,767 rows: sampled in chunks


def patch_offsets(window_px: int, stride: int = 1) -> np.ndarray:
    """Offsets (P, 2) px about its centre of every stride-th pixel of a window_px x window_px
    patch."""
    half = window_px // 2 // stride
    steps = stride * np.arange(-half, half + 1, dtype=np.float32)
    u, v = np.meshgrid(steps, steps)
    return np.column_stack([u.ravel(), v.ravel()])


def sample_patches(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear samples (M, P) float32 of image (H, W) float32 at pixels (x, y) (each
    (M, P) px), or (M, P, K) of an image (H, W, K)."""
    if not len(x):
        return np.empty(x.shape + image.shape[2:], np.float32)
    map_x, map_y = x.astype(np.float32, copy=False), y.astype(np.float32, copy=False)
    parts = [cv2.remap(image, map_x[start:start + REMAP_ROWS], map_y[start:start + REMAP_ROWS],
                       cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
             for start in range(0, len(map_x), REMAP_ROWS)]
    return parts[0] if len(parts) == 1 else np.concatenate(parts)


def _inside(pixels: np.ndarray, shape: tuple[int, ...], margin: float | np.ndarray
            ) -> np.ndarray:
    """(M,) bool: pixels (M, 2) at least `margin` px (scalar or (M,)) inside an image of
    shape (H, W)."""
    h, w = shape[:2]
    return ((pixels[:, 0] >= margin) & (pixels[:, 1] >= margin)
            & (pixels[:, 0] <= w - 1 - margin) & (pixels[:, 1] <= h - 1 - margin))


def inverse2(maps: np.ndarray) -> np.ndarray:
    """Inverses (M, 2, 2) of 2x2 matrices maps (M, 2, 2) in closed form (the adjugate over
    the determinant; LAPACK's batched inverse costs ~7x as much); not finite where singular."""
    a, b, c, d = maps[:, 0, 0], maps[:, 0, 1], maps[:, 1, 0], maps[:, 1, 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.stack([d, -b, -c, a], 1).reshape(-1, 2, 2) / (a * d - b * c)[:, None, None]


def template_patches(anchor: TrackingView, centres: np.ndarray, maps: np.ndarray,
                     offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The patches T, ∂T/∂x, ∂T/∂y (each (M, P)) of the anchor's image at `offsets` (P, 2)
    px about centres (M, 2) px, resampled through the local maps A (M, 2, 2) (∂ current /
    ∂ anchor): the patch as a view the maps lead to sees it, T(o) = I₀(c + A⁻¹ o), and its
    gradient in that view's pixels, A⁻ᵀ ∇I₀ (`TrackingView.gradients`)."""
    inv = inverse2(maps).astype(np.float32)
    back = np.matmul(offsets[None], inv.transpose(0, 2, 1))
    at = centres.astype(np.float32)
    samples = sample_patches(anchor.gradients, at[:, :1] + back[..., 0], at[:, 1:] + back[..., 1])
    patch, gx, gy = samples[..., 0], samples[..., 1], samples[..., 2]
    dx = inv[:, 0, 0, None] * gx + inv[:, 1, 0, None] * gy
    dy = inv[:, 0, 1, None] * gx + inv[:, 1, 1, None] * gy
    return patch, dx, dy


def align_patches(template: tuple[np.ndarray, np.ndarray, np.ndarray], image: np.ndarray,
                  pixels: np.ndarray, offsets: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray]]:
    """Where the patches template = (T, ∂T/∂x, ∂T/∂y) (each (M, P), samples at `offsets`
    (P, 2) px about their centre) match image (H, W) float32 best, starting at pixels
    (M, 2) px: Gauss-Newton on Σ (I(x + d + o) - a T(o) - b)² over the shift d, gain a and
    offset b, with the template's gradients (inverse compositional: I's gradient is a ∇T
    where they match, so the normal equations are set up once per patch, and with u = a δ
    each step is linear). Returns the shifts (M, 2) px, whether each converged (its last
    step under LOCK_STEP_PX, a positive gain), each patch's NCC with the image at the start
    and, for the converged ones (NaN elsewhere: the others are not kept, so it is not
    computed), at its last step (each (M,))."""
    patch, dx, dy = template
    design = np.stack([dx, dy, -patch, -np.ones_like(patch)], 1)  # (M, 4, P)
    normal = np.matmul(design, design.transpose(0, 2, 1)).astype(float)
    normal += (1e-6 * np.trace(normal, axis1=1, axis2=2) + 1e-9)[:, None, None] * np.eye(4)
    solver = spd_solve(normal, np.broadcast_to(np.eye(4), normal.shape))  # its inverse
    shift = np.zeros(pixels.shape)
    start_ncc = np.full(len(pixels), -1.0)
    end_ncc = np.full(len(pixels), np.nan)
    active = np.arange(len(pixels))
    converged = np.zeros(len(pixels), bool)
    for iteration in range(LOCK_ITERATIONS):
        if not len(active):
            break
        at = pixels[active] + shift[active]
        values = sample_patches(image, at[:, :1] + offsets[:, 0], at[:, 1:] + offsets[:, 1])
        if iteration == 0:  # every patch is active
            start_ncc = correlation(values, patch)
        fit = -np.matmul(solver[active], np.matmul(design[active], values[..., None]))[..., 0]
        gain = fit[:, 2]
        valid = gain > MIN_GAIN
        step = fit[:, :2] / np.where(valid, gain, 1.0)[:, None]
        shift[active[valid]] += step[valid]
        done = valid & (np.abs(step) < LOCK_STEP_PX).all(1)
        converged[active[done]] = True
        end_ncc[active[done]] = (start_ncc[done] if iteration == 0
                                 else correlation(values[done], patch[active[done]]))
        active = active[valid & ~done]
    return shift, converged, (start_ncc, end_ncc)


def lock_to_template(anchor: TrackingView, view: TrackingView, anchor_pixels: np.ndarray,
                     pixels: np.ndarray, window_px: int,
                     candidates: PixelNeighbours | None = None) -> np.ndarray:
    """The corrections (M, 2) px that take the drift out of one camera's tracked pixels
    (M, 2) (NaN = not found) against the template's image of that camera (module
    docstring): anchor_pixels (M, 2) px where the points were at frame 0 in `anchor` (NaN =
    not seen there), `view` the current image. NaN for tracks with too few neighbours
    (LOCK_NEIGHBOURS), no frame-0 pixel, a window leaving either image, or a correction
    not kept. candidates: `PixelNeighbours.of(anchor_pixels)` (None: the local maps'
    neighbours are queried)."""
    out = np.asarray(pixels, float)
    correction = np.full(out.shape, np.nan)
    rows = np.flatnonzero(np.isfinite(out).all(1) & np.isfinite(anchor_pixels).all(1))
    if len(rows) <= LOCK_NEIGHBOURS:
        return correction
    nearest = None if candidates is None else candidates.among(rows, anchor_pixels,
                                                               LOCK_NEIGHBOURS)
    jac = LocalFits.of(anchor_pixels[rows], out[rows], LOCK_NEIGHBOURS, quadratic=False,
                       nearest=nearest).jacobians()
    det = np.nan_to_num(jac[:, 0, 0] * jac[:, 1, 1] - jac[:, 0, 1] * jac[:, 1, 0])
    offsets = patch_offsets(window_px, LOCK_STRIDE)
    reach = float(np.abs(offsets).max())
    usable = ((det >= MIN_AREA_RATIO) & (det <= 1.0 / MIN_AREA_RATIO)
              & _inside(out[rows], view.grey_f32.shape, reach + 1.0))
    rows, jac = rows[usable], jac[usable]
    footprint = reach * np.abs(inverse2(jac)).sum(2).max(1)  # frame-0 patch half-size
    inside = _inside(anchor_pixels[rows], anchor.grey_f32.shape, footprint + 2.0)
    rows, jac = rows[inside], jac[inside]
    if not len(rows):
        return correction
    template = template_patches(anchor, anchor_pixels[rows], jac, offsets)
    start = out[rows]
    shift, converged, (start_ncc, end_ncc) = align_patches(template, view.grey_f32, start,
                                                           offsets)
    moved = start + shift
    keep = converged & (np.linalg.norm(shift, axis=1) <= LOCK_REACH * window_px)
    keep &= _inside(np.where(keep[:, None], moved, start), view.grey_f32.shape, reach + 1.0)
    keep &= end_ncc >= start_ncc
    correction[rows[keep]] = shift[keep]
    return correction


def lock_groups(centres: np.ndarray, points: np.ndarray) -> list[np.ndarray]:
    """Cameras (C,) that see the points from nearly one viewpoint, grouped: camera centres
    (C, 3) m (NaN: unusable) and points (N, 3) m (NaN ignored); two cameras whose baseline
    is at most SHARED_BASELINE_RATIO of the points' median distance from them (a stereo
    endoscope: ~0.06) are in one group, and groups are joined through shared members. Every
    usable camera is in exactly one group."""
    usable = np.flatnonzero(np.isfinite(centres).all(1))
    label = np.arange(len(centres))
    pts = points[np.isfinite(points).all(1)]
    if len(pts):
        for i, a in enumerate(usable):
            for b in usable[i + 1:]:
                depth = np.median(np.linalg.norm(pts - (centres[a] + centres[b]) / 2, axis=1))
                if np.linalg.norm(centres[a] - centres[b]) <= SHARED_BASELINE_RATIO * depth:
                    label[label == label[b]] = label[a]
    return [usable[label[usable] == g] for g in np.unique(label[usable])]


def shared_drift(drift: np.ndarray, groups: list[np.ndarray]) -> np.ndarray:
    """The corrections (N, C, 2) px to apply: within each group of cameras (`lock_groups`)
    every view of a point gets the mean of its views' corrections drift (N, C, 2)
    (`lock_to_template`; NaN: none). A narrow stereo pair's KLT tracks drift alike in both
    views, so their disparity (its depth) is better than either track; locked one by one,
    each view gets its own alignment error (on the real SurgT pair at 360x288 ~0.03 px
    each, ~0.1 mm of depth), so the pair's views share one correction, which takes out the
    common drift and keeps the disparity. Views of a point without any correction in their
    group get 0."""
    out = np.zeros(drift.shape)
    for group in groups:
        part = drift[:, group]
        have = np.isfinite(part).all(2)
        count = have.sum(1)
        mean = np.where(have[..., None], part, 0.0).sum(1) / np.maximum(count, 1)[:, None]
        out[:, group] = np.where((count > 0)[:, None, None], mean[:, None, :], 0.0)
    return out

