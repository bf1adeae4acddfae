"""How far each neighbourhood departs from one rigid motion, measured against the run's noise
(step 3 of core/classify/rules.py): the chi-square departure statistic of its measured
positions, the frame's noise scales, the rigid-fit RMS of its registered positions with
each direction counted by how well it is measured, the same of its measured positions less
what their noise explains, and the smallest departure along the least-known directions that
the registered RMS counts as deformation (the labels' floor). Pure numpy; no I/O."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
from scipy.stats import chi2

from .labels import rigid_fit_residuals

if TYPE_CHECKING:
    from .rules import Neighbourhoods

SIGMA_FLOOR_M = 1e-6  # ours: a σ below a micrometre is numerical, not a measurement
# Ours: the noise scale is read at the lower quartile of the neighbourhoods' departures, so
# that up to 3/4 of them may truly deform (a stereo endoscope close to a dent sees mostly
# the dent and its 5 mm surroundings; the median read too much deformation as noise there).
SCALE_QUANTILE = 0.25
# Ours: the registered field's scale (`field_noise_scale`) is read on this many labelled
# neighbourhoods at most, spread evenly (against all of them it moves by up to a third in a
# frame, where it is 0.06-1 on `default` and the sample: the macro-F1 of the sample and the
# 9 `default` tuning runs moves by at most 0.002; 512 cost 60-80 ms a
# frame at 1,350-2,300 points, 256 half that), and is kept above FIELD_SCALE_FLOOR (a field
# without scatter: the weights become the plain RMS's).
FIELD_SAMPLE = 256
FIELD_SCALE_FLOOR = 1e-3
# Ours: the field's scale is read at the median, not at the noise scale's lower quartile: a
# scale below 1 must err towards keeping the weights, and the lower quartile read the still
# regions of the shipped sample, whose dents' surroundings scatter more (its deforming
# precision 0.95 -> 0.88; at the median 0.94, recall 0.80 -> 0.82).
FIELD_QUANTILE = 0.5
# Ours: the registered field's dents at the tolerance are shallower than the truth (the
# regulariser smooths them: on the `default` tuning seeds s103 / s114 the lost dents'
# registered resolved RMS is 0.238 / 0.237 mm against a true rigid-fit RMS of 0.269 / 0.257
# mm), so where a neighbourhood's registered measure lies within this share of deform_mm
# and deform_mm, its measured positions are asked too (`measured_rms_mm`). 0.7 and 0.9 moved
# the mean macro-F1 of the tuning seeds by at most 0.003 from 0.8.
BORDERLINE_SHARE = 0.8


def departure_statistic(template: np.ndarray, positions: np.ndarray, covariance: np.ndarray,
                        nb: Neighbourhoods, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """How far each neighbourhood (the point `rows` (M,) and its neighbours) departs from one
    rigid motion, frame-0 template (N, 3) m to positions (N, 3) m with covariances
    (N, 3, 3) m²: S (M,) = Σ_j r_jᵀ Σ_j⁻¹ r_j and its degrees of freedom 3n − 6 (M,) (n
    usable members; S is chi-square with them under one rigid motion and the stated noise).
    The fit is weighted by each member's full precision Σ⁻¹ (`rigid_fit_residuals` with
    `information`), and S uses it too, so a direction the rig measures well counts fully
    even where depth is poor, and one member's depth error does not tilt the fit.
    Neighbourhoods with fewer than 3 usable members get dof <= 0."""
    if len(rows) == 0:
        return np.zeros(0), np.zeros(0)
    fit = _weighted_fit(template, positions, covariance, nb, rows, 0.0)
    return fit.energy, 3.0 * fit.keep.sum(1) - 6.0


def resolved_rms_mm(template: np.ndarray, positions: np.ndarray, covariance: np.ndarray,
                    nb: Neighbourhoods, rows: np.ndarray, deform_mm: float) -> np.ndarray:
    """The rigid-fit RMS (M,) mm of each neighbourhood (the point `rows` (M,) and its
    neighbours, frame-0 template (N, 3) m to positions (N, 3) m), each direction counted by
    how well it is measured: with W_j = (Σ_j + d²/3 I)⁻¹ (Σ_j (N, 3, 3) m² the member's noise
    covariance, d = `deform_mm` spread over three axes: a direction of noise σ counts by
    (d²/3) / (σ² + d²/3), alike where it is measured better than d/√3), RMS² = 3 Σ_j r_jᵀ
    W_j r_j / Σ_j tr W_j over the members' residuals r_j of the fit weighted by W_j.
    Without noise, or with the same isotropic noise for every member, it is the plain
    rigid-fit RMS; on a narrow stereo baseline a residual along a line of sight known to
    ±0.8 mm counts ~1/30 of one across it (±0.06 mm), and pure noise along it, however
    large, adds at most d²/2 to RMS². Not debiased: the registered field is smoother than
    its measurements (on the simulator, debiasing by their covariance cut deforming recall
    from 0.89 to 0.62). Members without a finite covariance are left out; fewer than 3
    left: NaN."""
    if len(rows) == 0:
        return np.zeros(0)
    fit = _weighted_fit(template, positions, covariance, nb, rows, (deform_mm * 1e-3) ** 2 / 3.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = np.sqrt(3.0 * fit.energy / fit.information()) * 1e3
    return np.where(fit.keep.sum(1) >= 3, out, np.nan)


@dataclass(frozen=True)
class Measured:
    """A frame's measured positions (N, 3) m with their covariances (N, 3, 3) m² as the
    noise model states them and the frame's noise scale (`noise_scale`, ≥ 1): the factor by
    which its neighbourhoods' departures show that model understating the noise."""

    positions: np.ndarray
    covariance: np.ndarray
    scale: float


def measured_rms_mm(template: np.ndarray, measured: Measured, nb: Neighbourhoods,
                    rows: np.ndarray, deform_mm: float) -> np.ndarray:
    """`resolved_rms_mm` (M,) mm of the neighbourhoods of `rows` (M,) on the measured
    positions, less what their noise explains: RMS² − 3 E / Σ_j tr W_j, where
    E = Σ_j tr(W_j c Σ_j) (3n − 6) / 3n is the energy that noise of covariance c Σ_j
    (Σ_j the stated covariance, c the frame's noise scale) leaves after the rigid fit of
    the n members. The departure itself, neither smoothed by the registration nor inflated
    by the noise as far as the noise model holds; 0 where the noise explains all of it,
    NaN with fewer than 3 members."""
    if len(rows) == 0:
        return np.zeros(0)
    covariance = np.asarray(measured.covariance, float)
    fit = _weighted_fit(template, np.asarray(measured.positions, float), covariance, nb, rows,
                        (deform_mm * 1e-3) ** 2 / 3.0)
    finite = np.where(np.isfinite(covariance), covariance, 0.0)
    noise_energy = measured.scale * np.einsum("nab,nba->n", fit.info, finite)
    n = fit.keep.sum(1)
    kept_dof = np.clip((3.0 * n - 6.0) / np.maximum(3.0 * n, 1.0), 0.0, 1.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        rms2 = 3.0 * (fit.energy - fit.member_sum(noise_energy) * kept_dof) / fit.information()
        out = np.sqrt(np.maximum(rms2, 0.0)) * 1e3
    return np.where(n >= 3, out, np.nan)


def deform_floor_mm(positions: np.ndarray, covariance: np.ndarray, nb: Neighbourhoods,
                    rows: np.ndarray, deform_mm: float) -> np.ndarray:
    """The rigid-fit RMS (M,) mm that a departure along every member's least-known
    direction (on a stereo rig, its line of sight) needs for `resolved_rms_mm` to count it
    as `deform_mm`: fit residuals r_j = D u_j read RMS² = 3 D² Σ_j λ_min(W_j) / Σ_j tr W_j,
    so D = deform_mm √(Σ_j tr W_j / (3 Σ_j λ_min(W_j))), W_j = (Σ_j + deform_mm²/3 I)⁻¹
    over the members of each neighbourhood (the point `rows` (M,) and its neighbours) the
    measure uses: a finite position (N, 3) and covariance (N, 3, 3) m². D is a bound on
    what is left after the neighbourhood's rigid fit, as deform_mm is (a shift or turn of
    the whole neighbourhood leaves nothing); `deform_mm` itself where every direction is
    measured better than deform_mm/√3; NaN with fewer than 3 members. The labels'
    sensitivity: a bend along the lines of sight whose rigid-fit RMS is below it is
    called shifting (deforming also needs the departure test)."""
    if len(rows) == 0:
        return np.zeros(0)
    index, mask = nb.members(rows)
    info = _precisions(covariance, (deform_mm * 1e-3) ** 2 / 3.0)
    least = np.linalg.eigvalsh(info)[:, 0]
    total = np.trace(info, axis1=1, axis2=2)
    keep = mask & (total[index] > 0) & np.isfinite(positions[index]).all(-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        floor = deform_mm * np.sqrt((total[index] * keep).sum(1)
                                    / (3.0 * (least[index] * keep).sum(1)))
    return np.where(keep.sum(1) >= 3, floor, np.nan)


class _WeightedFit(NamedTuple):
    """Each neighbourhood's rigid fit weighted by its members' information I_j: the energy
    Σ_j r_jᵀ I_j r_j (M,) of its residuals, its members (M, K) int and the ones used
    keep (M, K) bool, and I_j (N, 3, 3) m⁻² of every point."""

    energy: np.ndarray
    members: np.ndarray
    keep: np.ndarray
    info: np.ndarray

    def member_sum(self, per_point: np.ndarray) -> np.ndarray:
        """Σ over each neighbourhood's used members (M,) of a per-point value (N,)."""
        return (per_point[self.members] * self.keep).sum(1)

    def information(self) -> np.ndarray:
        """Σ_j tr I_j (M,) m⁻² over each neighbourhood's used members."""
        return self.member_sum(np.trace(self.info, axis1=1, axis2=2))


def _weighted_fit(template: np.ndarray, positions: np.ndarray, covariance: np.ndarray,
                  nb: Neighbourhoods, rows: np.ndarray, variance_m2: float) -> _WeightedFit:
    """The rigid fit of each neighbourhood (the point `rows` (M,) and its neighbours) from
    the frame-0 template (N, 3) m to positions (N, 3) m, weighted by every member's
    information I_j = (Σ_j + variance_m2 I)⁻¹ (`_precisions`, Σ_j covariance (N, 3, 3) m²)."""
    index, mask = nb.members(rows)
    info = _precisions(covariance, variance_m2)
    total = np.trace(info, axis1=1, axis2=2)
    residual, keep = rigid_fit_residuals(template, positions, index, mask, weights=total / 3.0,
                                         information=info)
    energy = (np.einsum("nkab,nkb->nka", info[index], residual) * residual).sum((1, 2))
    return _WeightedFit(energy, index, keep, info)


def _precisions(covariance: np.ndarray, variance_m2: float) -> np.ndarray:
    """(Σ + (variance_m2 + SIGMA_FLOOR_M²) I)⁻¹ (N, 3, 3) of covariances Σ (N, 3, 3) m²;
    zero (the member carries no weight) where Σ is not finite."""
    cov = np.asarray(covariance, float)
    usable = np.isfinite(cov).all((1, 2))
    info = np.zeros_like(cov)
    info[usable] = np.linalg.inv(cov[usable] + np.eye(3) * (variance_m2 + SIGMA_FLOOR_M**2))
    return info


def noise_scale(stat: np.ndarray, dof: np.ndarray) -> float:
    """The factor (>= 1) by which a frame's noise model understates the departures of its
    neighbourhoods from one rigid motion: the lower quartile over neighbourhoods (dof > 0)
    of S / the chi-square lower quartile of its dof (module docstring, step 3). 1 without
    any."""
    ratio = departure_ratio(stat, dof, SCALE_QUANTILE)
    return 1.0 if ratio is None else max(1.0, ratio)


def field_noise_scale(template: np.ndarray, registered: np.ndarray, covariance: np.ndarray,
                      nb: Neighbourhoods, judged: np.ndarray) -> float:
    """The factor (FIELD_SCALE_FLOOR..1) by which the registered field (N, 3) m departs from
    one rigid motion less than its covariances (N, 3, 3) m² predict: `departure_ratio` of
    the registered positions' `departure_statistic` at FIELD_QUANTILE, on up to
    FIELD_SAMPLE of the labelled neighbourhoods `judged` (M,), capped at 1. The registered
    field is the regularised solution: where it scatters less than its measurements'
    covariance says, that covariance overstates its noise (on the 6-camera simulator 7-100 %
    of it, in variance, at the median), and `resolved_rms_mm` weighted by it would discount
    real dents along the directions it calls poorly measured. Where it scatters more (narrow
    stereo baselines, real breathing), the excess is not the depth noise the weights model,
    and the covariance stays (module docstring, step 3). 1 without any neighbourhood."""
    if len(judged) > FIELD_SAMPLE:
        judged = judged[np.linspace(0, len(judged) - 1, FIELD_SAMPLE).round().astype(int)]
    ratio = departure_ratio(*departure_statistic(template, registered, covariance, nb,
                                                  judged), FIELD_QUANTILE)
    return 1.0 if ratio is None else min(1.0, max(FIELD_SCALE_FLOOR, ratio))


def departure_ratio(stat: np.ndarray, dof: np.ndarray, quantile: float) -> float | None:
    """The `quantile` over neighbourhoods (dof > 0) of S (M,) / the chi-square `quantile`
    of its dof (M,): 1 where S follows the chi-square law; None without any."""
    ok = (dof > 0) & np.isfinite(stat)
    if not ok.any():
        return None
    return float(np.quantile(stat[ok] / chi2.ppf(quantile, dof[ok]), quantile))
