"""Tool–tissue contact and indentation measured from the reconstruction (issue 17): the
geometry behind vision-based force estimation (Su et al. 2019, introduction). Pure numpy, no
I/O; lengths in metres in and out (core/measure/indentation.py assembles the per-frame figures, mm).

Inputs per frame k: the frame-0 template p_i (N, 3), its registered positions x_i (N, 3), their
uncertainty σ_i (N,) (3D RMS from the run's noise model, None for noiseless ground truth),
the tool-tip pose (4, 4) and the template's neighbourhoods (core/classify/rules.py).

- compensated displacement u_i = x_i − (R_i p_i + t_i), (R_i, t_i) the best rigid motion of
  the point's *ring*: template points between ring_inner_mm and ring_outer_mm from p_i at
  frame 0 (fitted at ring centres, a voxel subsample of the template, and blended over the
  3 nearest: rings of neighbouring points are nearly the same). Breathing shifts the ring
  with the point and is removed; an indentation narrower than the ring stays. The fit is
  robust (Tukey's biweight, which gives members moving otherwise no weight at all, scale
  SCALE_SIGMAS x the members' median σ, 0.2 mm at least; iteratively reweighted from the
  least-squares fit or the members' median shift, whichever more members follow), so a
  ring crossing the edge of a breathing region or the dent's tail follows its majority
  (a softer loss, or the least-squares start alone, let a ring half over a breathing ramp
  turn by 3-4° where the still part it centres on did not turn).
  σ_u² = σ_i² + σ̄²/n_eff (σ̄² the members' mean variance, n_eff their effective number).
- the geometry of the tool pressing the surface (clearance, the points under the tip, the
  deformed region, its area and volume): core/measure/dent.py.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..classify.rules import Neighbourhoods
from ..geometry.poses import nearest_rotation

SCALE_FLOOR_M = 2e-4  # robust scale of the ring fit at least 0.2 mm (noiseless truth)
SCALE_SIGMAS = 4.0  # ... else this many times the members' median σ
IRLS_ITERATIONS = 5
MIN_RING = 6  # ring members needed for a rigid fit worth the name
BLEND = 3  # ring centres whose motions carry a point


@dataclass(frozen=True)
class Rings:
    """Rings of C centres (a voxel subsample of the template, spaced so that a ring holds
    about `members` of them): centres (C,) template indices, index (C, K) ring members
    (template indices, padded with the centre) and mask (C, K) bool; every template point
    takes the rigid motion of its BLEND nearest centres, nearest (N, BLEND) centre numbers
    with inverse-distance weights (N, BLEND) summing to 1."""

    centres: np.ndarray
    index: np.ndarray
    mask: np.ndarray
    nearest: np.ndarray
    weights: np.ndarray


@dataclass(frozen=True)
class CompensatedField:
    """One frame: displacement (N, 3) m after removing the rings' rigid motion (NaN:
    unknown), sigma (N,) m its 3D RMS uncertainty (NaN without a noise model), each point's
    rotation (N, 3, 3) (its nearest centre's), and the rings' motions: centre_rotation
    (C, 3, 3), centre_translation (C, 3) m, centre_used (C,) bool (enough members)."""

    displacement: np.ndarray
    sigma: np.ndarray
    rotation: np.ndarray
    centre_rotation: np.ndarray
    centre_translation: np.ndarray
    centre_used: np.ndarray


@dataclass(frozen=True)
class ReferenceSurface:
    """The frame-0 surface frames are measured against: points (N, 3) m, their unit normals
    (N, 3), neighbourhoods (core/classify/rules.py) and rings (`surrounding_rings`)."""

    points: np.ndarray
    normals: np.ndarray
    nb: Neighbourhoods
    rings: Rings


def voxel_subsample(points: np.ndarray, spacing_m: float) -> np.ndarray:
    """Indices (M,) of one point (the first) per cube of `spacing_m` of points (N, 3) m."""
    keys = np.floor(np.asarray(points, float) / spacing_m).astype(np.int64)
    _, first = np.unique(keys, axis=0, return_index=True)
    return np.sort(first)


def surrounding_rings(points: np.ndarray, inner_mm: float, outer_mm: float,
                      members: int) -> Rings:
    """Rings (see `Rings`) of template points (N, 3) m: for each centre, up to `members`
    centres between `inner_mm` and `outer_mm` from it at frame 0, spread over the ring."""
    points = np.asarray(points, float)
    inner, outer = inner_mm * 1e-3, outer_mm * 1e-3
    centres = voxel_subsample(points, float(np.sqrt(np.pi * (outer**2 - inner**2) / members)))
    c = len(centres)
    k = int(min(c, 4 * members))
    tree = cKDTree(points[centres])
    dist, idx = tree.query(points[centres], k=k, distance_upper_bound=outer)
    dist, idx = dist.reshape(c, k), idx.reshape(c, k)
    valid = np.isfinite(dist) & (dist >= inner)
    packed = np.take_along_axis(idx, np.argsort(~valid, axis=1, kind="stable"), 1)
    count = valid.sum(1)[:, None]
    j = np.arange(members)[None, :]
    pos = np.minimum(np.where(count > members, (j * count) // members, j), k - 1)
    mask = j < np.minimum(count, members)
    chosen = centres[np.minimum(np.take_along_axis(packed, pos, 1), c - 1)]
    blend = min(BLEND, c)
    dist, nearest = tree.query(points, k=blend)
    dist, nearest = dist.reshape(len(points), blend), nearest.reshape(len(points), blend)
    weights = 1.0 / np.maximum(dist, 1e-4)
    return Rings(centres, np.where(mask, chosen, centres[:, None]), mask, nearest,
                 weights / weights.sum(1, keepdims=True))


def surface_normals(points: np.ndarray, nb: Neighbourhoods, viewpoint: np.ndarray) -> np.ndarray:
    """Unit normals (N, 3) of template points (N, 3) m: the least-variance direction of each
    neighbourhood, turned towards `viewpoint` (3,) m (e.g. the cameras: out of the tissue)."""
    index, mask = nb.members()
    w = mask.astype(float)
    q = points[index]
    mu = np.einsum("nk,nki->ni", w, q) / w.sum(1)[:, None]
    d = q - mu[:, None, :]
    _, vectors = np.linalg.eigh(np.einsum("nk,nki,nkj->nij", w, d, d))
    normals = vectors[:, :, 0]
    flip = ((np.asarray(viewpoint, float) - points) * normals).sum(1) < 0
    return np.where(flip[:, None], -normals, normals)


def compensated_field(reference: np.ndarray, moved: np.ndarray, rings: Rings,
                      sigma: np.ndarray | None = None) -> CompensatedField:
    """The rigid-motion-compensated displacement (module docstring) of every point from
    reference (N, 3) m (frame 0) to moved (N, 3) m (NaN: unknown), with σ (N,) m 3D RMS of
    the moved positions (including the template's) or None (noiseless). Each ring's motion
    is fitted at its centre; a point is carried by its nearest centres' motions, blended."""
    reference, moved = np.asarray(reference, float), np.asarray(moved, float)
    src, dst = reference[rings.index], moved[rings.index]
    keep = rings.mask & np.isfinite(dst).all(-1)
    member_sigma = np.zeros(rings.index.shape)
    if sigma is not None:
        member_sigma = np.asarray(sigma, float)[rings.index]
        keep &= np.isfinite(member_sigma)
        member_sigma = np.where(keep, member_sigma, 0.0)
    w = np.where(keep, 1.0 / (member_sigma**2 + SCALE_FLOOR_M**2), 0.0)
    used = keep.sum(1) >= MIN_RING
    scale = np.full(len(src), SCALE_FLOOR_M)
    if used.any() and sigma is not None:
        typical = np.nanmedian(np.where(keep, member_sigma, np.nan)[used], axis=1)
        scale[used] = np.maximum(SCALE_SIGMAS * typical, SCALE_FLOOR_M)
    dst = np.where(keep[..., None], dst, 0.0)
    R, t = _robust_start(src, dst, keep, w, used, scale)
    weight = w
    for _ in range(IRLS_ITERATIONS):
        r2 = (_residual(src, dst, keep, R, t) ** 2).sum(-1) / scale[:, None] ** 2
        weight = w * np.clip(1.0 - r2, 0.0, None) ** 2  # Tukey's biweight
        few = (weight > 0).sum(1) < MIN_RING  # too few left: Cauchy weights instead
        weight[few] = w[few] / (1.0 + r2[few])
        R, t = _fit_rigid(src, dst, np.where(used[:, None], weight, 1.0))
    # a point carried by its nearest centres' motions (NaN where none could be fitted)
    near, blend = rings.nearest, rings.weights
    carried = np.einsum("nbij,nj->nbi", R[near], reference) + t[near]
    ok = used[near]
    blend = np.where(ok, blend, 0.0)
    total = blend.sum(1)
    with np.errstate(invalid="ignore", divide="ignore"):
        predicted = np.einsum("nb,nbi->ni", blend, carried) / total[:, None]
    u = moved - predicted
    u[total <= 0] = np.nan
    out_sigma = np.full(len(reference), np.nan)
    if sigma is not None:
        weight = np.where(keep, weight, 0.0)
        wsum = np.maximum(weight.sum(1), 1e-300)
        n_eff = np.maximum(wsum**2 / np.maximum((weight**2).sum(1), 1e-300), 1.0)
        fit_var = (weight * member_sigma**2).sum(1) / wsum / n_eff  # (C,)
        out_sigma = np.sqrt(np.asarray(sigma, float) ** 2 + fit_var[near[:, 0]])
        out_sigma[total <= 0] = np.nan
    return CompensatedField(u, out_sigma, R[near[:, 0]], R, t, used)


def _residual(src: np.ndarray, dst: np.ndarray, keep: np.ndarray, R: np.ndarray,
              t: np.ndarray) -> np.ndarray:
    """Members' residuals (C, K, 3) m of the rigid motions (R, t) (0 for members left out)."""
    return np.where(keep[..., None], dst - np.matmul(src, R.transpose(0, 2, 1))
                    - t[:, None, :], 0.0)


def _robust_start(src: np.ndarray, dst: np.ndarray, keep: np.ndarray, w: np.ndarray,
                  used: np.ndarray, scale: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per ring, the better start of two, the one more members follow within the scale:
    the least-squares rigid fit (right when all move rigidly, even turning) or the
    members' median shift (right when a minority moves otherwise, e.g. breathing)."""
    R0, t0 = _fit_rigid(src, dst, np.where(used[:, None], w, 1.0))
    shift = np.zeros(t0.shape)
    if used.any():
        shift[used] = np.nanmedian(np.where(keep[used][..., None], dst[used] - src[used],
                                            np.nan), axis=1)
    R1 = np.tile(np.eye(3), (len(src), 1, 1))
    support = [(np.linalg.norm(_residual(src, dst, keep, R, t), axis=-1) < scale[:, None])
               .sum(1) for R, t in ((R0, t0), (R1, shift))]
    median_better = support[1] > support[0]
    return (np.where(median_better[:, None, None], R1, R0),
            np.where(median_better[:, None], shift, t0))


def _fit_rigid(src: np.ndarray, dst: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted least-squares rigid fits dst ≈ R src + t of (C, K, 3) members with weights
    (C, K): R (C, 3, 3), t (C, 3) (core/geometry.fit_rigid with batched matrix products)."""
    wn = w / np.maximum(w.sum(1, keepdims=True), 1e-300)
    mu_s = np.einsum("ck,cki->ci", wn, src)
    mu_d = np.einsum("ck,cki->ci", wn, dst)
    S = np.matmul((dst - mu_d[:, None, :]).transpose(0, 2, 1) * wn[:, None, :],
                  src - mu_s[:, None, :])
    R = nearest_rotation(S)
    return R, mu_d - np.einsum("cij,cj->ci", R, mu_s)
