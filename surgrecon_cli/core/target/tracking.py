"""Pyramidal KLT tracking of template points between two images of one camera, checked
forward-backward and photometrically (Su et al. 2019, section II.B: the target cloud's
2D tracks). Pure OpenCV/numpy on arrays."""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import cached_property
from typing import Any

import cv2
import numpy as np
from scipy.spatial import cKDTree

from ...config import TargetConfig
from ..noise.model import image_noise_sigma

NCC_PATCH_PX = 9  # ours: side of the patch compared after tracking (px)
PILOT_STRIDE = 8  # ours: an unknown motion is measured on every 8th point (~12 %) ...
PILOT_EXTRA_LEVELS = 1  # ... one pyramid level deeper than the tracks (twice the reach)
PILOT_ENOUGH = 0.9  # ours: a prior whose pilots track this share is used without the other's
SHADING_SIGMA_PX = 6.0  # ours: shading scale removed before tracking (px), ~ half a KLT window
SHADING_DOWNSCALE = 4  # the shading is measured at 1/4 resolution (`shading`)
SPECULAR_VALUE = 235  # ours: a pixel this bright (max of RGB, of 255) ...
SPECULAR_CHROMA = 40  # ... with max - min of RGB at most this is a saturated highlight
SPECULAR_MARGIN_PX = 4  # ours: a track this close to a highlight is not trusted (px)
MIN_MOTION_FIT = 6  # pilot tracks needed to fit the image motion (a 2D similarity)
NEIGHBOUR_TRACKS = 8  # ours: tracked neighbours whose median flow predicts a lost track
NEIGHBOUR_RADIUS_PX = 48.0  # ours: ... found within this distance (px, in the start image)
NEIGHBOUR_ROUNDS = 2  # ours: rounds of that prediction (each reaches one ring further in)
CROP_SHARE = 0.5  # KLT on crops of the images when they cover at most this share of them
CROP_SAVES_PX = 400_000  # ... and spare at least this many pixels of each (`klt_crops`)


def tracking_image(image: np.ndarray) -> np.ndarray:
    """The image KLT tracks: grey with the slowly varying shading removed (grey minus its
    Gaussian blur, re-centred on 128). Tissue that tilts under the tool changes its shading
    over a KLT window; brightness constancy then fails the same way in every view, and the
    tracks slide consistently (measured: dent targets 0.3-0.5 mm off with a 0.1 mm sigma)."""
    return shading_removed(cv2.cvtColor(image, cv2.COLOR_RGB2GRAY))


def shading_removed(grey: np.ndarray) -> np.ndarray:
    """`tracking_image` of the image whose grey (H, W) uint8 (cv2's RGB2GRAY) is `grey`."""
    return cv2.addWeighted(grey, 2.0, shading(grey), -2.0, 128.0, dtype=cv2.CV_8U)


def shading(grey: np.ndarray) -> np.ndarray:
    """The slowly varying shading of a grey image (H, W) uint8, float32 (H, W): its Gaussian
    blur at SHADING_SIGMA_PX, computed at a quarter of the resolution (area-averaged down,
    blurred there, bilinear up: ~40x cheaper than the full-size blur; the three together
    make a blur of nearly the same width, the 4x4 area (σ 1.1 px) and bilinear (σ 1.6 px)
    adding in quadrature to the blur's)."""
    h, w = grey.shape
    if min(h, w) < 4 * SHADING_DOWNSCALE:
        return cv2.GaussianBlur(grey.astype(np.float32), (0, 0), SHADING_SIGMA_PX)
    small = cv2.resize(grey, (w // SHADING_DOWNSCALE, h // SHADING_DOWNSCALE),
                       interpolation=cv2.INTER_AREA).astype(np.float32)
    sigma = float(np.sqrt(SHADING_SIGMA_PX**2 - 2.0**2)) / SHADING_DOWNSCALE
    blurred = cv2.GaussianBlur(small, (0, 0), sigma)
    return cv2.resize(blurred, (w, h), interpolation=cv2.INTER_LINEAR)


@dataclass(frozen=True)
class TrackingView:
    """One camera image prepared for tracking, built once and shared by every frame tracked
    from or into it: grey (H, W) uint8 (`tracking_image`), its float32 copy (patches) and
    the image's intensity noise σ_I (grey levels, core/noise.image_noise_sigma). (The KLT
    pyramid itself cannot be kept: OpenCV's Python binding of calcOpticalFlowPyrLK takes
    images only, not the output of buildOpticalFlowPyramid.)"""

    grey: np.ndarray
    grey_f32: np.ndarray
    noise_sigma: float
    specular: np.ndarray

    @cached_property
    def gradients(self) -> np.ndarray:
        """(H, W, 3) float32: the image and its x and y gradients (central differences),
        built when first asked for (a template's views, core/target/template_lock.py)."""
        grey = self.grey_f32
        dx = cv2.Sobel(grey, cv2.CV_32F, 1, 0, ksize=1, scale=0.5)
        dy = cv2.Sobel(grey, cv2.CV_32F, 0, 1, ksize=1, scale=0.5)
        return cv2.merge([grey, dx, dy])

    @cached_property
    def has_specular(self) -> bool:
        """Whether `specular` marks any pixel (an image without highlights: no track is
        refused for one, `on_specular`)."""
        return bool(self.specular.any())


def specular_mask(image: np.ndarray, grey: np.ndarray | None = None) -> np.ndarray:
    """Saturated specular highlights of an RGB image (H, W, 3) uint8: near-white pixels of
    low chroma (max of RGB >= SPECULAR_VALUE, max - min <= SPECULAR_CHROMA), (H, W) bool.
    A highlight moves with the light, not with the tissue: a KLT window on it follows the
    light. grey: the image's grey (H, W) uint8 (cv2's RGB2GRAY), if at hand: a highlight's
    channels are all at least SPECULAR_VALUE - SPECULAR_CHROMA, so is their weighted mean,
    and only the rows between the first and last grey pixel that bright are examined (the
    same mask)."""
    if grey is not None:
        rows = _rows_reaching(grey, SPECULAR_VALUE - SPECULAR_CHROMA)
        mask = np.zeros(grey.shape, bool)
        if len(rows):
            band = slice(rows[0], rows[-1] + 1)
            mask[band] = specular_mask(image[band])
        return mask
    r, g, b = cv2.split(image)  # per-pixel max / min of 3 channels: ~50x numpy's reduce
    top = cv2.max(cv2.max(r, g), b)
    bright = top >= SPECULAR_VALUE
    if not bright.any():  # no near-white pixel: the chroma is not needed
        return bright
    chroma = cv2.subtract(top, cv2.min(cv2.min(r, g), b))
    return bright & (chroma <= SPECULAR_CHROMA)


def specular_zone(highlight: np.ndarray) -> np.ndarray:
    """Highlights (H, W) bool grown by SPECULAR_MARGIN_PX: where a feature or track is not
    trusted (its window is dominated by the highlight's edges)."""
    rows = _rows_reaching(highlight.view(np.uint8), 1)
    grown = np.zeros(highlight.shape, bool)
    if not len(rows):
        return grown
    # only the rows within the margin of a highlight's (the same zone)
    band = slice(max(rows[0] - SPECULAR_MARGIN_PX, 0), rows[-1] + SPECULAR_MARGIN_PX + 1)
    side = 2 * SPECULAR_MARGIN_PX + 1
    grown[band] = cv2.dilate(highlight[band].view(np.uint8), np.ones((side, side), np.uint8)) > 0
    return grown


def _rows_reaching(image: np.ndarray, level: int) -> np.ndarray:
    """The rows (K,) of image (H, W) uint8 holding a value of at least `level`, ascending
    (each row's maximum by cv2.reduce: ~10x numpy's)."""
    return np.flatnonzero(cv2.reduce(image, 1, cv2.REDUCE_MAX).ravel() >= level)


def tracking_view(image: np.ndarray) -> TrackingView:
    """The `TrackingView` of an RGB image (H, W, 3) uint8: highlights (`specular_mask`) are
    set to the neutral grey 128 of `tracking_image`, and `specular` (H, W) bool marks them
    grown (`specular_zone`), where tracks are refused."""
    plain = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    grey = shading_removed(plain)
    highlight = specular_mask(image, plain)
    grey[highlight] = 128
    grey.flags.writeable = False  # shared by every frame tracked from this image
    grey_f32 = grey.astype(np.float32)
    grey_f32.flags.writeable = False
    grown = specular_zone(highlight)
    grown.flags.writeable = False
    return TrackingView(grey, grey_f32, image_noise_sigma(grey), grown)


def on_specular(view: TrackingView, pixels: np.ndarray) -> np.ndarray:
    """Whether pixels (M, 2) (finite) lie on or next to a highlight of `view`, (M,) bool."""
    if not view.has_specular:
        return np.zeros(len(pixels), bool)
    h, w = view.specular.shape
    col = np.clip(np.rint(pixels[:, 0]).astype(int), 0, w - 1)
    row = np.clip(np.rint(pixels[:, 1]).astype(int), 0, h - 1)
    return view.specular[row, col]


def klt_levels_for(motion_px: float, window_px: int, max_levels: int) -> int:
    """Pyramid levels above the image that KLT needs to bridge `motion_px` px between its
    initial guess and the truth: the Lucas-Kanade iteration at level l is trusted within a
    quarter window there (ours: half the window's half-width, where the linearisation of a
    textured patch still points the right way), i.e. (w / 4) 2^l px of the image; the
    smallest such l, capped at `max_levels` (also for an unknown, non-finite motion)."""
    if not np.isfinite(motion_px):
        return max_levels
    reach = window_px / 4.0
    return int(min(max_levels, max(0, np.ceil(np.log2(max(motion_px, 1e-9) / reach)))))


def klt_crops(start: np.ndarray, guess: np.ndarray, shape: tuple[int, ...], levels: int,
              window: int) -> tuple[tuple[int, int], tuple[int, int], tuple[int, int]] | None:
    """Equal-sized crops of two images (H, W) that hold what pyramidal KLT with `levels`
    levels above the image and a `window` px window reads around pixels start (M, 2) in
    the first and guess (M, 2) in the second: (x, y) offsets of each crop and their common
    (width, height); None when they would cover more than CROP_SHARE of the image or spare
    fewer than CROP_SAVES_PX pixels. Offsets are multiples of 2^levels, so every pyramid
    level of a crop is the same pixels as the image's; a margin of (window + 1) 2^levels
    px around the points holds each level's window, the motion it may find there (a
    quarter window) and the few pixels each level's border reflection reaches inward.
    OpenCV's Python binding builds both pyramids in every call: on a 1280x1024 image that
    is 1-2 ms a call whatever the number of points, on a 640x512 one 0.2-0.5 ms. (The
    tracks are the image's up to float32 rounding of the shifted coordinates: measured on
    the 1280x1024 simulator, 2-4 of ~1,300 converged tracks differ, by at most 0.04 px; so
    crops are used only where they spare a large image's pyramids.)"""
    h, w = shape[:2]
    if w * h < CROP_SAVES_PX:  # nothing to spare
        return None
    step = 2**levels
    margin = (window + 1) * step
    lo = np.minimum(np.floor(np.vstack([start.min(0), guess.min(0)]) - margin), [w, h])
    hi = np.maximum(np.ceil(np.vstack([start.max(0), guess.max(0)]) + margin), 0)
    lo = np.maximum(lo, 0).astype(int) // step * step  # rows: the two images; columns x, y
    hi = np.minimum(hi, [w, h]).astype(int)
    size = -(-(hi - lo).max(0) // step) * step + step  # one step of slack for the edges
    area = size[0] * size[1]
    if area > CROP_SHARE * w * h or w * h - area < CROP_SAVES_PX or (size >= [w, h]).any():
        return None
    limit = (np.array([w, h]) - size) // step * step
    lo = np.minimum(lo, limit)  # inside the image, still on the 2^levels grid
    return (int(lo[0, 0]), int(lo[0, 1])), (int(lo[1, 0]), int(lo[1, 1])), (
        int(size[0]), int(size[1]))


def _pyr_lk(prev: np.ndarray, cur: np.ndarray, p0: np.ndarray, p1: np.ndarray,
            params: dict[str, Any], only: np.ndarray | None = None
            ) -> tuple[np.ndarray, np.ndarray]:
    """cv2.calcOpticalFlowPyrLK from p0 (M, 1, 2) float32 in prev to the initial p1 in cur
    (images (H, W) uint8), on crops of both (`klt_crops`) where they pay: tracked (M, 1, 2)
    float32 and status (M, 1). `only` (M,) bool: only those K points are tracked (K, 1, 2),
    status (K, 1), on the crops all M would take (the same tracks as tracking all M)."""
    crop = klt_crops(p0.reshape(-1, 2), p1.reshape(-1, 2), prev.shape, params["maxLevel"],
                     params["winSize"][0])
    if only is not None:
        p0, p1 = p0[only], p1[only]
    if crop is None:
        out, status, _ = cv2.calcOpticalFlowPyrLK(prev, cur, p0, p1, **params)
        return out, status
    (ax, ay), (bx, by), (cw, ch) = crop
    at, to = np.array([ax, ay], np.float32), np.array([bx, by], np.float32)
    out, status, _ = cv2.calcOpticalFlowPyrLK(
        prev[ay:ay + ch, ax:ax + cw], cur[by:by + ch, bx:bx + cw], p0 - at, p1 - to, **params)
    return out + to, status


def klt_track(
    prev: TrackingView,
    cur: TrackingView,
    start: np.ndarray,
    guess: np.ndarray,
    cfg: TargetConfig,
    levels: int | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Track pixels (M, 2) from prev to cur starting from `guess`, with `levels` pyramid
    levels above the image (None: `cfg.klt_levels`), forward-backward checked (within
    `cfg.klt_fb_px`; measured: forward only, with the multi-view reprojection check
    standing in, let the registration p95 grow 6 % on unseen simulated seeds),
    photometrically checked (`patch_ncc` at least `cfg.min_ncc`) and off highlights.
    Returns tracked pixels (M, 2) and ok (M,)."""
    if len(start) == 0:
        return np.zeros((0, 2)), np.zeros(0, bool)
    params: dict[str, Any] = dict(
        winSize=(cfg.klt_window_px, cfg.klt_window_px),
        maxLevel=cfg.klt_levels if levels is None else levels,
        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01),
        flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
    )
    p0 = start.astype(np.float32).reshape(-1, 1, 2)
    p1: np.ndarray = guess.astype(np.float32).reshape(-1, 1, 2).copy()
    # The cheap checks first, KLT only for the points that may pass them: a start on a
    # highlight fails whatever the track (it keeps its guess), and the backward pass (as
    # costly as the forward one) runs only for the forward tracks that pass the highlight
    # and patch checks (most lost tracks fail the patch check). Each point is tracked
    # alone, on the crops of the points of its direction's full pass (forward: all M;
    # backward: every track found forward): the same tracks pass as in any order.
    moved = ~on_specular(prev, start)
    if moved.any():
        p1[moved], st1 = _pyr_lk(prev.grey, cur.grey, p0, p1, params, moved)
        moved[moved] = st1.ravel() == 1
    tracked = p1.reshape(-1, 2).astype(np.float64)
    ok = moved.copy()
    ok[ok] &= ~on_specular(cur, tracked[ok])
    ok[ok] &= patch_ncc(prev.grey_f32, start[ok], cur.grey_f32, tracked[ok],
                        NCC_PATCH_PX) >= cfg.min_ncc
    if ok.any():  # backward, from the forward tracks that passed the checks
        back, st2 = _pyr_lk(cur.grey, prev.grey, p1[moved], p0[moved].copy(), params,
                            ok[moved])
        fb = np.linalg.norm((back - p0[ok]).reshape(-1, 2), axis=1)
        ok[ok] = (st2.ravel() == 1) & (fb <= cfg.klt_fb_px)
    return tracked, ok


def expected_motion_px(moved: np.ndarray) -> float:
    """The motion (px) KLT should expect between a guess and the truth, from the distances
    (K,) px of tracks found so far in this frame: twice their 95th percentile (NaN when
    there are none: unknown)."""
    return float(2.0 * np.percentile(moved, 95)) if len(moved) else float("nan")


def image_motion(source: np.ndarray, moved: np.ndarray, fit_px: float = 2.0,
                 min_inliers: int = MIN_MOTION_FIT) -> np.ndarray | None:
    """The image motion of a camera as a 2D similarity (2, 3) fitted robustly (RANSAC,
    inliers within `fit_px` px) to pixels source (K, 2) found at moved (K, 2); None with
    fewer than `min_inliers` pairs agreeing on it. A camera sweeping over a distant surface
    moves its image nearly as one similarity; the fit predicts where the other points went."""
    if len(source) < min_inliers:
        return None
    fit, inliers = cv2.estimateAffinePartial2D(
        source.astype(np.float32), moved.astype(np.float32), method=cv2.RANSAC,
        ransacReprojThreshold=fit_px)
    if fit is None or inliers is None or int(inliers.sum()) < min_inliers:
        return None
    return np.asarray(fit, float)


def apply_motion(motion: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """Pixels (M, 2) moved by an image motion (2, 3) (`image_motion`)."""
    return pixels @ motion[:, :2].T + motion[:, 2]


@dataclass(frozen=True)
class TrackPrior:
    """Where M tracks are expected in the current image (`track_adaptive`): guess (M, 2) px,
    the motion to expect from it motion_px px (NaN = unknown) and alternative (M, 2) px
    other guesses (or None)."""

    guess: np.ndarray
    motion_px: float = float("nan")
    alternative: np.ndarray | None = None


def track_adaptive(prev: TrackingView, cur: TrackingView, start: np.ndarray,
                   prior: TrackPrior, cfg: TargetConfig
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`klt_track` from `start` (M, 2) px with `prior`'s guesses (`track_first`), the
    failed tracks tracked again from their neighbours' flow (`retrack_from_neighbours`).
    Returns tracked (M, 2), ok (M,) and each track's distance from its (corrected) guess
    (M,) px (NaN where not ok)."""
    tracked, ok, guess = track_first(prev, cur, start, prior, cfg)
    tracked, ok = retrack_from_neighbours((prev, cur), start, guess, (tracked, ok), cfg)
    moved = np.linalg.norm(tracked - guess, axis=1)
    return tracked, ok, np.where(ok, moved, np.nan)


def track_first(prev: TrackingView, cur: TrackingView, start: np.ndarray, prior: TrackPrior,
                cfg: TargetConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`klt_track` from `start` (M, 2) px with `prior`'s guesses, the pyramid depth chosen
    for its expected motion `motion_px` px (`klt_levels_for`); a track that moved from its
    guess farther than that depth reaches has slid and is failed. The failed ones are left
    to the neighbour retries (`retrack_from_neighbours`, at full depth; a full-depth pass
    of them from their own guesses before the retries found 0.05 % more tracks on the
    5-camera frame-cost log, for ~17 ms of KLT a frame; a camera whose guesses were wrong
    as a whole is piloted instead, core/target/track_points._chain).
    An unknown motion (NaN) is measured first on every PILOT_STRIDE-th point, tracked
    PILOT_EXTRA_LEVELS deeper than the full depth: the guesses are corrected by the image
    motion those pilot tracks show (`image_motion`: a camera or scene that moved without
    the poses saying so), and the motion left is the expected one (`expected_motion_px`).
    `alternative` (M, 2): other guesses (e.g. no motion, where `guess` comes from the
    poses), piloted too unless `guess`'s pilots track PILOT_ENOUGH of their points; the one
    whose pilot tracks more points is used. With a known motion each point's track is the
    same whichever points are tracked with it. Returns tracked (M, 2), ok (M,) and the
    (corrected) guesses (M, 2) px."""
    guess, motion_px, alternative = prior.guess, prior.motion_px, prior.alternative
    full = cfg.klt_levels
    if not np.isfinite(motion_px) and len(start) >= 2 * PILOT_STRIDE:
        pilot = slice(None, None, PILOT_STRIDE)
        deep = full + PILOT_EXTRA_LEVELS
        sample, ok = klt_track(prev, cur, start[pilot], guess[pilot], cfg, deep)
        if alternative is not None and ok.mean() < PILOT_ENOUGH:
            other, other_ok = klt_track(prev, cur, start[pilot], alternative[pilot], cfg, deep)
            if other_ok.sum() > ok.sum():
                guess, sample, ok = alternative, other, other_ok
        motion = image_motion(guess[pilot][ok], sample[ok])
        if motion is not None:
            guess = apply_motion(motion, guess)
        motion_px = expected_motion_px(np.linalg.norm(sample - guess[pilot], axis=1)[ok])
    levels = klt_levels_for(motion_px, cfg.klt_window_px, full)
    tracked, ok = klt_track(prev, cur, start, guess, cfg, levels)
    if levels < full:
        reach = cfg.klt_window_px / 4.0 * 2.0**levels
        ok &= np.linalg.norm(tracked - guess, axis=1) <= reach
    return tracked, ok, guess


def patch_ncc(image_a: np.ndarray, pixels_a: np.ndarray, image_b: np.ndarray,
              pixels_b: np.ndarray, size: int) -> np.ndarray:
    """Normalised cross-correlation (M,) of the size x size patches around pixels_a (M, 2)
    in image_a and pixels_b (M, 2) in image_b (bilinear, sub-pixel); -1 where a patch is
    flat. A drifted track that KLT still reports lands on a patch that no longer looks like
    the one it left."""
    if len(pixels_a) == 0:
        return np.zeros(0)
    offsets = np.arange(size, dtype=np.float32) - (size - 1) / 2.0

    def patches(image: np.ndarray, pixels: np.ndarray) -> np.ndarray:
        px = pixels.astype(np.float32)
        map_x = (px[:, 0, None, None] + offsets[None, None, :]).repeat(size, 1)
        map_y = (px[:, 1, None, None] + offsets[None, :, None]).repeat(size, 2)
        # one row of the maps per patch: remap's cost goes by rows (half that of a row
        # per patch row)
        out = cv2.remap(np.asarray(image, np.float32), map_x.reshape(-1, size * size),
                        map_y.reshape(-1, size * size), cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_REPLICATE)
        return out

    return correlation(patches(image_a, pixels_a), patches(image_b, pixels_b))


def correlation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Normalised cross-correlation (M,) of patches a, b (M, P) (their samples in one
    order); -1 where a patch is flat."""
    a = a.astype(np.float64)
    b = b.astype(np.float64)
    a -= a.mean(1, keepdims=True)
    b -= b.mean(1, keepdims=True)
    denom = np.sqrt(np.einsum("ij,ij->i", a, a) * np.einsum("ij,ij->i", b, b))
    return np.where(denom > 1e-9, np.einsum("ij,ij->i", a, b) / np.maximum(denom, 1e-9), -1.0)


def neighbour_flow(source: np.ndarray, flow: np.ndarray, query: np.ndarray) -> np.ndarray:
    """The local flow (M, 2) px at pixels query (M, 2): the median of `flow` (K, 2) over the
    NEIGHBOUR_TRACKS nearest of source (K, 2) within NEIGHBOUR_RADIUS_PX (NaN where none
    is). Tissue pushed by a tool moves its image several px more than the camera's motion
    says, smoothly: the tracks found around a point predict where it went."""
    out = np.full((len(query), 2), np.nan)
    if len(source) == 0 or len(query) == 0:
        return out
    k = min(NEIGHBOUR_TRACKS, len(source))
    dist, idx = cKDTree(source).query(query, k=k, distance_upper_bound=NEIGHBOUR_RADIUS_PX)
    dist, idx = dist.reshape(len(query), k), idx.reshape(len(query), k)
    near = np.isfinite(dist)
    padded = np.vstack([flow, np.full((1, 2), np.nan)])
    values = padded[np.where(near, idx, len(source))]  # (M, k, 2), NaN where none
    has = near.any(1)
    out[has] = _nanmedian_axis1(values[has])
    return out


def _nanmedian_axis1(values: np.ndarray) -> np.ndarray:
    """np.nanmedian(values, axis=1) of values (M, k, d) by one sort (NaN last), NaN where
    (m, :, j) has no finite value: numpy's small-array nanmedian goes through masked arrays,
    ~0.3 ms a call."""
    ordered = np.sort(values, axis=1)
    count = np.isfinite(values).sum(1, keepdims=True)  # (M, 1, d)
    low = np.take_along_axis(ordered, np.maximum(count - 1, 0) // 2, axis=1)[:, 0]
    high = np.take_along_axis(ordered, count // 2 - (count == 0), axis=1)[:, 0]
    return np.where(count[:, 0] > 0, 0.5 * (low + high), np.nan)


def retrack_from_neighbours(views: tuple[TrackingView, TrackingView], start: np.ndarray,
                            guess: np.ndarray, found: tuple[np.ndarray, np.ndarray],
                            cfg: TargetConfig, wanted: np.ndarray | None = None
                            ) -> tuple[np.ndarray, np.ndarray]:
    """The first pass's `found` = (tracks (M, 2), ok (M,)) from views = (prev, cur), with
    the failed ones tracked again (full pyramid, same checks, half the window: a deformed
    patch, which the full window failed on from its guess, shows less of its deformation
    in a smaller one) from their guess (M, 2) moved by the `neighbour_flow` of the found
    tracks' departures from their guesses, around their start pixels (M, 2);
    NEIGHBOUR_ROUNDS rounds, so a patch of tissue that moved far from the prediction is
    reached from its rim inwards. (Retried with the full window first, on simulated runs
    7 of ~4,300 retried tracks passed on the 5-camera frame-cost log and the stereo and
    rig-sweep seed-201 runs.) A later round tracks again only the points
    whose predicted flow changed (KLT from the same guess fails the same way). wanted (M,)
    bool: the tracks whose result is used (None: all); a round then retries only the lost
    points within reach of them (the rounds left times NEIGHBOUR_RADIUS_PX: where a later
    round's flow of a wanted point can see them), so the wanted tracks are those of
    retrying every point, the others are not."""
    prev, cur = views
    narrow = replace(cfg, klt_window_px=max(5, cfg.klt_window_px // 2 | 1))
    tracked, ok = found[0].copy(), found[1].copy()
    tried = np.full((len(start), 2), np.nan)  # the flow each lost point was last tried with
    for rounds_left in range(NEIGHBOUR_ROUNDS - 1, -1, -1):
        lost = np.flatnonzero(~ok)
        if wanted is not None and len(lost):
            lost = lost[_within(start[wanted], start[lost], rounds_left * NEIGHBOUR_RADIUS_PX)]
        if not len(lost) or not ok.any():
            break
        flow = neighbour_flow(start[ok], tracked[ok] - guess[ok], start[lost])
        lost_flow = np.isfinite(flow).all(1) & (np.linalg.norm(flow, axis=1) > 1.0)
        lost_flow &= ~(flow == tried[lost]).all(1)
        lost, flow = lost[lost_flow], flow[lost_flow]
        if not len(lost):
            break
        tried[lost] = flow
        again, again_ok = klt_track(prev, cur, start[lost], guess[lost] + flow, narrow)
        tracked[lost[again_ok]] = again[again_ok]
        ok[lost[again_ok]] = True
    return tracked, ok


def _within(centres: np.ndarray, pixels: np.ndarray, reach_px: float) -> np.ndarray:
    """(M,) bool: pixels (M, 2) within reach_px (plus 1 px of slack) of one of centres
    (K, 2)."""
    if not len(centres):
        return np.zeros(len(pixels), bool)
    distance = cKDTree(centres).query(pixels, k=1, distance_upper_bound=reach_px + 1.0)[0]
    return np.isfinite(distance)
