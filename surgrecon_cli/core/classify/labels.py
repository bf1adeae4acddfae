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
FIT_BLOCKS = 8  # ours: blocks of neighbourhoods of similar width (`rigid_fit_residuals`)

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
    point-frames called deforming with scalar weights, 1 with the information).

    Neighbourhoods are fitted in FIT_BLOCKS blocks of rows of similar width (the last
    member's column), each cut to its widest row: within 5 mm a neighbourhood holds 6 to
    129 members, and padding every row to the widest doubled the work."""
    n, k = mask.shape
    span = np.where(mask.any(1), k - np.argmax(mask[:, ::-1], axis=1), 0)
    residual = np.zeros((n, k, 3))
    keep = np.zeros((n, k), bool)
    for block in np.array_split(np.argsort(span, kind="stable"), min(FIT_BLOCKS, max(n, 1))):
        width = int(span[block].max()) if len(block) else 0
        if width == 0:
            continue
        residual[block, :width], keep[block, :width] = _rigid_fit_block(
            reference, moved, index[block, :width], mask[block, :width], weights, information)
    return residual, keep


def _rigid_fit_block(
    reference: np.ndarray, moved: np.ndarray, index: np.ndarray, mask: np.ndarray,
    weights: np.ndarray | None, information: np.ndarray | None,
) -> tuple[np.ndarray, np.ndarray]:
    """`rigid_fit_residuals` of neighbourhoods index (M, K), mask (M, K)."""
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
    error of 1 mm across a 5 mm neighbourhood can tilt the scalar fit by ~10°).

    With J_j = [−[q_j]×, I] (q_j the member about the mean) the normal matrix Σ J_jᵀ I_j J_j
    has the blocks Σ [q_j]× I_j (turn-shift), −Σ [q_j]× I_j [q_j]× (turn-turn) and Σ I_j:
    with [q]×_ab = ε_aeb q_e they are the member sums Σ q_e I_bc and Σ q_e q_f I_bc (e <= f;
    each one batched product per neighbourhood) times constant matrices of ε."""
    target = pred + residual
    n, k = keep.shape
    usable = keep.sum(1) >= 3
    count = np.maximum(keep.sum(1), 1)[:, None]
    members = keep.astype(float)[:, None, :]  # (N, 1, K): sums over members as products
    info_flat = info.reshape(n, k, 9)
    shift_shift = np.matmul(members, info_flat).reshape(n, 3, 3)
    normal = np.empty((n, 6, 6))
    for _ in range(INFORMATION_STEPS):
        centre = (np.matmul(members, pred)[:, 0] / count)[:, None, :]
        q = pred - centre
        q_t = np.swapaxes(q, 1, 2)
        first = np.matmul(q_t, info_flat).reshape(n, 9, 3)  # Σ q_e I_bc, rows (e, b)
        pairs = np.stack([q_t[:, e] * q_t[:, f] for e, f in _SYMMETRIC_PAIRS], 1)  # (N, 6, K)
        second = np.matmul(pairs, info_flat).reshape(n, 54)  # Σ q_e q_f I_bc, e <= f
        turn_shift = np.matmul(_EPS_AEB, first)  # ε_aeb Σ q_e I_bc
        normal[:, :3, :3] = (second @ _TURN_TURN).reshape(n, 3, 3)
        normal[:, :3, 3:] = turn_shift
        normal[:, 3:, :3] = np.swapaxes(turn_shift, 1, 2)
        normal[:, 3:, 3:] = shift_shift
        info_r = np.einsum("nkab,nkb->nka", info, target - pred)  # batched 3x3 products
        moment = np.matmul(q_t, info_r).reshape(n, 9) @ _EPS_AEB.T  # ε_aeb Σ q_e (I r)_b
        rhs = np.concatenate([moment, np.matmul(members, info_r)[:, 0]], -1)
        scale = np.trace(normal, axis1=1, axis2=2)[:, None, None]
        step = np.linalg.solve(normal + (1e-12 * scale + 1e-30) * np.eye(6), rhs[..., None])[..., 0]
        turn = Rotation.from_rotvec(np.where(usable[:, None], step[:, :3], 0.0)).as_matrix()
        pred = q @ np.swapaxes(turn, 1, 2) + (
            centre + np.where(usable[:, None], step[:, 3:], 0.0)[:, None, :])
    return np.where(keep[..., None], target - pred, 0.0)


def _levi_civita() -> np.ndarray:
    """ε (3, 3, 3): +1 on even permutations of (0, 1, 2), −1 on odd ones, else 0."""
    eps = np.zeros((3, 3, 3))
    for a, b, c in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):
        eps[a, b, c], eps[a, c, b] = 1.0, -1.0
    return eps


def _turn_turn() -> np.ndarray:
    """−ε_aeb ε_cfd as an (e f b c) x (a d) matrix (54, 9) over the pairs e <= f
    (`_SYMMETRIC_PAIRS`; q_e q_f is symmetric, so the (f, e) rows join the (e, f) ones):
    −Σ [q]× I [q]× from the sums Σ q_e q_f I_bc."""
    full = -np.einsum("aeb,cfd->efbcad", _LEVI_CIVITA, _LEVI_CIVITA).reshape(3, 3, 9, 9)
    return np.stack([full[e, f] + (full[f, e] if e != f else 0.0)
                     for e, f in _SYMMETRIC_PAIRS]).reshape(54, 9)


_LEVI_CIVITA = _levi_civita()
_EPS_AEB = _LEVI_CIVITA.reshape(3, 9)  # ε_a,(e b): [q]× I = ε_aeb q_e I_bc
_SYMMETRIC_PAIRS = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
_TURN_TURN = _turn_turn()


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
