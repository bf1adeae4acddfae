"""Point classes and the ground-truth label rule the simulator's truth follows; the colour
of each class and status in every output (report figures, Foxglove export).

With frame 0 as reference, a point is `static` if it moved less than `static_mm`;
otherwise `deforming` if its neighbourhood (points within `neighbourhood_mm` at frame 0)
does not follow one rigid motion (RMS residual of the best rigid fit above `rigid_rms_mm`),
and `shifting` if it does. The simulator labels its truth with this rule and scoring uses it.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from ..geometry.poses import fit_rigid

INFORMATION_STEPS = 3  # Gauss-Newton steps of the information-weighted rigid fit

STATIC, SHIFTING, DEFORMING, UNKNOWN = 0, 1, 2, 255
CLASS_NAMES = {STATIC: "static", SHIFTING: "shifting", DEFORMING: "deforming"}

# What the reprojection-error check (core/target/cloud.py) found for a point in a frame.
INTRA, INTER, OUTLIER, UNOBSERVED = 0, 1, 2, 3
STATUS_NAMES = {INTRA: "intra", INTER: "inter", OUTLIER: "outlier", UNOBSERVED: "unobserved"}


def radius_neighbourhoods(points: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Neighbours of every point within `radius` (m), padded.

    Returns index (N, K) int (padded with the point itself) and mask (N, K) bool.
    """
    tree = cKDTree(points)
    lists = tree.query_ball_point(points, r=radius)
    counts = np.fromiter((len(x) for x in lists), int, len(lists))
    width = int(counts.max())
    flat = np.concatenate([np.asarray(x, int) for x in lists])
    rows = np.repeat(np.arange(len(points)), counts)
    cols = np.arange(len(flat)) - np.repeat(np.cumsum(counts) - counts, counts)
    index = np.repeat(np.arange(len(points))[:, None], width, axis=1)
    index[rows, cols] = flat
    mask = np.zeros((len(points), width), bool)
    mask[rows, cols] = True
    return index, mask


def rigid_fit_residuals(
    reference: np.ndarray, moved: np.ndarray, index: np.ndarray, mask: np.ndarray,
    weights: np.ndarray | None = None, information: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Residuals (N, K, 3) m (moved minus fitted; 0 for members left out) of the best
    (weighted) rigid fit of each neighbourhood (index (N, K), mask (N, K)) from reference to
    moved positions, and the members used (N, K) bool: those with a finite moved position
    (and a positive finite weight, weights (P,) per point, if given). With `information`
    (P, 3, 3) per point (inverse covariances), the fit weighted by `weights` is refined to
    the one weighted by each member's full information (`_information_step`): a narrow
    stereo baseline measures depth ~20x worse than across, and scalar weights let one
    member's depth error tilt the fit, which then leaves residuals across the lines of
    sight of the others (a still real SurgT scene at 360x288: 116 of ~4,200 labelled
    point-frames called deforming with scalar weights, 1 with the information)."""
    src = reference[index]
    dst = moved[index]
    keep = mask & np.isfinite(dst).all(-1)
    if weights is not None:
        w_members = np.asarray(weights, float)[index]
        keep &= np.isfinite(w_members) & (w_members > 0)
        w = np.where(keep, w_members, 0.0)
    else:
        w = keep.astype(float)
    dst = np.where(keep[..., None], dst, 0.0)
    R, t = fit_rigid(src, dst, w)
    pred = src @ np.swapaxes(R, 1, 2) + t[:, None, :]
    residual = np.where(keep[..., None], dst - pred, 0.0)
    if information is not None:
        info = np.where(keep[..., None, None], np.asarray(information, float)[index], 0.0)
        residual = _information_step(pred, residual, info, keep)
    return residual, keep


def _information_step(pred: np.ndarray, residual: np.ndarray, info: np.ndarray,
                      keep: np.ndarray) -> np.ndarray:
    """Residuals (N, K, 3) of each neighbourhood's rigid fit weighted by the members'
    information info (N, K, 3, 3) (0 for members left out), from the fitted positions pred
    (N, K, 3) and residuals of a fit with scalar weights: INFORMATION_STEPS Gauss-Newton
    steps, each turning the fitted positions by ω about their mean and shifting them by δ
    (the normal equations in (ω, δ) are linear; the turn is applied exactly, as a depth
    error of 1 mm across a 5 mm neighbourhood can tilt the scalar fit by ~10°)."""
    target = pred + residual
    n, k = keep.shape
    usable = (keep.sum(1) >= 3)[:, None, None]
    count = np.maximum(keep.sum(1), 1)[:, None]
    for _ in range(INFORMATION_STEPS):
        centre = (np.where(keep[..., None], pred, 0.0).sum(1) / count)[:, None, :]
        q = pred - centre
        # info @ [-[q]x, I]: the members' rows stacked, so that the sums over members and
        # axes are one (6, 3K) @ (3K, 6) product per neighbourhood
        jac = np.concatenate([-_skew(q), np.broadcast_to(np.eye(3), (*q.shape, 3))], -1)
        weighted = np.matmul(info, jac).reshape(n, 3 * k, 6)
        normal = np.matmul(np.swapaxes(jac.reshape(n, 3 * k, 6), 1, 2), weighted)
        rhs = np.matmul(np.swapaxes(weighted, 1, 2), (target - pred).reshape(n, 3 * k, 1))
        scale = np.trace(normal, axis1=1, axis2=2)[:, None, None]
        step = np.linalg.solve(normal + (1e-12 * scale + 1e-30) * np.eye(6), rhs)[..., 0]
        turn = Rotation.from_rotvec(np.where(usable[:, 0], step[:, :3], 0.0)).as_matrix()
        pred = centre + q @ np.swapaxes(turn, 1, 2) + np.where(
            usable[:, 0], step[:, 3:], 0.0)[:, None, :]
    return np.where(keep[..., None], target - pred, 0.0)


def _skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices [v]x (..., 3, 3) of vectors v (..., 3)."""
    zero = np.zeros(v.shape[:-1])
    return np.stack([np.stack([zero, -v[..., 2], v[..., 1]], -1),
                     np.stack([v[..., 2], zero, -v[..., 0]], -1),
                     np.stack([-v[..., 1], v[..., 0], zero], -1)], -2)


def rigid_fit_rms(
    reference: np.ndarray, moved: np.ndarray, index: np.ndarray, mask: np.ndarray
) -> np.ndarray:
    """RMS residual (N,) m of the best rigid fit of each neighbourhood (index (N, K), mask
    (N, K)) from reference to moved positions. Members without a finite moved position are
    left out; a neighbourhood with fewer than 3 members left gets NaN."""
    residual, keep = rigid_fit_residuals(reference, moved, index, mask)
    rms = np.sqrt((residual**2).sum((1, 2)) / np.maximum(keep.sum(1), 1.0))
    return np.where(keep.sum(1) >= 3, rms, np.nan)


def label_rule(
    reference: np.ndarray,
    moved: np.ndarray,
    index: np.ndarray,
    mask: np.ndarray,
    static_mm: float,
    rigid_rms_mm: float,
) -> np.ndarray:
    """Labels (N,) uint8 of points moved from `reference` (N, 3) to `moved` (N, 3), metres."""
    moved_by = np.linalg.norm(moved - reference, axis=1)
    labels = np.full(len(reference), STATIC, np.uint8)
    dynamic = moved_by >= static_mm * 1e-3
    if dynamic.any():
        rms = rigid_fit_rms(reference, moved, index[dynamic], mask[dynamic])
        labels[dynamic] = np.where(rms > rigid_rms_mm * 1e-3, DEFORMING, SHIFTING)
    return labels


def true_labels(
    vertices: np.ndarray, static_mm: float, neighbourhood_mm: float, rigid_rms_mm: float
) -> np.ndarray:
    """Spec label rule over a sequence: vertices (T, V, 3) m -> labels (T, V) uint8."""
    index, mask = radius_neighbourhoods(vertices[0], neighbourhood_mm * 1e-3)
    return np.stack(
        [label_rule(vertices[0], frame, index, mask, static_mm, rigid_rms_mm) for frame in vertices]
    )


# -- colours: one per class and status, for every output (report figures, Foxglove export) -----
CLASS_COLOURS = {"static": "#4C78A8", "shifting": "#F2A541", "deforming": "#D1495B",
                 "unknown": "#BAB0AC"}
STATUS_COLOURS = {"intra": "#4C78A8", "inter": "#59A14F", "outlier": "#D1495B",
                  "unobserved": "#BAB0AC"}


def rgba255(hex_colour: str, alpha: int = 255) -> tuple[int, int, int, int]:
    """"#RRGGBB" -> (r, g, b, a), each 0..255."""
    value = hex_colour.lstrip("#")
    return int(value[0:2], 16), int(value[2:4], 16), int(value[4:6], 16), alpha
