"""Colourless scanned-shape pairs with known truth (tests and benchmarks/registration.py).

Shapes (metres, real sizes, so that nothing can assume millimetre-sized data):
- `blob`: a bumpy closed blob ~80 mm across (an organ-like lump);
- `torus`: a bumpy torus ~140 mm across;
- `body`: a standing human-like body, ~1.7 m, a union of ellipsoids (torso, pelvis, head,
  neck, limbs segment by segment, hands, feet) with seeded proportions and arm pose;
- `limb`: an arm ~0.6 m long (a tube with muscle bulges and a narrowed elbow, capped).

Motions: a smooth non-rigid field (a few Gaussian radial-basis displacements) whose largest
displacement is `motion` times the shape's bounding-box diagonal (default 10 %); the limb
instead bends at the elbow (linear-blend skinning, distal end moving ~`motion` of the
diagonal) plus a mild field. The `rotation` pair adds a similarity: 90 degrees about a random
axis, scale 0.8, a shift of 10 % of the diagonal, after a mild (3 %) non-rigid field.

Scans: source and target are sampled independently and uniformly by area. The target is the
moved surface with Gaussian noise (`noise` x diagonal per axis) and spikes (`spikes` of its
points shot 2-8 % of the diagonal along their normal), optionally a single-view scan
(`partial`: back-facing points dropped, about half the surface). truth = motion(source).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from .pairs import Pair, diagonal, finish_pair, unit_vectors

Param = Callable[[np.ndarray, np.ndarray], np.ndarray]  # (u, v) in [0, 1] -> points (k, 3)
Field = Callable[[np.ndarray], np.ndarray]  # points (k, 3) -> moved points (k, 3)


# ----------------------------------------------------------------------------- surfaces
def _tangents(fn: Param, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Central-difference partial derivatives (k, 3) of a parametric surface at (u, v)."""
    h = 1e-5
    return ((fn(u + h, v) - fn(u - h, v)) / (2 * h), (fn(u, v + h) - fn(u, v - h)) / (2 * h))


def sample_parametric(fn: Param, n: int, rng: np.random.Generator,
                      sign: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """n points (n, 3) uniform by area on a parametric surface, with unit normals (n, 3)
    (d/du x d/dv, times `sign`). Rejection sampling on the area element, bounded on a grid."""
    g = np.linspace(0.004, 0.996, 64)
    gu, gv = (a.ravel() for a in np.meshgrid(g, g))
    bound = 1.3 * np.linalg.norm(np.cross(*_tangents(fn, gu, gv)), axis=1).max()
    pts, nrm = [], []
    got = 0
    while got < n:
        u, v = rng.uniform(0, 1, (2, 3 * n + 64))
        cross = np.cross(*_tangents(fn, u, v))
        area = np.linalg.norm(cross, axis=1)
        ok = rng.uniform(0, bound, len(u)) < area
        pts.append(fn(u[ok], v[ok]))
        nrm.append(sign * cross[ok] / area[ok, None])
        got += int(ok.sum())
    return np.concatenate(pts)[:n], np.concatenate(nrm)[:n]


def _sphere_dir(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Unit directions (k, 3): u -> polar angle 0..pi, v -> azimuth 0..2 pi (outward order)."""
    th, ph = np.pi * u, 2 * np.pi * v
    return np.c_[np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)]


def _bump_field(rng: np.random.Generator, k: int, amp: float, width: float) -> Callable:
    """A smooth random scalar function of unit directions: k Gaussian bumps of +-amp."""
    centres, amps = unit_vectors(rng, k), rng.uniform(-amp, amp, k)

    def f(d: np.ndarray) -> np.ndarray:
        return (amps * np.exp(-((d[:, None, :] - centres) ** 2).sum(2) / (2 * width**2))).sum(1)

    return f


def blob_surface(seed: int) -> Param:
    """A bumpy blob, radius ~40 mm (m): a sphere with lobes and bumps of a seed."""
    bumps = _bump_field(np.random.default_rng(seed + 11), 10, 0.22, 0.45)
    squash = np.random.default_rng(seed + 12).uniform(0.75, 1.2, 3)

    def fn(u: np.ndarray, v: np.ndarray) -> np.ndarray:
        d = _sphere_dir(u, v)
        return 0.04 * squash * d * (1 + bumps(d))[:, None]

    return fn


def torus_surface(seed: int) -> Param:
    """A bumpy torus (m): major radius 50 mm, tube radius ~18 mm with seeded ripples."""
    rng = np.random.default_rng(seed + 13)
    ph = rng.uniform(0, 2 * np.pi, 3)

    def fn(u: np.ndarray, v: np.ndarray) -> np.ndarray:
        a, b = 2 * np.pi * u, 2 * np.pi * v
        r = 0.018 * (1 + 0.2 * np.sin(3 * b + ph[0]) + 0.12 * np.sin(2 * a + 5 * b + ph[1])
                     + 0.1 * np.cos(7 * b + ph[2]))
        ring = 0.05 + r * np.cos(a)
        return np.c_[ring * np.cos(b), ring * np.sin(b), r * np.sin(a)]

    return fn


def limb_surface(seed: int) -> Param:
    """An arm along x (m): 0.6 m long, radius ~40 mm with muscle bulges, a narrowed elbow at
    x = 0, hemispherical caps. Surface of revolution of a seeded profile."""
    rng = np.random.default_rng(seed + 14)
    half, r0 = 0.3, 0.035
    bulge = rng.uniform(0.15, 0.3, 2)
    side = 2 * half
    total = np.pi * r0 + side  # profile arc length: cap, side, cap

    def fn(u: np.ndarray, v: np.ndarray) -> np.ndarray:
        s = u * total
        a0 = np.clip(s / r0, 0, np.pi / 2)  # left cap angle
        a1 = np.clip((s - np.pi * r0 / 2 - side) / r0, 0, np.pi / 2)  # right cap angle
        t = np.clip((s - np.pi * r0 / 2) / side, 0, 1)  # along the side, 0..1
        x = -half - r0 * np.cos(a0) + side * t + r0 * np.sin(a1)
        muscles = (bulge[0] * np.sin(2 * np.pi * np.minimum(t, 0.5)) ** 2
                   + bulge[1] * np.sin(2 * np.pi * np.maximum(t, 0.5)) ** 2)
        elbow = 0.12 * np.exp(-(((t - 0.5) / 0.05) ** 2))
        rho = r0 * np.sin(a0) * np.cos(a1) * (1 + muscles - elbow)
        ph = 2 * np.pi * v
        return np.c_[x, rho * np.cos(ph), rho * np.sin(ph)]

    return fn


@dataclass(frozen=True)
class Ellipsoid:
    centre: np.ndarray  # (3,) m
    axes: np.ndarray  # (3,) semi-axes m
    rotation: np.ndarray  # (3, 3) columns = the semi-axes' directions

    def param(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        return self.centre + (_sphere_dir(u, v) * self.axes) @ self.rotation.T

    def inside(self, p: np.ndarray) -> np.ndarray:
        q = ((p - self.centre) @ self.rotation) / self.axes
        return (q**2).sum(1) < 1 - 1e-9


def _segment(a: list[float], b: list[float], radius: float) -> Ellipsoid:
    """An elongated ellipsoid from joint a to joint b (m), overlapping both joints."""
    a_, b_ = np.asarray(a), np.asarray(b)
    axis = (b_ - a_) / np.linalg.norm(b_ - a_)
    helper = np.array([1.0, 0, 0]) if abs(axis[0]) < 0.9 else np.array([0, 1.0, 0])
    e1 = np.cross(axis, helper)
    e1 /= np.linalg.norm(e1)
    rot = np.c_[e1, np.cross(axis, e1), axis]
    return Ellipsoid((a_ + b_) / 2, np.array([radius, radius, 0.58 * np.linalg.norm(b_ - a_)]),
                     rot)


def body_parts(seed: int) -> list[Ellipsoid]:
    """A standing body (m, z up, facing +y) of a seed: proportions +-5 %, arm pose varied."""
    rng = np.random.default_rng(seed + 15)
    k = rng.uniform(0.95, 1.05)
    raise_l, raise_r = rng.uniform(0.05, 0.5, 2)  # arm abduction, radians
    eye = np.eye(3)
    parts = [Ellipsoid(np.array([0, 0, 1.25]) * k, np.array([0.17, 0.11, 0.30]) * k, eye),
             Ellipsoid(np.array([0, 0, 0.95]) * k, np.array([0.16, 0.11, 0.13]) * k, eye),
             Ellipsoid(np.array([0, 0.01, 1.68]) * k, np.array([0.085, 0.1, 0.115]) * k, eye),
             _segment([0, 0, 1.5 * k], [0, 0, 1.6 * k], 0.05 * k)]
    for sx, lift in ((-1, raise_l), (1, raise_r)):
        shoulder = np.array([0.2 * sx, 0, 1.45]) * k
        elbow = shoulder + 0.3 * k * np.array([sx * np.sin(lift), 0, -np.cos(lift)])
        wrist = elbow + 0.27 * k * np.array([sx * np.sin(lift * 0.7), 0.15, -np.cos(lift * 0.7)])
        hand = wrist + 0.1 * k * (wrist - elbow) / np.linalg.norm(wrist - elbow)
        hip, knee, ankle = (np.array([0.09 * sx, 0, h]) * k for h in (0.9, 0.5, 0.09))
        parts += [_segment(list(shoulder), list(elbow), 0.048 * k),
                  _segment(list(elbow), list(wrist), 0.04 * k),
                  _segment(list(wrist), list(hand), 0.03 * k),
                  _segment(list(hip), list(knee), 0.075 * k),
                  _segment(list(knee), list(ankle), 0.052 * k),
                  Ellipsoid(np.array([0.1 * sx, 0.06, 0.04]) * k,
                            np.array([0.045, 0.12, 0.04]) * k, eye)]
    return parts


def sample_union(parts: list[Ellipsoid], n: int,
                 rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """n points (n, 3) uniform by area on the outer surface of a union of ellipsoids, with
    outward normals: each part is sampled in proportion to its area, points inside another
    part are dropped, and n of the rest are kept at random."""
    areas = np.array([4 * np.pi * (np.prod(e.axes[[0, 1, 1, 2, 0, 2]].reshape(3, 2), 1) ** 1.6
                                   ).mean() ** (1 / 1.6) for e in parts])
    m = 2 * n
    while True:
        counts = rng.multinomial(m, areas / areas.sum())
        drawn = [sample_parametric(e.param, int(c), rng)
                 for e, c in zip(parts, counts, strict=True)]
        pts, nrm = [d[0] for d in drawn], [d[1] for d in drawn]
        owner = np.repeat(np.arange(len(parts)), counts)
        p, q = np.concatenate(pts), np.concatenate(nrm)
        hidden = np.zeros(len(p), bool)
        for i, e in enumerate(parts):
            hidden |= (owner != i) & e.inside(p)
        if (~hidden).sum() >= n:
            keep = rng.choice(np.flatnonzero(~hidden), n, replace=False)
            return p[keep], q[keep]
        m *= 2


Sampler = Callable[[int, np.random.Generator], tuple[np.ndarray, np.ndarray]]


def shape_sampler(shape: str, seed: int) -> Sampler:
    """Area-uniform sampler (n, rng) -> (points, outward normals) of a named seeded shape."""
    if shape == "body":
        parts = body_parts(seed)
        return lambda n, rng: sample_union(parts, n, rng)
    fn, sign = {"blob": (blob_surface, 1.0), "torus": (torus_surface, -1.0),
                "limb": (limb_surface, -1.0)}[shape]
    surface = fn(seed)
    return lambda n, rng: sample_parametric(surface, n, rng, sign)


# ----------------------------------------------------------------------------- motions
def rbf_field(reference: np.ndarray, amount: float, rng: np.random.Generator,
              kernels: int = 6) -> Field:
    """A smooth displacement field: `kernels` Gaussian bumps (width 30 % of the diagonal)
    centred on reference points (k, 3), random directions, scaled so that the largest
    displacement over the reference points is `amount` times their diagonal."""
    diag = diagonal(reference)
    centres = reference[rng.integers(0, len(reference), kernels)]
    vecs = unit_vectors(rng, kernels) * rng.uniform(0.4, 1.0, (kernels, 1))
    width = 0.3 * diag

    def raw(p: np.ndarray) -> np.ndarray:
        w = np.exp(-((p[:, None, :] - centres) ** 2).sum(2) / (2 * width**2))
        return w @ vecs

    scale = amount * diag / np.linalg.norm(raw(reference), axis=1).max()
    return lambda p: p + scale * raw(p)


def elbow_bend(diag: float, amount: float, rng: np.random.Generator) -> Field:
    """Bend the limb's distal half (x > 0) about an axis through the elbow (origin), blended
    over +-25 mm (linear-blend skinning); the hand end moves ~`amount` x diagonal."""
    angle = 2 * np.arcsin(min(amount * diag / (2 * 0.3), 1.0)) * rng.choice([-1.0, 1.0])
    axis = np.r_[rng.uniform(-0.3, 0.3), rng.uniform(-1, 1), 1.0]
    rot = Rotation.from_rotvec(angle * axis / np.linalg.norm(axis)).as_matrix()

    def fn(p: np.ndarray) -> np.ndarray:
        s = np.clip((p[:, 0] + 0.025) / 0.05, 0, 1)
        w = (s * s * (3 - 2 * s))[:, None]
        return (1 - w) * p + w * (p @ rot.T)

    return fn


def similarity(centre: np.ndarray, degrees: float, scale: float, shift: np.ndarray,
               rng: np.random.Generator) -> tuple[Field, np.ndarray]:
    """x -> scale R (x - centre) + centre + shift, R a rotation by `degrees` about a random
    axis; returns the map and R (3, 3)."""
    rot = Rotation.from_rotvec(np.radians(degrees) * unit_vectors(rng, 1)[0]).as_matrix()
    return (lambda p: scale * (p - centre) @ rot.T + centre + shift), rot


def shape_motion(shape: str, seed: int, sampler: Sampler, amount: float) -> Field:
    """The true motion of a seeded shape (see the module docstring)."""
    rng = np.random.default_rng(seed + 21)
    reference = sampler(2000, np.random.default_rng(seed + 22))[0]
    if shape != "limb":
        return rbf_field(reference, amount, rng)
    bend = elbow_bend(diagonal(reference), amount, rng)
    mild = rbf_field(reference, 0.02, rng)
    return lambda p: bend(mild(p))


# ----------------------------------------------------------------------------- scans
def scan(sampler: Sampler, motion: Field, n: int, rng: np.random.Generator, *, noise: float,
         spikes: float, partial: bool, diag: float) -> tuple[np.ndarray, np.ndarray]:
    """Target (M, 3) m and its spike flags (M,): n points of the moved surface, noise and
    spikes as fractions of the diagonal; `partial`: only points facing a random view."""
    rest, nrm = sampler(n, rng)
    if partial:
        view = unit_vectors(rng, 1)[0]
        keep = nrm @ view > 0.0
        rest, nrm = rest[keep], nrm[keep]
    moved = motion(rest)
    tgt = moved + rng.normal(0, noise * diag, rest.shape)
    spike = rng.uniform(0, 1, len(tgt)) < spikes
    k = int(spike.sum())
    out = motion(rest[spike] + 1e-4 * diag * nrm[spike]) - moved[spike]  # moved normals
    out /= np.linalg.norm(out, axis=1, keepdims=True)
    tgt[spike] += out * (rng.uniform(0.02, 0.08, k) * rng.choice([-1.0, 1.0], k) * diag)[:, None]
    return tgt, spike


def shape_pair(shape: str, n: int = 5000, seed: int = 0, *, motion: float = 0.1,
               noise: float = 0.001, spikes: float = 0.02, partial: bool = False) -> Pair:
    """A colourless scanned-shape pair (`blob`, `torus`, `body`, `limb`)."""
    rng = np.random.default_rng(seed)
    sampler = shape_sampler(shape, seed)
    src = sampler(n, rng)[0]
    diag = diagonal(src)
    field = shape_motion(shape, seed, sampler, motion)
    tgt, spike = scan(sampler, field, n, rng, noise=noise, spikes=spikes, partial=partial,
                      diag=diag)
    return finish_pair(shape + ("_partial" if partial else ""), src, field(src), tgt, spike, rng)


def rotation_pair(n: int = 5000, seed: int = 0, *, shape: str = "body", degrees: float = 90.0,
                  scale: float = 0.8, nonrigid: float = 0.03, noise: float = 0.001,
                  spikes: float = 0.02) -> Pair:
    """A shape rotated by `degrees` about a random axis, scaled by `scale` about its centre
    and shifted by 10 % of its diagonal, after a mild non-rigid field (`nonrigid` x diagonal):
    truth = scale R (field(x) - c) + c + t."""
    rng = np.random.default_rng(seed)
    sampler = shape_sampler(shape, seed)
    src = sampler(n, rng)[0]
    diag = diagonal(src)
    field = shape_motion(shape, seed, sampler, nonrigid) if nonrigid > 0 else (lambda p: p)
    sim, _ = similarity(src.mean(0), degrees, scale, 0.1 * diag * unit_vectors(rng, 1)[0], rng)

    def motion(p: np.ndarray) -> np.ndarray:
        return sim(field(p))

    tgt, spike = scan(sampler, motion, n, rng, noise=noise, spikes=spikes, partial=False,
                      diag=diag)
    return finish_pair("rotation", src, motion(src), tgt, spike, rng)
