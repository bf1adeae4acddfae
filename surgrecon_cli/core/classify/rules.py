"""Point classification: static / shifting / deforming (Su et al. 2019, section II.E, Fig. 2)
as statistical tests against the run's measured noise.

Every template point p_i (frame-0 position) is labelled at every frame k from its
registered position, the uncertainties of the run's noise model (core/noise/model.py,
core/registration/frame_step.py: σ is the RMS of a 3D position error, metres) and its neighbours j
(template points within `neighbourhood_mm` of p_i at frame 0):

1. unknown: no finite registered position, or the uncertainty σ_Δ of its displacement from
   frame 0 exceeds `max_sigma_mm` (a point far from any data: the registration extrapolates
   it, it is not measured) and the displacement is within what that uncertainty explains
   (the test of step 2). σ_Δ, not the position's σ: the labels are decided from
   displacements, and the template's frame-0 image error, which tracking carries into every
   later measurement of the point, cancels in them (`Evidence.displacement_sigma`; on a
   4 mm stereo baseline that error is ~0.9 mm of depth at 65 mm, the displacement's 0.1–0.3).
   A loosely known point that moved far beyond its noise has moved, whatever its σ: it goes
   on to step 3 (on a 360×288 stereo pair at the breath's peak, a quarter of the observed
   point-frames had σ_Δ of 1.8–2.5 mm, along the lines of sight, while moving millimetres
   across them; unknown, they made the moving tissue 78 % detected, labelled 95 %).
2. static vs dynamic: dynamic when the registered displacement Δ_i = x_i − p_i reaches
   `static_mm` (the tolerance below which motion does not count, the spec's rule) and is
   significant: Δᵀ Σ_Δ⁻¹ Δ above the chi-square bound (3 dof) at `significance`, Σ_Δ the
   target's plus the template point's covariance (anisotropic: a narrow stereo baseline
   knows depth far worse than the other directions), or isotropic from σ without a target.
   A displacement the noise explains is no evidence of motion.
3. shifting vs deforming, for dynamic points ("rigid_rms", default): two questions.
   Is the neighbourhood's departure from one rigid motion real? Its measured positions
   (targets where the reprojection check gave one, else registered) are fitted by one
   rigid motion from frame 0, weighted by precision; under "one rigid motion" the residual
   S = Σ_j r_jᵀ Σ_j⁻¹ r_j (Σ_j the member's displacement covariance) is chi-square with
   3n − 6 degrees of freedom (n members), and the departure is significant when S exceeds
   its bound at `significance`, after the frame's noise scale: the lower quartile over all
   its labelled neighbourhoods of S / the chi-square lower quartile of its dof, when above 1
   (at least a quarter of a scene moves rigidly; the noise model's σ is a floor,
   and real images scatter positions more than it says: on the simulator's real-image
   breathing variant, 82 % of truly rigid moving neighbourhoods failed the unscaled test,
   S / dof 2.5). Is it large enough to count? The rigid-fit RMS of the *registered*
   positions (the spec's rule applied to the estimated field) reaches `deform_mm` (the
   spec's tolerance) with every direction counted by how well it is measured
   (`resolved_rms_mm`: each member's residual weighted by (Σ_j + deform_mm²/3 I)⁻¹,
   normalised so that without noise it is the plain RMS; Σ_j the covariance of the
   member's displacement from frame 0, `displacement_covariance`: the template's frame-0
   image error, which tracking carries into every later measurement, cancels in it; not
   scaled up by the frame's noise scale, which the directions across the lines of sight
   set: with tracks locked to the template the model understates those 1.5-2x while it
   states depth right, and the scaled weights discounted real dents along the lines of
   sight, stereo simulator deforming recall 0.64 -> 0.55; scaled down where the registered
   field itself scatters less than Σ_j predicts, `field_noise_scale`: on the 6-camera
   simulator the unscaled weights discounted dents along the lines of sight, deforming
   recall 0.81 -> 0.83 on its tuning seeds with the scale; what that leaves visible is
   reported per point, `FrameClasses.floor_mm`: the rigid-fit RMS a departure along the
   members' least-known directions needs to reach `deform_mm`, `deform_floor_mm`).
   Where that RMS falls short of `deform_mm` by less than a fifth (`BORDERLINE_SHARE`),
   the measured positions' own resolved RMS, less the energy their noise explains at the
   frame's noise scale (`measured_rms_mm`), may reach it instead: the regulariser makes a
   dent just over the tolerance register just under it (on the `default` tuning seeds the
   lost dents' registered RMS was 8-12 % under the truth), and the measurements, not
   smoothed, keep it; only there, since on a narrow baseline their depth errors are
   heavier-tailed than the noise model (docs/labels_noise.md).
   Both, or it is shifting. A point the tool touches (`Evidence.touched`: within the
   capsule's radius + margin of a tool whose pose the robot's kinematics give) needs no
   image evidence for the first question: the tool pressing it is the departure, measured
   by the kinematics where the images see nothing (the tool hides the dent, its points
   have no target, and the registered field there carries the extrapolation's σ, which
   no departure exceeds). On the stereo simulator's tuning seeds 101–105, 11–143
   point-frames per run moved, reached `deform_mm` and departed not significantly; 86–100 %
   of them truly deforming, the ones without measured neighbours 2–7 mm from the tool tip;
   on the breathing variant the same step held 26–230, truly static or shifting, 47 mm from
   the tool. (The measured positions answer the first question well but
   their plain RMS, debiased by their noise, alone underestimates borderline dents — 0.16–0.20
   mm for a true 0.27–0.28 mm on the shipped sample — while the registered field's RMS
   follows the truth there — 0.28–0.34 mm. On a 4 mm stereo baseline the registered field
   carries the depth noise of its displacement, 0.2–0.35 mm of rigid-fit RMS on rigidly
   moving tissue: the plain RMS reached `deform_mm` on 22–50 % of the moving
   neighbourhoods of a real-texture breathing clip where 0–4 % truly deform. A 0.3 mm
   departure along a line of sight known to ±0.8 mm is no evidence, across it to ±0.06 mm
   it is: docs/labels_noise.md, "Breathing on a narrow stereo baseline".)
   Why not the paper's (T_j − T_i) p_i ("transform_diff", kept as an option): on a surface
   the linear part of a point's affine is not determined by the data (the derivative of
   the motion along the normal is unobserved, and the regulariser picks it), so carrying
   p_i with its neighbour's transform measures that gauge as much as the motion (3.8 mm
   where the truth is 0.09 mm on a real stereo log). The rigid fit over the neighbourhood
   asks the same question, do the neighbours follow one rigid motion, of positions, which
   the data do determine.
4. optional temporal hysteresis: a label run shorter than `hysteresis_frames` frames is
   replaced by the label before it (offline, so the whole sequence is known).

Without uncertainties (σ = None) the tests reduce to the plain thresholds. Frame 0 is the
reference: all static. Pure numpy; no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree
from scipy.stats import chi2

from ...config import ClassifyConfig
from ...errors import GeometryError
from .departure import (
    BORDERLINE_SHARE,
    SIGMA_FLOOR_M,
    Measured,
    deform_floor_mm,
    departure_statistic,
    field_noise_scale,
    measured_rms_mm,
    noise_scale,
    resolved_rms_mm,
)
from .hysteresis import apply_hysteresis
from .labels import (
    DEFORMING,
    INTER,
    INTRA,
    SHIFTING,
    STATIC,
    UNKNOWN,
    rigid_fit_rms,
)


@dataclass(frozen=True)
class Neighbourhoods:
    """Neighbours of every template point: index (N, K) int (padded with the point itself)
    and mask (N, K) bool; the point itself is never a masked-in neighbour."""

    index: np.ndarray
    mask: np.ndarray

    def members(self, rows: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Each neighbourhood of `rows` (M,) (default all points) with the point first:
        index (M, K + 1) and mask (M, K + 1)."""
        rows = np.arange(len(self.index)) if rows is None else rows
        return (np.concatenate([rows[:, None], self.index[rows]], axis=1),
                np.concatenate([np.ones((len(rows), 1), bool), self.mask[rows]], axis=1))

    @property
    def counts(self) -> np.ndarray:
        """Neighbours per point (N,)."""
        return self.mask.sum(1)


@dataclass(frozen=True)
class Evidence:
    """Per point uncertainties of one frame (metres): sigma (N,) of the registered position
    (inf = unsupported), template_sigma (N,) of the frame-0 position, measured (N, 3) the
    position the data give (target where there is one, else registered), measured_sigma
    (N,) its uncertainty, displacement_cov (N, 3, 3) m² the covariance of the displacement
    from frame 0 and departure_cov (N, 3, 3) m² the part of it that is not a rigid error
    shared by a whole neighbourhood (for the rigid-motion test); template_shared_var (N,)
    m² the part of the template point's error variance that every later measurement of the
    point carries too (its frame-0 image noise, which tracking keeps: it cancels in the
    displacement; None = none shared); touched (N,) bool the points a tool touches at
    this frame (robot kinematics; None = no tool known)."""

    sigma: np.ndarray
    template_sigma: np.ndarray
    measured: np.ndarray
    measured_sigma: np.ndarray
    displacement_cov: np.ndarray
    departure_cov: np.ndarray
    template_shared_var: np.ndarray | None = None
    touched: np.ndarray | None = None

    def displacement_sigma(self) -> np.ndarray:
        """σ_Δ (N,) m of the displacement x_i − p_i the labels are decided from: σ the
        better of the registered and measured positions' σ, σ_t the template's, and s the
        variance they share: σ_Δ² = σ² + σ_t² − 2 s, s = min(template_shared_var, σ²) (a
        later measurement cannot carry more of the template's error than its own; from
        more views than the template it carries less). Inf stays inf."""
        position = np.fmin(np.asarray(self.sigma, float), np.asarray(self.measured_sigma, float))
        var = position**2 + np.asarray(self.template_sigma, float) ** 2
        if self.template_shared_var is not None:
            shared = np.fmin(np.asarray(self.template_shared_var, float), position**2)
            with np.errstate(invalid="ignore"):
                var = var - 2.0 * shared
        return np.sqrt(np.where(np.isnan(var), np.inf, np.maximum(var, 0.0)))


@dataclass(frozen=True)
class RegisteredFrame:
    """One frame's registration: positions (N, 3) m T_i p̃_i (NaN = unknown), per-point
    affines transforms (N, 3, 4) (needed by measure "transform_diff") and status (N,) the
    reprojection check codes of core/target/cloud.py (None = displacement only)."""

    positions: np.ndarray
    transforms: np.ndarray | None = None
    status: np.ndarray | None = None


@dataclass(frozen=True)
class FrameClasses:
    """One frame: labels (N,) uint8, displacement_mm (N,) ‖T_i p̃_i − p_i‖,
    deformation_mm (N,) the shifting/deforming measure (NaN where not computed) and
    floor_mm (N,) the rigid-fit RMS a departure along the lines of sight needs to count as
    deforming (`departure.deform_floor_mm`; deform_mm without noise, NaN where the point
    is not labelled or the measure is "transform_diff")."""

    labels: np.ndarray
    displacement_mm: np.ndarray
    deformation_mm: np.ndarray
    floor_mm: np.ndarray


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
    index, mask = nb.members(rows)
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


def displacement_covariance(position_cov: np.ndarray, template_cov: np.ndarray) -> np.ndarray:
    """Covariance (N, 3, 3) m² of a displacement x − p from a later measurement x (position_cov
    (N, 3, 3) m² from image noise) of a template point p (template_cov (N, 3, 3) m², its
    frame-0 image noise), where tracking carries p's image error into x: Σ_x + Σ_p − 2 S,
    S the error they share, in each direction no more than either carries. In the basis where
    Σ_p = I and Σ_x = Λ (generalised eigenvectors), S = min(Λ, I), so the displacement's
    variance is |Λ − I| there (the matrix form of `Evidence.displacement_sigma`'s
    |σ² − σ_t²|): on a narrow stereo baseline both positions know depth to ~1 mm, their
    difference to the tracking error alone. Rows with non-finite input: Σ_x + Σ_p."""
    cx = np.asarray(position_cov, float)
    cp = np.asarray(template_cov, float)
    out = cx + cp
    ok = np.isfinite(cx).all((1, 2)) & np.isfinite(cp).all((1, 2))
    if not ok.any():
        return out
    floor = np.eye(3) * SIGMA_FLOOR_M**2
    low = np.linalg.cholesky(cp[ok] + floor)  # Σ_p = L Lᵀ
    inv = np.linalg.inv(low)
    whitened = inv @ (cx[ok] + floor) @ np.swapaxes(inv, 1, 2)
    lam, vec = np.linalg.eigh(0.5 * (whitened + np.swapaxes(whitened, 1, 2)))
    back = low @ vec
    out[ok] = np.einsum("nij,nj,nkj->nik", back, np.abs(lam - 1.0), back)
    return out


def significant_motion(displacement: np.ndarray, covariance: np.ndarray,
                       significance: float) -> np.ndarray:
    """(N,) bool: the displacement (N, 3) m is more than its covariance (N, 3, 3) m²
    explains (Mahalanobis² above the chi-square bound, 3 dof, at `significance`). Points
    with a non-finite displacement or covariance: False."""
    d = np.asarray(displacement, float)
    cov = np.asarray(covariance, float)
    ok = np.isfinite(d).all(1) & np.isfinite(cov).all((1, 2))
    out = np.zeros(len(d), bool)
    if ok.any():
        reg = cov[ok] + np.eye(3) * SIGMA_FLOOR_M**2
        m2 = np.einsum("ni,ni->n", d[ok], np.linalg.solve(reg, d[ok][..., None])[..., 0])
        out[ok] = m2 > chi2.isf(significance, 3)
    return out


def labelled_motion(displacement: np.ndarray, evidence: Evidence, cfg: ClassifyConfig
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Steps 1-2 of the module docstring for displacements (N, 3) m from frame 0: known (N,)
    bool, a finite displacement whose σ_Δ is at most `max_sigma_mm` or that moved, and moved
    (N,) bool, beyond its covariance (`significant_motion` at `significance`)."""
    moved = significant_motion(displacement, evidence.displacement_cov, cfg.significance)
    known = np.isfinite(displacement).all(1) & (
        moved | (evidence.displacement_sigma() * 1e3 <= cfg.max_sigma_mm))
    return known, moved


def classify_frame(template: np.ndarray, frame: RegisteredFrame, nb: Neighbourhoods,
                   cfg: ClassifyConfig, evidence: Evidence | None = None) -> FrameClasses:
    """Label one frame: template (N, 3) m frame-0 positions p_i; evidence the frame's
    uncertainties (None = plain thresholds, no noise)."""
    template = _points(template, "template points")
    registered = np.asarray(frame.positions, float)
    transforms, status = frame.transforms, frame.status
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
    if evidence is not None:
        decidable, moved = labelled_motion(registered - template, evidence, cfg)
        known &= decidable
        dynamic &= known & moved
    if status is not None and cfg.status_band_mm > 0:
        status = np.asarray(status)
        near = known & (np.abs(disp - cfg.static_mm) < cfg.status_band_mm)
        dynamic[near & (status == INTRA)] = False
        dynamic[near & (status == INTER)] = True

    labels = np.full(n, UNKNOWN, np.uint8)
    labels[known] = STATIC
    deformation = np.full(n, np.nan)
    floor = np.full(n, np.nan)
    rows = np.flatnonzero(dynamic)
    if transforms is not None and cfg.measure == "transform_diff":
        measure = transform_difference_mm(template, np.asarray(transforms, float), nb,
                                          cfg.neighbour_percentile, rows)
        deforming = measure >= cfg.deform_mm
    elif evidence is not None:
        # Every labelled neighbourhood calibrates the tests (most of a scene moves rigidly).
        judged = np.flatnonzero(known)
        stat, dof = departure_statistic(template, np.asarray(evidence.measured, float),
                                        evidence.departure_cov, nb, judged)
        scale = noise_scale(stat, dof)
        at = np.searchsorted(judged, rows)
        significant = (dof[at] > 0) & (stat[at] / scale > chi2.isf(cfg.significance,
                                                                    np.maximum(dof[at], 1.0)))
        if evidence.touched is not None:
            significant |= np.asarray(evidence.touched, bool)[rows]
        field_scale = field_noise_scale(template, registered, evidence.departure_cov, nb,
                                        judged)
        weights_cov = field_scale * np.asarray(evidence.departure_cov, float)
        measure = resolved_rms_mm(template, registered, weights_cov, nb, rows, cfg.deform_mm)
        near = (measure >= BORDERLINE_SHARE * cfg.deform_mm) & (measure < cfg.deform_mm)
        measured = Measured(evidence.measured, evidence.departure_cov, scale)
        measure[near] = np.fmax(measure[near], measured_rms_mm(template, measured, nb,
                                                               rows[near], cfg.deform_mm))
        deforming = significant & (measure >= cfg.deform_mm)
        floor[judged] = deform_floor_mm(registered, weights_cov, nb, judged, cfg.deform_mm)
    else:
        measure = rigid_rms_mm(template, registered, nb, rows)
        deforming = measure >= cfg.deform_mm
        floor[known] = cfg.deform_mm
    deformation[rows] = measure
    # A neighbourhood too small to measure (NaN) cannot show deformation: shifting.
    labels[rows] = np.where(deforming, DEFORMING, SHIFTING)
    return FrameClasses(labels=labels, displacement_mm=disp, deformation_mm=deformation,
                        floor_mm=floor)


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
        classify_frame(template, RegisteredFrame(registered[k],
                                                 None if transforms is None else transforms[k],
                                                 None if status is None else status[k]), nb, cfg)
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
