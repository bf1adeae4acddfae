"""Ground-truth motion fields for classification/evaluation tests (no registration needed).

`true_field` maps template-like points onto the simulator's true surface, follows them
through the frames and fits each point a per-point affine from the true motion of the
surface around it: exactly what a perfect registration would return.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from surgrecon_cli.core.evaluate.scoring import SurfaceMapping, map_to_surface


@dataclass(frozen=True)
class TrueField:
    """template (N, 3); registered (T, N, 3); transforms (T, N, 3, 4); labels (T, N) GT labels
    of the nearest vertex; mapping onto the frame-0 surface."""

    template: np.ndarray
    registered: np.ndarray
    transforms: np.ndarray
    labels: np.ndarray
    mapping: SurfaceMapping


def fit_affines(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Least-squares affines (M, 3, 4) with dst ~ A src + t, for src/dst (M, K, 3)."""
    ms, md = src.mean(1, keepdims=True), dst.mean(1, keepdims=True)
    S, D = src - ms, dst - md
    cov = np.einsum("mki,mkj->mij", S, S) + 1e-12 * np.eye(3)
    cross = np.einsum("mki,mkj->mij", D, S)
    A = cross @ np.linalg.inv(cov)
    t = md[:, 0] - np.einsum("mij,mj->mi", A, ms[:, 0])
    return np.concatenate([A, t[:, :, None]], axis=2)


def true_field(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray, labels: np.ndarray,
               fit_vertices: int = 12) -> TrueField:
    """Perfect registration of template points (N, 3) under the true motion vertices (T, V, 3).

    Each point's affine is fitted to its `fit_vertices` nearest surface vertices and then
    re-anchored so that T_i p̃_i = p_i + (true motion of its material point): the template's
    own error (its distance to the surface) is carried along, not corrected."""
    mapping = map_to_surface(points, vertices[0], faces)
    surface0 = mapping.follow(vertices[0], faces)
    _, near = cKDTree(vertices[0]).query(surface0, k=fit_vertices)
    n = len(points)
    ph = np.concatenate([points, np.ones((n, 1))], axis=1)
    regs, transforms = [], []
    for frame in vertices:
        moved = points + mapping.follow(frame, faces) - surface0
        T = fit_affines(vertices[0][near], frame[near])
        T[:, :, 3] += moved - np.einsum("nij,nj->ni", T, ph)
        regs.append(moved)
        transforms.append(T)
    truth = labels[:, mapping.nearest_vertex(faces)]
    return TrueField(points, np.stack(regs), np.stack(transforms), truth, mapping)
