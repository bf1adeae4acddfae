"""Peer registration methods for benchmarks/registration.py, each run as its own program.

Binaries come from flags or environment variables (SURGRECON_BCPD, SURGRECON_FAST_RNRR);
without them a peer is "not available". Peers run as subprocesses on one thread
(OMP_NUM_THREADS=1, OPENBLAS_NUM_THREADS=1); their time is the subprocess's CPU time (user +
system: the machine is shared, so wall time would measure the others' load), i.e. it
includes process start-up and their text/mesh file reading and writing (input files are
written before the clock starts). Coordinates are written in mm.

- BCPD (Hirose): `bcpd -x target -y source -w0.1 -A -sy -q`, its defaults otherwise (lambda
  2, beta 2, similarity + non-rigid, tolerance 1e-4, at most 500 loops, each cloud
  normalised separately); w = 0.1 because its default w = 0 assumes no outliers; -A (its
  documented default acceleration: Nystrom + KD-tree) because its README asks for an
  acceleration above several thousand points (without it a 5k pair takes > 300 s here).
  With colour, each cloud is 6-D: x, y, z in mm and R, G, B (0..1) times `colour_mm`
  (default 20 mm per unit of RGB: a full colour difference weighs like 20 mm of distance;
  chosen on tuning seed 0 of the tissue among 5 / 20 / 50, medians 3.3 / 0.40 / 2.0 mm vs
  0.49 mm without colour); the registered source is the first three columns.
- Fast_RNRR (Yao et al.): `Fast_RNRR source.obj target.obj out_`, its built-in defaults; it
  needs a source triangle mesh: a Delaunay triangulation over the dome's plane for the
  tissue (a height field), otherwise a mesh of local tangent-plane Delaunay umbrellas
  (`umbrella_faces`) with consistently propagated normals. The target is written
  as a point cloud (vertices only). Colour is not used.
- pycpd / probreg (Python, optional `bench` extra) run in a subprocess of this interpreter.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import breadth_first_order
from scipy.spatial import Delaunay, cKDTree

MM = 1e-3
ONE_THREAD = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


class PeerError(RuntimeError):
    """A peer exited with an error, timed out or wrote no result."""


def _children_cpu() -> float:
    t = os.times()
    return t.children_user + t.children_system


def run_timed(cmd: list[str], cwd: Path, cap_s: float) -> float:
    """Run cmd on one thread in cwd; its CPU time (user + system, s). Raises PeerError."""
    env = {**os.environ, **ONE_THREAD}
    t0 = _children_cpu()
    try:
        proc = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, timeout=cap_s)
    except subprocess.TimeoutExpired as exc:
        raise PeerError(f"capped at {cap_s:.0f} s") from exc
    wall = _children_cpu() - t0
    if proc.returncode != 0:
        tail = (proc.stderr or proc.stdout).decode(errors="replace").strip().splitlines()[-1:]
        raise PeerError(f"exit {proc.returncode}: {' '.join(tail)[:80]}")
    return wall


# ----------------------------------------------------------------------------- BCPD
def run_bcpd(binary: str, source: np.ndarray, target: np.ndarray,
             source_rgb: np.ndarray | None, target_rgb: np.ndarray | None,
             cap_s: float, colour_mm: float = 20.0) -> tuple[np.ndarray, float]:
    """(registered source (N, 3) m, wall s) from BCPD; colour as 3 extra coordinates."""
    x, y = target / MM, source / MM
    if source_rgb is not None and target_rgb is not None:
        x, y = np.c_[x, colour_mm * target_rgb], np.c_[y, colour_mm * source_rgb]
    with tempfile.TemporaryDirectory(prefix="bcpd_") as tmp:
        d = Path(tmp)
        np.savetxt(d / "X.txt", x, delimiter="\t", fmt="%.6f")
        np.savetxt(d / "Y.txt", y, delimiter="\t", fmt="%.6f")
        wall = run_timed([binary, "-x", "X.txt", "-y", "Y.txt", "-w0.1", "-A", "-o", "out_",
                          "-sy", "-q"], d, cap_s)
        out = d / "out_y.txt"
        if not out.exists():
            raise PeerError("no out_y.txt")
        reg = np.loadtxt(out, ndmin=2)[:, :3] * MM
    if reg.shape != source.shape:
        raise PeerError(f"result shape {reg.shape}")
    return reg, wall


# ----------------------------------------------------------------------------- Fast_RNRR
def _spacing(points: np.ndarray) -> float:
    return float(np.mean(cKDTree(points).query(points, k=2)[0][:, 1]))


def heightfield_faces(points: np.ndarray) -> np.ndarray:
    """Triangles (F, 3) of a Delaunay triangulation over the points' best-fit plane (rim
    slivers kept: Fast_RNRR needs every vertex in a face), wound along the plane normal."""
    c = points - points.mean(0)
    axes = np.linalg.svd(c, full_matrices=False)[2]
    tri = Delaunay(c @ axes[:2].T).simplices
    return _orient(points, tri, axes[2])


def _orient(points: np.ndarray, faces: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Faces (F, 3) flipped where their winding disagrees with normals ((3,) or (F, 3))."""
    v = points[faces]
    flip = (np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]) * normals).sum(1) < 0
    faces = faces.copy()
    faces[flip] = faces[flip][:, [0, 2, 1]]
    return faces


def oriented_normals(points: np.ndarray, k: int = 12) -> tuple[np.ndarray, np.ndarray]:
    """PCA normals (N, 3) made consistent by propagation along a breadth-first tree of the
    kNN graph, and the kNN indices (N, k) (self first)."""
    idx = cKDTree(points).query(points, k=k)[1]
    nb = points[idx] - points[idx].mean(1, keepdims=True)
    normals = np.linalg.eigh(np.einsum("nki,nkj->nij", nb, nb))[1][:, :, 0]
    n = len(points)
    graph = coo_matrix((np.ones(idx[:, 1:].size), (np.repeat(np.arange(n), k - 1),
                                                    idx[:, 1:].ravel())), shape=(n, n))
    for root in range(n):  # one breadth-first pass per connected component
        if np.isnan(normals[root, 0]):
            continue
        order, pred = breadth_first_order(graph, root, directed=False)
        for i in order[1:]:  # parents are visited (and flipped) before their children
            if normals[i] @ normals[pred[i]] < 0:
                normals[i] = -normals[i]
        if len(order) == n:
            break
    return normals, idx


def umbrella_faces(points: np.ndarray, k: int = 12) -> np.ndarray:
    """A triangle mesh (F, 3) of a cloud sampled from a smooth surface: each point's
    neighbours are projected on its tangent plane and Delaunay-triangulated; triangles are
    wound along the propagated normals and kept, most agreed-on first, while the mesh stays
    edge-manifold."""
    normals, idx = oriented_normals(points, k)
    faces = []
    for i in range(len(points)):  # benchmark input preparation, not a hot path
        e1 = np.cross(normals[i], [1.0, 0, 0] if abs(normals[i, 0]) < 0.9 else [0, 1.0, 0])
        e1 /= np.linalg.norm(e1)
        local = (points[idx[i]] - points[i]) @ np.c_[e1, np.cross(normals[i], e1)]
        tri = Delaunay(local).simplices
        faces.append(idx[i][tri[(tri == 0).any(1)]])
    all_faces = _orient(points, np.concatenate(faces), np.repeat(
        normals, [len(f) for f in faces], axis=0))
    _, first, count = np.unique(np.sort(all_faces, 1), axis=0, return_index=True,
                                return_counts=True)
    order = np.argsort(-count, kind="stable")  # most agreed first
    return manifold_subset(all_faces[first[order]])


def manifold_subset(faces: np.ndarray) -> np.ndarray:
    """Greedily keep faces (in the given order) whose directed edges are new and whose edges
    have fewer than two faces, so that the mesh stays edge-manifold and consistently wound."""
    directed: set[tuple[int, int]] = set()
    uses: dict[tuple[int, int], int] = {}
    kept = []
    for f in faces.tolist():  # benchmark input preparation, not a hot path
        edges = [(f[0], f[1]), (f[1], f[2]), (f[2], f[0])]
        if any(e in directed or uses.get((min(e), max(e)), 0) >= 2 for e in edges):
            continue
        for e in edges:
            directed.add(e)
            uses[(min(e), max(e))] = uses.get((min(e), max(e)), 0) + 1
        kept.append(f)
    return np.asarray(kept, dtype=np.int64)


def write_obj(path: Path, points_mm: np.ndarray, faces: np.ndarray | None) -> None:
    lines = [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in points_mm]
    if faces is not None:
        lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces]
    path.write_text("\n".join(lines) + "\n")


def read_obj_vertices(path: Path) -> np.ndarray:
    rows = [ln.split()[1:4] for ln in path.read_text().splitlines() if ln.startswith("v ")]
    return np.asarray(rows, float)


def run_fast_rnrr(binary: str, source: np.ndarray, target: np.ndarray, height_field: bool,
                  cap_s: float) -> tuple[np.ndarray, float]:
    """(registered source (N, 3) m, wall s) from Fast_RNRR on a mesh of the source."""
    faces = heightfield_faces(source) if height_field else umbrella_faces(source)
    with tempfile.TemporaryDirectory(prefix="rnrr_") as tmp:
        d = Path(tmp)
        write_obj(d / "source.obj", source / MM, faces)
        write_obj(d / "target.obj", target / MM, None)
        wall = run_timed([binary, "source.obj", "target.obj", str(d / "out_")], d, cap_s)
        out = d / "out_res.obj"
        if not out.exists():
            raise PeerError("no out_res.obj")
        reg = read_obj_vertices(out) * MM
    if len(reg) < len(source):  # OpenMesh appends copies of vertices at non-manifold faces
        raise PeerError(f"result shape {reg.shape}")
    return reg[: len(source)], wall


# ----------------------------------------------------------------------------- Python peers
PY_PEER = """
import sys, numpy as np
src, tgt, out, name = sys.argv[1:5]
s, t = np.load(src), np.load(tgt)
if name == "pycpd":
    from pycpd import DeformableRegistration
    reg = DeformableRegistration(X=t, Y=s, alpha=2.0, beta=2.0, w=0.1).register()[0]
else:
    from probreg import bcpd, cpd
    if name == "probreg-cpd":
        tf = cpd.registration_cpd(s, t, tf_type_name="nonrigid", w=0.1).transformation
    else:
        tf = bcpd.registration_bcpd(s, t, w=0.1)
    reg = tf.transform(s)
np.save(out, np.asarray(reg))
"""


def run_python_peer(name: str, source: np.ndarray, target: np.ndarray,
                    cap_s: float) -> tuple[np.ndarray, float]:
    """(registered (N, 3) m, wall s) from pycpd / probreg-cpd / probreg-bcpd (mm, w = 0.1)."""
    with tempfile.TemporaryDirectory(prefix="pypeer_") as tmp:
        d = Path(tmp)
        np.save(d / "s.npy", source / MM)
        np.save(d / "t.npy", target / MM)
        wall = run_timed([sys.executable, "-c", PY_PEER, "s.npy", "t.npy", "r.npy", name], d,
                         cap_s)
        return np.load(d / "r.npy") * MM, wall


Peer = Callable[..., tuple[np.ndarray, float]]
