"""Scoring against the simulator's ground truth (io/logs/ground_truth.py).

Each template point is mapped to the nearest point of the true surface at frame 0
(triangle + barycentric coordinates); that material point is followed through the frames
and compared with the run's estimate. Distances are returned in metres; reports show mm.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..classify.labels import CLASS_NAMES, UNKNOWN


@dataclass(frozen=True)
class SurfaceMapping:
    """Points mapped onto a mesh: face (N,) int, barycentric (N, 3), distance (N,) m."""

    face: np.ndarray
    bary: np.ndarray
    distance: np.ndarray

    def follow(self, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
        """Positions (N, 3) of the mapped material points on a mesh state vertices (V, 3)."""
        return np.einsum("nk,nkd->nd", self.bary, vertices[faces[self.face]])

    def nearest_vertex(self, faces: np.ndarray) -> np.ndarray:
        """Index (N,) of the mesh vertex with the largest barycentric weight."""
        return faces[self.face, np.argmax(self.bary, axis=1)]


def closest_point_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray):
    """Closest points on triangles (a, b, c) to points p, all (M, 3); returns (M, 3) points
    and (M, 3) barycentric weights. Region tests of Ericson, Real-Time Collision Detection 5.1.5."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = (ab * ap).sum(1), (ac * ap).sum(1)
    bp = p - b
    d3, d4 = (ab * bp).sum(1), (ac * bp).sum(1)
    cp = p - c
    d5, d6 = (ab * cp).sum(1), (ac * cp).sum(1)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    bary = np.zeros((len(p), 3))
    done = np.zeros(len(p), bool)

    def take(mask, w):
        nonlocal done
        m = mask & ~done
        bary[m] = w[m]
        done |= m

    one = np.ones(len(p))
    zero = np.zeros(len(p))
    with np.errstate(divide="ignore", invalid="ignore"):
        take((d1 <= 0) & (d2 <= 0), np.stack([one, zero, zero], 1))
        take((d3 >= 0) & (d4 <= d3), np.stack([zero, one, zero], 1))
        take((d6 >= 0) & (d5 <= d6), np.stack([zero, zero, one], 1))
        v = d1 / (d1 - d3)
        take((vc <= 0) & (d1 >= 0) & (d3 <= 0), np.stack([1 - v, v, zero], 1))
        w = d2 / (d2 - d6)
        take((vb <= 0) & (d2 >= 0) & (d6 <= 0), np.stack([1 - w, zero, w], 1))
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        take((va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0), np.stack([zero, 1 - w, w], 1))
        denom = 1.0 / (va + vb + vc)
        v, w = vb * denom, vc * denom
        take(np.ones(len(p), bool), np.stack([1 - v - w, v, w], 1))
    closest = bary[:, :1] * a + bary[:, 1:2] * b + bary[:, 2:3] * c
    return closest, bary


def map_to_surface(
    points: np.ndarray, vertices: np.ndarray, faces: np.ndarray, candidates: int = 12
) -> SurfaceMapping:
    """Nearest point on the mesh (vertices (V, 3), faces (F, 3)) for every point (N, 3).

    Candidate triangles are the `candidates` nearest by centroid; exact on smooth meshes
    whose triangles are small compared with the query distance.
    """
    centroids = vertices[faces].mean(1)
    k = min(candidates, len(faces))
    _, cand = cKDTree(centroids).query(points, k=k)
    cand = cand.reshape(len(points), k)
    tri = vertices[faces[cand.ravel()]]
    rep = np.repeat(points, k, axis=0)
    closest, bary = closest_point_on_triangles(rep, tri[:, 0], tri[:, 1], tri[:, 2])
    dist = np.linalg.norm(closest - rep, axis=1).reshape(len(points), k)
    best = np.argmin(dist, axis=1)
    rows = np.arange(len(points))
    return SurfaceMapping(
        face=cand[rows, best],
        bary=bary.reshape(len(points), k, 3)[rows, best],
        distance=dist[rows, best],
    )


def on_mesh_rim(mapping: SurfaceMapping, faces: np.ndarray) -> np.ndarray:
    """(N,) bool: mapped points whose nearest point lies on the mesh's rim (an edge of one
    face only, or a vertex of one), i.e. points beyond the mesh's border or over one of its
    holes: a truth with holes (depth maps, where stereo or a scanner measured nothing) maps
    them to the hole's rim, millimetres from where the surface is, an error of the truth."""
    faces = np.asarray(faces)
    edges = np.sort(np.stack([faces[:, [1, 2]], faces[:, [2, 0]], faces[:, [0, 1]]], 1), -1)
    pairs, inverse, count = np.unique(edges.reshape(-1, 2), axis=0, return_inverse=True,
                                      return_counts=True)
    rim_edge = (count == 1)[inverse.ravel()].reshape(len(faces), 3)  # edge opposite vertex j
    rim_vertex = np.zeros(int(faces.max()) + 1, bool)
    rim_vertex[pairs[count == 1].ravel()] = True
    zero = mapping.bary <= 0.0
    on_edge = (zero & rim_edge[mapping.face]).any(1)
    corner = zero.sum(1) == 2  # nearest point is a vertex: the one of weight 1
    at_vertex = corner & rim_vertex[faces[mapping.face, np.argmax(mapping.bary, 1)]]
    return on_edge | at_vertex


def distance_stats_mm(distances_m: np.ndarray) -> dict[str, float]:
    """Median / p95 / max / mean of distances, in millimetres (NaNs ignored)."""
    d = np.asarray(distances_m, float)
    d = d[np.isfinite(d)] * 1e3
    if d.size == 0:
        return {
            "count": 0,
            "median_mm": float("nan"),
            "p95_mm": float("nan"),
            "max_mm": float("nan"),
            "mean_mm": float("nan"),
        }
    return {
        "count": int(d.size),
        "median_mm": float(np.median(d)),
        "p95_mm": float(np.percentile(d, 95)),
        "max_mm": float(d.max()),
        "mean_mm": float(d.mean()),
    }


def label_scores(predicted: np.ndarray, truth: np.ndarray) -> dict:
    """Per-class precision/recall/F1, macro-F1 and the confusion matrix (rows: truth).

    Points predicted UNKNOWN count as misses for their true class.
    """
    predicted = np.asarray(predicted).ravel()
    truth = np.asarray(truth).ravel()
    classes = sorted(CLASS_NAMES)
    confusion = np.zeros((len(classes), len(classes) + 1), int)  # last column: unknown
    for i, t in enumerate(classes):
        row = predicted[truth == t]
        for j, p in enumerate(classes):
            confusion[i, j] = int((row == p).sum())
        confusion[i, -1] = int((row == UNKNOWN).sum())
    per_class = {}
    for i, t in enumerate(classes):
        tp = confusion[i, i]
        n_pred = confusion[:, i].sum()
        n_true = confusion[i].sum()
        precision = tp / n_pred if n_pred else float("nan")
        recall = tp / n_true if n_true else float("nan")
        f1 = 2 * precision * recall / (precision + recall) if (precision + recall) > 0 else 0.0
        per_class[CLASS_NAMES[t]] = {
            "precision": float(precision),
            "recall": float(recall),
            "f1": float(f1),
            "support": int(n_true),
        }
    f1s = [v["f1"] for v in per_class.values() if v["support"] > 0]
    return {
        "per_class": per_class,
        "macro_f1": float(np.mean(f1s)) if f1s else float("nan"),
        "confusion": confusion.tolist(),
        "confusion_axes": {
            "rows": [CLASS_NAMES[c] for c in classes],
            "cols": [CLASS_NAMES[c] for c in classes] + ["unknown"],
        },
    }
