"""Point classification: static / shifting / deforming (Su et al. 2019, section II.E, Fig. 2).

Every template point p_i (frame-0 position, homogeneous p̃_i) is labelled at every frame k
from its registered affine T_i (3x4, so that T_i p̃_i is its position now), the
reprojection-error check of the target cloud, and its neighbours j (template points within
`neighbourhood_mm` of p_i at frame 0):

1. static vs dynamic: the registered displacement ‖T_i p̃_i − p_i‖ against `static_mm`
   (the spec's truth rule moves the same threshold from frame 0). Inside a band of
   ±`status_band_mm` around the threshold the displacement alone is not trusted (the
   registration's own error is of that size) and the reprojection check breaks the tie:
   an intra-camera inlier (its frame-0 position still reprojects in every view) is
   static, an inter-camera inlier (re-triangulated elsewhere) is dynamic.
2. shifting vs deforming, for dynamic points, by one of two measures (`measure`):
   - "rigid_rms": RMS residual of the best rigid fit of the neighbourhood from its frame-0
     positions to its registered positions — the spec's truth rule seen through the
     registration;
   - "transform_diff": d_i = a percentile (100 = max) over neighbours j of
     ‖(T_j − T_i) p̃_i‖, the paper's "(Tj−Ti)pi": how far neighbour j's transform would
     carry point i from where its own transform carries it.
   At or above `deform_mm` -> deforming, else shifting.
3. optional temporal hysteresis: a label run shorter than `hysteresis_frames` frames is
   replaced by the label before it (offline, so the whole sequence is known).

Points without a finite registered position are UNKNOWN. Frame 0 is the reference: all
static. Pure numpy; no I/O.

Defaults (ours, not the paper's), measured against the simulator's truth (macro-F1 over
frames >= 1 of the labels of the template points' nearest true vertices; 6-camera 640x480
logs: a 6-frame one and the shipped 20-frame sample, registered by stages/register.py):
- Fed the *true* motion field, "rigid_rms" with the truth rule's own thresholds (1.0 mm,
  0.25 mm, 5 mm) reproduces the truth (macro-F1 0.97); "transform_diff" peaks lower (0.95
  with the median over neighbours at 0.1 mm, 0.93 with the max at 0.8 mm): a per-point
  affine extrapolated to a neighbour is not the same quantity as a rigid-fit residual, and
  the truth is a rigid-fit rule. So "rigid_rms" is the default.
- Through the registration, the l1 smoothness and node blending flatten the tool's dent:
  truly deforming neighbourhoods show about half their true RMS (medians 0.14–0.18 mm vs
  0.32 mm): the registration keeps about 0.6 of a neighbourhood's rigid-fit RMS. So
  `deform_mm` = 0.15 mm = 0.6 x the rule's 0.25 mm. Measured: macro-F1 0.91 on the shipped
  sample at 0.15 mm (deforming recall 0.95), 0.895 at 0.12 mm, 0.87 at 0.25 mm; on a
  6-frame log 0.77 at 0.15 mm vs 0.82 at 0.12 mm ("transform_diff" peaks at 0.77 / 0.84,
  75th percentile, 0.2 mm).
- The registration also shrinks motions slightly towards rest (a 1.04 mm breathing shift
  comes out at 1.01 mm median), so `static_mm` = 0.9 mm (+0.01 to +0.08 over 1.0 mm).
- The reprojection check is weak evidence here: 98.5 % of intra-camera inliers are truly
  static, but so are 70 % of inter-camera inliers (tracker noise pushes static points out
  of the intra gate and they are re-triangulated). Letting it break ties within ±0.3 mm
  of `static_mm` lowered macro-F1 by 0.06–0.15 (intra-only tie-breaking by 0.01), so
  `status_band_mm` defaults to 0: the displacement decides.
- Hysteresis of 2–3 frames changed nothing on 20 frames and hurt on 6 (-0.02 to -0.04): off.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..config import ClassifyConfig
from ..errors import GeometryError
from .labels import DEFORMING, INTER, INTRA, SHIFTING, STATIC, UNKNOWN, rigid_fit_rms


@dataclass(frozen=True)
class Neighbourhoods:
    """Neighbours of every template point: index (N, K) int (padded with the point itself)
    and mask (N, K) bool; the point itself is never a masked-in neighbour."""

    index: np.ndarray
    mask: np.ndarray

    @property
    def counts(self) -> np.ndarray:
        """Neighbours per point (N,)."""
        return self.mask.sum(1)


@dataclass(frozen=True)
class FrameClasses:
    """One frame: labels (N,) uint8, displacement_mm (N,) ‖T_i p̃_i − p_i‖ and
    deformation_mm (N,) the shifting/deforming measure (NaN where not computed)."""

    labels: np.ndarray
    displacement_mm: np.ndarray
    deformation_mm: np.ndarray


@dataclass(frozen=True)
class SequenceClasses:
    """All frames: labels (T, N) uint8 (after hysteresis), raw_labels (T, N) uint8 (before),
    displacement_mm (T, N) and deformation_mm (T, N) float32."""

    labels: np.ndarray
    raw_labels: np.ndarray
    displacement_mm: np.ndarray
    deformation_mm: np.ndarray


def template_neighbourhoods(points: np.ndarray, radius_mm: float, min_neighbours: int,
                            max_neighbours: int) -> Neighbourhoods:
    """Neighbours of template points (N, 3) m within `radius_mm` at frame 0, the nearest
    `max_neighbours` at most; a point with fewer than `min_neighbours` inside the radius
    takes its `min_neighbours` nearest instead (so sparse regions still get a fit)."""
    points = _points(points, "template points")
    n = len(points)
    if n < 2:
        raise GeometryError(f"classification needs >= 2 template points, got {n}")
    k = min(max_neighbours, n - 1) + 1  # +1: the point itself comes first
    dist, index = cKDTree(points).query(points, k=k)
    dist, index = dist.reshape(n, k), index.reshape(n, k)
    cols = np.arange(k)[None, :]
    mask = (dist <= radius_mm * 1e-3) | (cols <= min_neighbours)
    rows = np.arange(n)[:, None]
    mask &= index != rows
    index = np.where(mask, index, rows)
    return Neighbourhoods(index=index, mask=mask)


def displacement_mm(template: np.ndarray, registered: np.ndarray) -> np.ndarray:
    """‖T_i p̃_i − p_i‖ (N,) mm of registered positions (N, 3) m from template (N, 3) m."""
    return np.linalg.norm(registered - template, axis=1) * 1e3


def rigid_rms_mm(template: np.ndarray, registered: np.ndarray, nb: Neighbourhoods,
                 rows: np.ndarray | None = None) -> np.ndarray:
    """RMS residual (M,) mm of the best rigid fit of each neighbourhood (the point and its
    neighbours) from frame-0 to registered positions, for `rows` (M,) (default all points).
    Neighbours without a finite registered position are left out of the fit."""
    rows = np.arange(len(template)) if rows is None else rows
    if len(rows) == 0:
        return np.zeros(0)
    index = np.concatenate([rows[:, None], nb.index[rows]], axis=1)
    mask = np.concatenate([np.ones((len(rows), 1), bool), nb.mask[rows]], axis=1)
    return rigid_fit_rms(template, registered, index, mask) * 1e3


def transform_difference_mm(template: np.ndarray, transforms: np.ndarray, nb: Neighbourhoods,
                            percentile: float, rows: np.ndarray | None = None) -> np.ndarray:
    """d_i (M,) mm = `percentile` (100 = max) over neighbours j of ‖(T_j − T_i) p̃_i‖
    (Su et al. 2019, Fig. 2), for `rows` (M,) (default all); transforms (N, 3, 4) act on
    homogeneous frame-0 points. Neighbours with non-finite transforms are left out."""
    rows = np.arange(len(template)) if rows is None else rows
    if len(rows) == 0:
        return np.zeros(0)
    ph = np.concatenate([template[rows], np.ones((len(rows), 1))], axis=1)  # (M, 4)
    own = np.einsum("mij,mj->mi", transforms[rows], ph)  # (M, 3)
    other = np.einsum("mkij,mj->mki", transforms[nb.index[rows]], ph)  # (M, K, 3)
    diff = np.linalg.norm(other - own[:, None, :], axis=-1) * 1e3
    valid = nb.mask[rows] & np.isfinite(diff)
    diff = np.where(valid, diff, np.nan)
    out = np.full(len(rows), np.nan)
    has = valid.any(1)
    if has.any():
        if percentile >= 100:
            out[has] = np.nanmax(diff[has], axis=1)
        else:
            out[has] = np.nanpercentile(diff[has], percentile, axis=1)
    return out


def classify_frame(template: np.ndarray, registered: np.ndarray, nb: Neighbourhoods,
                   cfg: ClassifyConfig, transforms: np.ndarray | None = None,
                   status: np.ndarray | None = None) -> FrameClasses:
    """Label one frame.

    template (N, 3) m frame-0 positions p_i; registered (N, 3) m positions T_i p̃_i (NaN =
    unknown); transforms (N, 3, 4) per-point affines (needed by measure "transform_diff");
    status (N,) reprojection check codes of core/target.py (None = displacement only).
    """
    template = _points(template, "template points")
    registered = np.asarray(registered, float)
    n = len(template)
    if registered.shape != (n, 3):
        raise GeometryError(f"registered positions must be ({n}, 3), got {registered.shape}")
    if transforms is not None and np.shape(transforms) != (n, 3, 4):
        raise GeometryError(f"transforms must be ({n}, 3, 4), got {np.shape(transforms)}")
    if status is not None and np.shape(status) != (n,):
        raise GeometryError(f"status must be ({n},), got {np.shape(status)}")
    if cfg.measure == "transform_diff" and transforms is None:
        raise GeometryError('classify.measure = "transform_diff" needs per-point transforms')

    known = np.isfinite(registered).all(1)
    disp = np.full(n, np.nan)
    disp[known] = displacement_mm(template[known], registered[known])
    dynamic = known & (disp >= cfg.static_mm)
    if status is not None and cfg.status_band_mm > 0:
        status = np.asarray(status)
        near = known & (np.abs(disp - cfg.static_mm) < cfg.status_band_mm)
        dynamic[near & (status == INTRA)] = False
        dynamic[near & (status == INTER)] = True

    labels = np.full(n, UNKNOWN, np.uint8)
    labels[known] = STATIC
    deformation = np.full(n, np.nan)
    rows = np.flatnonzero(dynamic)
    if transforms is not None and cfg.measure == "transform_diff":
        measure = transform_difference_mm(template, np.asarray(transforms, float), nb,
                                          cfg.neighbour_percentile, rows)
    else:
        measure = rigid_rms_mm(template, registered, nb, rows)
    deformation[rows] = measure
    # A neighbourhood too small to measure (NaN) cannot show deformation: shifting.
    labels[rows] = np.where(measure >= cfg.deform_mm, DEFORMING, SHIFTING)
    return FrameClasses(labels=labels, displacement_mm=disp, deformation_mm=deformation)


def apply_hysteresis(labels: np.ndarray, frames: int) -> np.ndarray:
    """Labels (T, N) with every run shorter than `frames` frames replaced by the label before
    it (frame 0 is the reference and never changes; a run that reaches the last frame is kept:
    the future that would confirm it is not recorded). UNKNOWN entries stay unknown and do
    not break runs. frames <= 1 returns a copy."""
    out = np.array(labels, np.uint8, copy=True)
    if frames <= 1 or out.shape[0] < 2:
        return out
    n_frames = out.shape[0]
    current = out[0].copy()
    for k in range(1, n_frames):
        raw = labels[k]
        change = (raw != current) & (raw != UNKNOWN)
        if change.any():
            # Accept a change only if it persists for `frames` known frames (or to the end).
            stays = np.ones(len(current), bool)
            seen = np.zeros(len(current), int)
            for ahead in range(k, n_frames):
                fut = labels[ahead]
                counts = fut != UNKNOWN
                stays &= ~counts | (fut == raw) | (seen >= frames)
                seen += counts
                if (seen >= frames).all():
                    break
            accept = change & stays
            current[accept] = raw[accept]
        out[k] = np.where(raw == UNKNOWN, UNKNOWN, current)
    return out


def classify_sequence(template: np.ndarray, registered: np.ndarray, cfg: ClassifyConfig,
                      transforms: np.ndarray | None = None, status: np.ndarray | None = None,
                      nb: Neighbourhoods | None = None) -> SequenceClasses:
    """Label every frame: registered (T, N, 3) m with frame 0 the template itself;
    transforms (T, N, 3, 4) and status (T, N) optional as in `classify_frame`."""
    template = _points(template, "template points")
    registered = np.asarray(registered, float)
    if registered.ndim != 3 or registered.shape[1:] != template.shape:
        raise GeometryError(f"registered must be (T, {len(template)}, 3), got {registered.shape}")
    nb = nb or template_neighbourhoods(template, cfg.neighbourhood_mm, cfg.min_neighbours,
                                       cfg.max_neighbours)
    frames = [
        classify_frame(template, registered[k], nb, cfg,
                       None if transforms is None else transforms[k],
                       None if status is None else status[k])
        for k in range(len(registered))
    ]
    raw = np.stack([f.labels for f in frames])
    raw[0] = np.where(raw[0] == UNKNOWN, UNKNOWN, STATIC)
    return SequenceClasses(
        labels=apply_hysteresis(raw, cfg.hysteresis_frames),
        raw_labels=raw,
        displacement_mm=np.stack([f.displacement_mm for f in frames]).astype(np.float32),
        deformation_mm=np.stack([f.deformation_mm for f in frames]).astype(np.float32),
    )


def _points(points: np.ndarray, name: str) -> np.ndarray:
    points = np.asarray(points, float)
    if points.ndim != 2 or points.shape[1] != 3:
        raise GeometryError(f"{name} must be (N, 3), got {points.shape}")
    if not np.isfinite(points).all():
        raise GeometryError(f"{name} contain NaN/Inf")
    return points
