"""What the target cloud says about itself: local planes, noise, strays, colour contrast.

Measured once per `register` call on the target G (M, 3), in the solver's normalised units:
- a local plane per target point (centroid and unit normal of its k nearest neighbours, PCA):
  the "supporting surface" residuals are measured against;
- the surface noise sigma: a robust scale (1.4826 x median) of every point's distance to the
  plane of its neighbours;
- strays: points farther from that plane than `STRAY_SIGMAS` x (noise, spacing): isolated
  outliers off the surface, never used as correspondences;
- the colour weight (position units per RGB unit) from how the colour changes between
  neighbours at two distances (below).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

PLANE_NEIGHBOURS = 10  # ours: neighbours of a target point's local plane
STRAY_SIGMAS = 4.0  # ours: a point this many noise scales off its neighbours' plane is a stray
MAD_SCALE = 1.4826  # median absolute value -> standard deviation for Gaussian data
# Colour weight (ours): a slide d along textured tissue costs COLOUR_GAIN * d in the matcher's
# joint position + colour distance; colour is used when, over the gate, the texture changes by
# more than COLOUR_SNR x its noise.
COLOUR_GAIN = 7.5
COLOUR_SNR = 2.0
COLOUR_NEIGHBOUR = 16  # the far neighbour of the two-distance contrast measurement
COLOUR_SAMPLES = 2000  # ours: target points the contrast is measured on (at most ~2x this)


@dataclass(frozen=True)
class TargetSurface:
    """Local planes (M, 3) centroids and (M, 3) unit normals; `stray` (M,) bool; `spacing`
    median nearest-neighbour distance and `noise` sigma off the local plane (normalised)."""

    centroid: np.ndarray
    normal: np.ndarray
    stray: np.ndarray
    spacing: float
    noise: float


def smallest_axis(cov: np.ndarray) -> np.ndarray:
    """(P, 3) unit eigenvectors of the smallest eigenvalue of symmetric cov (P, 3, 3), in
    closed form (trigonometric eigenvalues; ~2x faster than a batched eigh); rows where that
    is ill-conditioned (a repeated smallest eigenvalue: collinear or coincident points) from
    eigh."""
    q = np.trace(cov, axis1=1, axis2=2) / 3.0
    off = cov[:, 0, 1] ** 2 + cov[:, 0, 2] ** 2 + cov[:, 1, 2] ** 2
    diag = np.diagonal(cov, axis1=1, axis2=2) - q[:, None]
    p = np.sqrt(np.maximum(((diag**2).sum(axis=1) + 2.0 * off) / 6.0, 1e-300))
    eye = np.eye(3)
    b = (cov - q[:, None, None] * eye) / p[:, None, None]
    phi = np.arccos(np.clip(np.linalg.det(b) / 2.0, -1.0, 1.0)) / 3.0
    shifted = cov - (q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0))[:, None, None] * eye
    # the null direction of cov - lambda_min I: the largest cross product of two of its rows
    cands = np.stack([np.cross(shifted[:, 0], shifted[:, 1]),
                      np.cross(shifted[:, 0], shifted[:, 2]),
                      np.cross(shifted[:, 1], shifted[:, 2])], axis=1)
    norms = np.linalg.norm(cands, axis=2)
    best = np.argmax(norms, axis=1)
    rows = np.arange(len(cov))
    out = cands[rows, best] / np.maximum(norms[rows, best], 1e-300)[:, None]
    # a cross product of two rows of size ~trace is ~trace^2; far below: two eigenvalues
    # (nearly) equal the smallest and the null direction is not defined by the rows
    weak = norms[rows, best] <= 1e-8 * np.maximum(3.0 * q, 1e-300) ** 2
    if weak.any():
        out[weak] = np.linalg.eigh(cov[weak])[1][:, :, 0]
    return out


def local_planes(q: np.ndarray, nn: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centroid, normal and distance of each point to the plane of its neighbours nn (M, k)
    (the point itself excluded, so an off-surface point does not pull its own plane)."""
    nb = q[nn]
    centroid = nb.mean(axis=1)
    c = nb - centroid[:, None, :]
    normal = smallest_axis(np.matmul(c.transpose(0, 2, 1), c))
    off = np.abs(np.einsum("pi,pi->p", q - centroid, normal))
    return centroid, normal, off


def analyse_target(q: np.ndarray, tree: cKDTree) -> TargetSurface:
    """Planes, spacing, noise and strays of the target `q` (M, 3) indexed by `tree`."""
    m = len(q)
    k = min(PLANE_NEIGHBOURS + 1, m)
    d, nn = tree.query(q, k=k)
    spacing = float(np.median(d[:, 1])) if k > 1 else 0.0
    if k < 4:
        normal = np.tile([0.0, 0.0, 1.0], (m, 1))
        return TargetSurface(centroid=q.copy(), normal=normal, stray=np.zeros(m, bool),
                             spacing=spacing, noise=0.0)
    centroid, normal, off = local_planes(q, nn[:, 1:])
    noise = MAD_SCALE * float(np.median(off))
    stray = off > STRAY_SIGMAS * max(noise, 0.5 * spacing)
    return TargetSurface(centroid=centroid, normal=normal, stray=stray, spacing=spacing,
                         noise=noise)


def colour_weight(q: np.ndarray, rgb: np.ndarray, tree: cKDTree, use: np.ndarray,
                  reach: float) -> float:
    """Position units per RGB unit for the matcher, from the target's own texture.

    With colour gradient g (RGB units per length) and colour noise s per point, the colour
    difference of two points a distance r apart is c(r)^2 ~ g^2 r^2 + 2 s^2; the median
    difference to the 1st and the 16th neighbour gives g^2 and s^2. Colour can decide a
    match only if the texture changes by more than its noise over the distance a match may
    span (`reach`, the correspondence gate): g * reach > COLOUR_SNR * sqrt(2) s. Then the
    weight is COLOUR_GAIN / g (a slide d along the texture costs COLOUR_GAIN * d); otherwise
    0 (flat or noisy colour stays out). `use` (M,) bool: the points measured (not strays).
    """
    pts = np.flatnonzero(use)
    pts = pts[:: max(len(pts) // COLOUR_SAMPLES, 1)]  # medians: a spread subset is enough
    k = COLOUR_NEIGHBOUR + 1
    if len(pts) < 2 * k:
        return 0.0
    d, nn = tree.query(q[pts], k=k)
    r1, r2 = float(np.median(d[:, 1])), float(np.median(d[:, -1]))
    c1 = float(np.median(np.sum((rgb[pts] - rgb[nn[:, 1]]) ** 2, axis=1)))
    c2 = float(np.median(np.sum((rgb[pts] - rgb[nn[:, -1]]) ** 2, axis=1)))
    if not 0 < r1 < r2:
        return 0.0
    g = np.sqrt(max((c2 - c1) / (r2**2 - r1**2), 0.0))
    s = np.sqrt(max(c1 - g * g * r1**2, 0.0) / 2.0)
    if g <= 0 or g * reach <= COLOUR_SNR * np.sqrt(2.0) * s:
        return 0.0
    return float(COLOUR_GAIN / g)
