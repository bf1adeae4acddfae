"""Partial overlap in `register_pair` (pair.py): what a source point does where the target
has no surface for it or where its match may lie past the target's cut.

- A source point left without target surface (not `supported`) takes the median
  displacement of its `FOLLOW_NEIGHBOURS` nearest supported points, i.e. it moves rigidly
  (a translation) with its supported neighbourhood (`follow_supported`).
- With colour used, each supported point keeps the share of its motion (1, 1/2 or 0,
  averaged over its neighbours) under which its neighbourhood's colour and surface misfit is
  lowest (`stay_where_better`), leaving out hypotheses at the rim of the target
  (`target_rim`); then a point does not move at all where that explains its neighbourhood's
  data within a margin over the measured noises (`explained_by_identity`; at the target's
  rim its neighbours inside decide); a point whose deformation node it shares with points
  without target surface (`coupled_to_unsupported`) keeps only the part of its motion across
  the target's surface (`across_only`) where that explains its neighbourhood's data within
  the same margin; and a point matched onto the rim of a cut target (`matched_onto_cut`)
  follows as one without surface.
Inputs and outputs in metres.
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np
from scipy import sparse
from scipy.spatial import cKDTree

from . import graph
from .colour import ColourDecision, Neighbourhoods
from .surface import local_planes

FOLLOW_NEIGHBOURS = 16  # ours: supported neighbours an unsupported point moves with
# ours: an unsupported point follows its supported neighbourhood in full within 2 % of the
# diagonal of it (1.4 mm on the 70 mm tissue), blending to `register`'s own motion for it
# (smoothness plus a weak pull to not moving) at 5 %: on stray_colour_partial tuning seeds
# 0-4 the unsupported points' median error then stays within 0.05 mm of doing nothing's
# (+0.18 mm with a full follow out to 5 % fading to not moving at 10 %), and colourless
# partial shapes keep the solver's extrapolated motion far from their support
FOLLOW_REACH = (0.02, 0.05)

# ours: with colour used, each supported point's motion is scaled by the share of it
# (STAY_SHARES) whose colour + surface misfit, summed over about STAY_NEIGHBOURS nearby
# points, is lowest (then averaged over its neighbours): the colour-decided matches of
# static tissue next to moving tissue settle where the smoothness dragged it (the nearest
# match in position + colour is biased towards where the point already is), and comparing
# the hypotheses "moved" / "half moved" / "not moved" on the target's smoothed colour
# field has no such bias. Tuned on stray_colour / stray_colour_partial seeds 0-4: at 5k the
# partial pair's worst 5 mm cell goes from +0.48 to +0.35 mm over doing nothing (mean over
# seeds; supported cells from up to +0.50 to up to +0.38), the median from 0.175-0.279 to
# 0.150-0.274 mm, stray_colour's from 0.145-0.172 to 0.12-0.15 mm; 32 neighbours, shares
# {0, 1}, 5 shares, a scale of 1.5 or 6 noises, or the distance across the local plane in
# place of the nearest distance: no better. The misfits are taken on every 2nd supported
# point, at most STAY_SAMPLES of them, so a neighbourhood spans the same part of the
# surface at any density (100k: p95 0.24-0.36 -> 0.27-0.39 mm; every 2nd point: 0.28-0.41)
STAY_SHARES = (1.0, 0.5, 0.0)  # in this order: a tie (no data near) keeps the motion
STAY_NEIGHBOURS = 64
STAY_STRIDE = 2
STAY_SAMPLES = 2500
STAY_TARGET_NEIGHBOURS = 8  # target points the colour field is smoothed over
STAY_TAU_NOISE = 3.0  # robust scale of the misfit, in colour-noise units
# ours, tuned on stray_colour_partial 5k seeds 0-9 (worst 5 mm cell over doing nothing,
# mean +0.39 -> +0.29 mm) and stray_colour 2k: a rim point sees none of its RIM_NEIGHBOURS
# nearest points over an angle this wide around its normal (a straight edge: >= 180
# degrees; inside a randomly sampled surface 16 neighbours leave one at ~0.5 % of the
# points; 120 or 165 degrees: no better), and RIM_COMPANIONS of them are rim points too (a
# rim is a line; without: stray_colour 2k seed 100 p95 0.71 -> 0.85 mm; also sparing the
# source's own border zone, 3 spacings from its rim, changed nothing)
RIM_NEIGHBOURS = 16
RIM_GAP_DEG = 150.0
RIM_COMPANIONS = 2
# ours, tuned on stray_colour_partial 5k seeds 0-9 (worst 5 mm cell over doing nothing, mean
# +0.29 -> +0.07 mm, max +0.51 -> +0.22), stray_colour 2k / 5k, tissue_partial / tissue_noisy
# 3k seeds 0-4: a supported point goes back to not moving unless its own motion lowers the
# mean misfit of its IDENTITY_NEIGHBOURS nearest supported points (colour against the
# target's smoothed colour over the measured colour noise, squared, plus the distance across
# the target's local plane over its measured spread, squared) by more than IDENTITY_MARGIN
# (worst cell on seeds 0-9 with 8 / 24 neighbours +0.31 / +0.22 mm, a margin of 2 / 4 +0.23 /
# +0.32 mm; the own motion was fitted to these data, so it wins ties by a margin; the test on
# `stay_where_better`'s sample of every 2nd point, sharing its look-ups: +0.40 mm); points
# whose nearest target point, moved or not, is on the target's rim are left out of the means
# (static tissue at a border both clouds share, dragged 0.3-0.5 mm inwards, won its motion
# there by 4-6 per point on the across-plane term, planes fitted on one side: seed 208
# +0.34 -> +0.02 mm, the worst over seeds 0-9 and 200-209 +0.34 -> +0.15); and with
# colour an unsupported point follows its nearest supported points only within
# FOLLOW_REACH_COLOURED x the diagonal, fading to not moving (nothing measured its motion:
# following them out to 2-5 % as without colour left cut-away static cells +0.4 mm off, and
# out to any distance +2.3 mm). The across-plane term's variance is the spread's plus (the
# position's distance along the plane from its centre x the error of the plane's normal,
# `tilt`)^2: a plane extrapolated past the rim of a cut (its 16 points a strip along the
# rim, normals off by 20-30 degrees) put static tissue 1 mm past the rim 0.7 mm off it, and
# one such point outweighed its 15 neighbours (stray_colour_partial 5k seed 396: worst cell
# +0.31 -> 0 mm, 301 +0.19 -> 0; over tuning seeds 0-9, 200-209, 300-399 max +0.31 ->
# +0.15, mean +0.023 -> +0.009; mean median 0.1654 -> 0.1656 mm, mean p95 2.211 -> 2.215
# mm; the normal's error as the residual variance over k x the in-plane one, without the
# perturbation's denominator: the same cells; capping the term as the colour is capped
# instead: +0.19 mm, mean median +0.003 and p95 +0.036 mm)
IDENTITY_NEIGHBOURS = 16
IDENTITY_MARGIN = 2.8
FOLLOW_REACH_COLOURED = (0.0, 0.01)
# the colour misfit u of explained_by_identity (|colour difference|^2 over the measured
# noise^2: under noise alone about chi^2 with 3 degrees of freedom / 3) counts as
# u c / (u + c), c its 99.9 % quantile (16.27 / 3): a point whose colour the target does not
# show near it (its samples left out as colour strays, or sparse at the target's border; a
# random-coloured stray kept) weighs at most c, not 20-150 noises. Fresh seeds 300-319 of
# stray_colour_partial 5k: static tissue at the border both clouds share, dragged 1.3 mm by
# `register`, won its motion by a few such points (seed 313 +1.256 -> +0.015 mm, 308 +0.423
# -> +0.177); the same worst cells for c from 7.81 / 3 (95 %) to 9.49; at 12 and above seed
# 313 is back (+0.85 mm)
IDENTITY_COLOUR_CAP = 16.27 / 3.0
# ours, tuned on stray_colour_partial 5k seeds 0-9, 200-209, 300-319: next to a cut,
# `register` drags the supported tissue away from the cut along the surface (seed 300: 1.9 /
# 1.7 / 1.2 / 0.6 / 0.1 mm within 1 / 2 / 4 / 6 / 9 mm of the points without target surface;
# the nodes there blend the cut-away points' matches onto the rim, and the smoothness carries
# them on); a supported point blending a node whose weight comes mostly from points without
# target surface, or one of its smoothness neighbours (1 ring: about the 6 mm the drag
# reaches), keeps only its motion across the surface unless the slide explains its
# neighbourhood's data better by IDENTITY_MARGIN, the colour counted in full (seed 300 +0.58 ->
# +0.26 mm, 308 +0.18 -> +0.02, 203 +0.13 -> 0; no ring: 300 +0.55; any node touched, 1 ring:
# stray_colour 2k p95 0.60 -> 0.89 mm, from a border node the resampling left; the colour
# counted robustly (any node touched): medians of seeds 9 / 204 +0.03 / +0.08 mm; without
# the test: +0.06 / +0.15)
COUPLED_RINGS = 1
# ours, tuned on the same: a supported point whose registered position lies within
# CUT_RIM_SPACINGS target spacings of the target's rim (`target_rim`) and within
# CUT_LOST_SPACINGS of a source point without target surface (the source goes on past the
# rim: a cut, not a border both clouds share) was matched onto the rim of a cut target, whose
# partner may lie past it: it follows, as a point without target surface does
# (stray_colour_partial 5k seeds 0-9, worst cell max +0.22 -> +0.15 mm; tissue_partial 3k
# seeds 0-4 +0.94 -> +0.19; 1.5 / 3 spacings of the rim: +0.18 / +0.10 mm but stray_colour 5k
# p95 up by 0.02 / 0.10 mm; within 3 / 4 spacings of a lost point: +0.22 / +0.22 mm, and
# tissue_partial +0.89 / +0.48; 8: as 6; over 6 spacings inside the source's own rim in
# place of the lost points: the same cells, stray_colour 5k p95 +0.03 mm, 20 ms more)
# A supported position past the rim (its nearest target point a rim point more than one
# spacing away: inside the surface a point lies within about half a spacing of its nearest
# sample) counts too: `register`'s support gate reaches 3 spacings, and on seed 8 points
# whose partners lie 1-3 mm past the cut slid 0.8-1.5 mm past the rim (worst cell +0.107 ->
# +0.044 mm; seeds 0-9 and 200-209 otherwise the same or lower)
CUT_RIM_SPACINGS = 2.0
CUT_LOST_SPACINGS = 6.0


def target_rim(xyz: np.ndarray, k: int = RIM_NEIGHBOURS,
               gap_deg: float = RIM_GAP_DEG, companions: int = RIM_COMPANIONS) -> np.ndarray:
    """(M,) bool: the points of a cloud xyz (M, 3) m on its boundary (the rim of a surface
    patch or of a cut): seen from the point, its k nearest neighbours, projected on the
    local tangent plane (PCA of them), leave an angular gap wider than `gap_deg` degrees
    (inside a surface they surround the point), and at least `companions` of them are such
    points too."""
    return rim_and_planes(xyz, k, gap_deg, companions)[0]


def rim_and_planes(xyz: np.ndarray, k: int = RIM_NEIGHBOURS, gap_deg: float = RIM_GAP_DEG,
                   companions: int = RIM_COMPANIONS,
                   near: Neighbourhoods | None = None) -> tuple[np.ndarray, ...]:
    """(rim (M,) bool as `target_rim`, centre (M, 3) m, normal (M, 3) unit, tilt (M,)
    radians): with each point's local plane, the centroid and PCA normal of its k nearest
    neighbours (xyz (M, 3) m), and the standard error of that normal towards the plane's
    weaker in-plane axis (first-order eigenvector perturbation: large where the neighbours
    span a strip, at a rim); near: the points' neighbour lists (`colour.Neighbourhoods`;
    None: measured here)."""
    m = len(xyz)
    if m <= 3:
        return (np.zeros(m, bool), xyz.copy(), np.tile([0.0, 0.0, 1.0], (m, 1)),
                np.zeros(m))
    k = min(k, m - 1)
    if near is not None and near.indices.shape[1] >= k + 1:
        nn = near.indices[:, :k + 1]
    else:
        nn = cKDTree(xyz).query(xyz, k=k + 1)[1]
    centre, normal, _ = local_planes(xyz, nn[:, 1:])
    rel = xyz[nn[:, 1:]] - xyz[:, None, :]
    # a tangent basis (u, v): u across the normal from the axis least along it
    axis = np.eye(3)[np.argmin(np.abs(normal), axis=1)]
    u = np.cross(normal, axis)
    u /= np.linalg.norm(u, axis=1)[:, None]
    v = np.cross(normal, u)
    along_u, along_v = np.einsum("pki,pi->pk", rel, u), np.einsum("pki,pi->pk", rel, v)
    angle = np.sort(np.arctan2(along_v, along_u), axis=1)
    gaps = np.diff(angle, axis=1, append=angle[:, :1] + 2 * np.pi)
    rim = gaps.max(axis=1) > np.deg2rad(gap_deg)
    # a rim is a line: a point flagged alone among its neighbours is a sampling accident
    rim = np.asarray(rim & (rim[nn[:, 1:]].sum(axis=1) >= companions))
    # the normal's error towards the weaker in-plane axis (an eigenvector's perturbation):
    # variance l2 l3 / (k (l2 - l3)^2), l3 the residual variance across the plane, l2 the
    # smallest eigenvalue of the neighbours' 2x2 in-plane covariance
    l3 = (np.einsum("pki,pi->pk", xyz[nn[:, 1:]] - centre[:, None, :], normal) ** 2).mean(1)
    cuu, cvv = along_u.var(axis=1), along_v.var(axis=1)
    cuv = (along_u * along_v).mean(axis=1) - along_u.mean(axis=1) * along_v.mean(axis=1)
    l2 = 0.5 * (cuu + cvv) - np.sqrt(0.25 * (cuu - cvv) ** 2 + cuv**2)
    tilt = np.sqrt(l2 * l3 / (k * np.maximum(l2 - l3, 1e-12 * l2 + 1e-30) ** 2))
    return rim, centre, normal, tilt


def follow_supported(source: np.ndarray, registered: np.ndarray, supported: np.ndarray,
                     reach: tuple[float, float] = FOLLOW_REACH,
                     beyond: np.ndarray | None = None) -> np.ndarray:
    """(N, 3) registered positions where every point not `supported` (N,) bool moves by the
    per-axis median displacement of its nearest supported points (source (N, 3), m), in
    full within reach[0] x the source's bounding-box diagonal of the nearest one, blending
    to its position in `beyond` (N, 3) m (None: its own `registered` position) at reach[1]
    x it (FOLLOW_REACH)."""
    diagonal = float(np.linalg.norm(source.max(axis=0) - source.min(axis=0)))
    reach_m = (reach[0] * diagonal, reach[1] * diagonal)
    out = registered.copy()
    have = np.flatnonzero(supported)
    lost = np.flatnonzero(~supported)
    if len(have) == 0 or len(lost) == 0:
        return out
    k = min(FOLLOW_NEIGHBOURS, len(have))
    d, nn = cKDTree(source[have], balanced_tree=False).query(source[lost], k=k)
    d, nn = d.reshape(len(lost), k), nn.reshape(len(lost), k)
    fade = np.clip((reach_m[1] - d[:, 0]) / (reach_m[1] - reach_m[0]), 0.0, 1.0)
    moves = (registered - source)[have[nn]]
    follow = source[lost] + np.median(moves, axis=1)
    far = registered if beyond is None else beyond
    out[lost] = fade[:, None] * follow + (1.0 - fade[:, None]) * far[lost]
    return out


@dataclasses.dataclass(frozen=True)
class ColouredPoints:
    """Points xyz (M, 3) m with their colours rgb (M, 3) 0..1; rim (M,) bool: the points on
    the cloud's boundary (`target_rim`; None = none known); centre (M, 3) m and normal (M, 3)
    unit: each point's local plane and tilt (M,) radians the standard error of its normal
    (`rim_and_planes`; None = not known); kdtree: the points' k-d tree when already built
    (None: built on first use)."""

    xyz: np.ndarray
    rgb: np.ndarray
    rim: np.ndarray | None = None
    centre: np.ndarray | None = None
    normal: np.ndarray | None = None
    tilt: np.ndarray | None = None
    kdtree: cKDTree | None = dataclasses.field(default=None, repr=False, compare=False)

    @classmethod
    def analysed(cls, xyz: np.ndarray, rgb: np.ndarray,
                 near: Neighbourhoods | None = None) -> ColouredPoints:
        """The points with their rim and local planes (`rim_and_planes`); near: their tree
        and neighbour lists when measured already (`colour.Neighbourhoods`, e.g. the colour
        decision's of the agreeing target points), None: measured here."""
        rim, centre, normal, tilt = rim_and_planes(xyz, near=near)
        return cls(xyz, rgb, rim, centre, normal, tilt, None if near is None else near.tree)

    @functools.cached_property
    def tree(self) -> cKDTree:
        """The points' k-d tree, built once for every look-up."""
        return self.kdtree if self.kdtree is not None else cKDTree(self.xyz)

    def colour_at(self, positions: np.ndarray, spacing_m: float
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The colour (P, 3) smoothed at positions (P, 3) m: a Gaussian of σ spacing_m over
        the STAY_TARGET_NEIGHBOURS nearest points, whose distances (P, k) m and indices
        (P, k) come with it."""
        d, j = self.tree.query(positions, k=STAY_TARGET_NEIGHBOURS)
        w = np.exp(-0.5 * (d / spacing_m) ** 2) + 1e-12
        return np.einsum("nk,nkc->nc", w, self.rgb[j]) / w.sum(axis=1)[:, None], d, j


def stay_where_better(source: np.ndarray, registered: np.ndarray, supported: np.ndarray,
                      source_rgb: np.ndarray, target: ColouredPoints,
                      decision: ColourDecision) -> np.ndarray:
    """(N,) share of its motion each source point keeps (STAY_SHARES, neighbourhood-averaged;
    module constants): for positions source + share x (registered - source) (N, 3) m, the
    misfit of a point is u = |rgb - target colour smoothed at it|^2 + (gradient x distance to
    the nearest target point)^2 (RGB units), robust rho = u / (u + (STAY_TAU_NOISE x
    noise)^2), on a spread sample of the supported points (STAY_STRIDE, STAY_SAMPLES),
    summed over about STAY_NEIGHBOURS sample points near each; a position whose nearest
    target point is on the target's rim (`target.rim`) tells nothing (its partner may lie
    past the rim of a cut target) and is left out of the sums.
    target: the agreeing target points; colours 0..1."""
    n = len(source)
    if not supported.any() or len(target.xyz) < STAY_TARGET_NEIGHBOURS:
        return np.ones(n)
    h = max(decision.spacing_m, 1e-9)
    g = decision.gradient * 1e3  # RGB units per metre
    tau2 = (STAY_TAU_NOISE * max(decision.noise, 1e-6)) ** 2
    move = registered - source
    have = np.flatnonzero(supported)
    # misfits on a spread sample of the supported points (every 2nd, or STAY_SAMPLES at most:
    # the neighbourhoods then span the same part of the surface at any density)
    sample = have[:: max(STAY_STRIDE, len(have) // STAY_SAMPLES)]
    m = len(sample)
    costs = np.zeros((m, len(STAY_SHARES)))
    known = np.ones((m, len(STAY_SHARES)))
    for a, share in enumerate(STAY_SHARES):
        smoothed, d, j = target.colour_at(source[sample] + share * move[sample], h)
        u = ((source_rgb[sample] - smoothed) ** 2).sum(axis=1) + (g * d[:, 0]) ** 2
        costs[:, a] = u / (u + tau2)
        if target.rim is not None:
            known[:, a] = ~target.rim[j[:, 0]]
    # a sum over about STAY_NEIGHBOURS sample points as two means over 8x fewer
    k = min(STAY_NEIGHBOURS // 8, m)
    # every source point's nearest sample points (the sample's own among them)
    nb = cKDTree(source[sample], balanced_tree=False).query(source, k=k)[1].reshape(n, k)
    mean = _mean_operator(nb[sample], m)
    seen = mean @ (mean @ known)
    summed = (mean @ (mean @ (costs * known))) / np.maximum(seen, 1e-12)
    summed[seen <= 0] = 0.0  # nothing seen: a tie keeps the motion
    best = np.asarray(STAY_SHARES)[np.argmin(summed, axis=1)]
    return np.asarray(_mean_operator(nb, m) @ (mean @ best))


@dataclasses.dataclass(frozen=True)
class MotionTest:
    """What `explained_by` tests: source (N, 3) m, registered (N, 3) m, supported (N,) bool,
    source_rgb (N, 3) 0..1; alternative (N, 3) m: the positions tested in place of the
    motion (None: the source, not moving); robust: the colour misfit counted robustly
    (`robust_colour`; False: in full, so a slide's evidence is kept whole); only (N,) bool:
    the points asked about (None: every supported one; the answer is meant for them)."""

    source: np.ndarray
    registered: np.ndarray
    supported: np.ndarray
    source_rgb: np.ndarray
    alternative: np.ndarray | None = None
    robust: bool = True
    only: np.ndarray | None = None


def explained_by_identity(source: np.ndarray, registered: np.ndarray, supported: np.ndarray,
                          source_rgb: np.ndarray, target: ColouredPoints,
                          decision: ColourDecision) -> np.ndarray:
    """(N,) bool: the supported points that move (source -> registered (N, 3) m) for which not
    moving explains the data about as well as their motion does (`explained_by`, colours
    source_rgb (N, 3) 0..1, supported (N,) bool)."""
    return explained_by(MotionTest(source, registered, supported, source_rgb), target,
                        decision)


def explained_by(test: MotionTest, target: ColouredPoints,
                 decision: ColourDecision) -> np.ndarray:
    """(N,) bool: the supported points of `test` that move (source -> registered) for which
    its alternative (not moving by default) explains the data about as well as their motion
    does. Per point and position, the misfit is `robust_colour`(|source colour - target
    colour smoothed at it|^2 / noise^2, the colour noise measured on the target; in full
    when not test.robust) + (distance across the local plane of its nearest target point)^2
    / (s^2 + (its distance along that plane from the plane's centre x the plane's `tilt`)^2),
    s the robust spread of that distance at the registered positions (the target's noise as
    this run sees it; the second term: a plane's error grows with the distance it is
    extrapolated over, most where its points span a strip, at a rim); a point is explained
    by the alternative unless its motion lowers the mean misfit of its IDENTITY_NEIGHBOURS
    nearest supported points by more than IDENTITY_MARGIN. A point whose nearest target
    point, at either position, is on the target's rim (`target.rim`) is left out of the
    means (there the misfits favour any motion onto the target); one whose neighbours are
    all left out keeps its motion.
    target: the agreeing target points, colours 0..1, with their planes (computed when not
    given)."""
    source, registered, supported = test.source, test.registered, test.supported
    source_rgb, alternative, robust, only = (test.source_rgb, test.alternative, test.robust,
                                             test.only)
    n = len(source)
    still = np.zeros(n, bool)
    have = np.flatnonzero(supported)
    if len(have) == 0 or len(target.xyz) < STAY_TARGET_NEIGHBOURS:
        return still
    if target.centre is None or target.normal is None or target.tilt is None:
        target = ColouredPoints.analysed(target.xyz, target.rgb)
    centre, normal, tilt = target.centre, target.normal, target.tilt
    assert centre is not None and normal is not None and tilt is not None
    h = max(decision.spacing_m, 1e-9)
    noise = max(decision.noise, 1e-6)

    rim = target.rim if target.rim is not None else np.zeros(len(target.xyz), bool)

    def fit(pos: np.ndarray, rgb: np.ndarray) -> tuple[np.ndarray, ...]:
        """Colour misfit at pos, its distance across the plane and that distance's variance
        from the plane's tilt, and whether its nearest target point is on the target's rim."""
        smoothed, _, j = target.colour_at(pos, h)
        return (((rgb - smoothed) ** 2).sum(axis=1) / noise**2, *across(pos, j[:, 0]),
                rim[j[:, 0]])

    def across(pos: np.ndarray, near: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distance across the plane of target point `near`, and its variance from the
        plane's tilt over the distance along it (lateral distance x tilt, squared)."""
        rel = pos - centre[near]
        off = np.abs((rel * normal[near]).sum(axis=1))
        return off, np.maximum((rel**2).sum(axis=1) - off**2, 0.0) * tilt[near] ** 2

    # where a point does not move both misfits are the same and not moving changes nothing:
    # only the moving ones are sought and tested (the others count in the spread alone)
    alt = source if alternative is None else alternative
    moving = np.flatnonzero(np.any(registered[have] != alt[have], axis=1))
    k = min(IDENTITY_NEIGHBOURS, len(have))
    source_tree = cKDTree(source[have], balanced_tree=False)
    if only is not None:  # the points asked about and the neighbours they average over
        asked = np.flatnonzero(only[have])
        needed = np.zeros(len(have), bool)
        if len(asked):
            needed[source_tree.query(source[have[asked]], k=k)[1].ravel()] = True
        moving = moving[needed[moving]]
    if len(moving) == 0:
        return still
    resting = np.setdiff1d(np.arange(len(have)), moving, assume_unique=True)
    across1 = np.empty(len(have))
    colour1, across1[moving], tilted1, rim1 = fit(registered[have[moving]],
                                                  source_rgb[have[moving]])
    if len(resting):
        pos = registered[have[resting]]
        across1[resting] = across(pos, target.tree.query(pos, k=1)[1])[0]
    spread2 = max(1.4826 * float(np.median(across1)), 1e-9) ** 2
    gain = np.zeros(len(have))  # > 0: the motion fits better
    colour0, across0, tilted0, rim0 = fit(alt[have[moving]], source_rgb[have[moving]])
    c0, c1 = (robust_colour(colour0), robust_colour(colour1)) if robust else (colour0, colour1)
    gain[moving] = (c0 + across0**2 / (spread2 + tilted0)
                    - c1 - across1[moving] ** 2 / (spread2 + tilted1))
    # at the target's rim the misfits favour the motion whatever the truth (past the rim the
    # colour is smoothed over one side and the plane is fitted on one side): a point whose
    # position either way has its nearest target point on the rim tells nothing, and its
    # neighbours decide for it; with none that tells, it keeps its motion
    seen = np.ones(len(have))
    seen[moving] = ~(rim0 | rim1)
    nb = source_tree.query(source[have[moving]], k=k)[1].reshape(len(moving), k)
    count = seen[nb].sum(axis=1)
    mean_gain = (gain * seen)[nb].sum(axis=1) / np.maximum(count, 1.0)
    still[have[moving]] = (count > 0) & (mean_gain <= IDENTITY_MARGIN)
    return still


def coupled_to_unsupported(source: np.ndarray, supported: np.ndarray, max_nodes: int,
                           interp_neighbors: int, k_neighbors: int,
                           nodes: graph.NodeBlend | None = None) -> np.ndarray:
    """(N,) bool: supported points (N,) bool of source (N, 3) m whose motion `register`
    blends from a node next to a part without target surface: its nodes
    (`graph.node_blend`, max_nodes, each point's interp_neighbors blended ones, k_neighbors
    smoothness neighbours; nodes: the same when already built), the nodes whose blend
    weight comes mostly (> 1/2) from points not supported and which have such a node among
    their smoothness neighbours (a part that spans nodes: a cut, not a border sample the
    resampling missed), and their smoothness neighbours (COUPLED_RINGS rings)."""
    out = np.zeros(len(source), bool)
    if supported.all() or not supported.any() or max_nodes <= 0 or len(source) <= max_nodes:
        return out
    if nodes is None:
        nodes = graph.node_blend(source, max_nodes, interp_neighbors, k_neighbors)
    idx, w, ea, eb = nodes.idx, nodes.w, nodes.a, nodes.b
    total = np.bincount(idx.ravel(), w.ravel(), nodes.count)
    lost = np.bincount(idx[~supported].ravel(), w[~supported].ravel(), nodes.count)
    mostly = lost > 0.5 * total
    touched = mostly & (np.bincount(ea[mostly[eb]], minlength=nodes.count) > 0)
    for _ in range(COUPLED_RINGS):
        ring = touched.copy()
        ring[eb[touched[ea]]] = True
        touched = ring
    return supported & (touched[idx] & (w > 0)).any(axis=1)


def across_only(source: np.ndarray, registered: np.ndarray,
                target: ColouredPoints) -> np.ndarray:
    """(N, 3) m: each source point (N, 3) m moved by only the part of its motion (registered
    - source) along the normal of the target point nearest its registered position (the
    slide along the surface dropped)."""
    if target.normal is None:
        target = ColouredPoints.analysed(target.xyz, target.rgb)
    assert target.normal is not None
    normal = target.normal[target.tree.query(registered, k=1)[1]]
    move = registered - source
    return source + normal * (move * normal).sum(axis=1)[:, None]


def robust_colour(u: np.ndarray) -> np.ndarray:
    """The robust colour misfit u c / (u + c) of colour misfits u (noise units, squared),
    c = IDENTITY_COLOUR_CAP: ~u for misfits noise explains, at most c."""
    return u * IDENTITY_COLOUR_CAP / (u + IDENTITY_COLOUR_CAP)


def matched_onto_cut(source: np.ndarray, registered: np.ndarray, supported: np.ndarray,
                     target: ColouredPoints, spacing_m: float) -> np.ndarray:
    """(N,) bool: supported points whose registered position (N, 3) m lies within
    CUT_RIM_SPACINGS x spacing_m (the target's spacing, m) of a point on the target's rim
    (`target.rim`), or past the rim (its nearest target point a rim point more than
    spacing_m away), while the source (N, 3) m goes on past them: within CUT_LOST_SPACINGS x
    spacing_m of a source point not `supported` (N,) bool. Their partner may lie past the
    rim of a cut target: the data do not measure their motion."""
    out = np.zeros(len(source), bool)
    if target.rim is None or not target.rim.any() or supported.all() or not supported.any():
        return out
    reach = CUT_RIM_SPACINGS * spacing_m
    have = np.flatnonzero(supported)
    near = cKDTree(target.xyz[target.rim], balanced_tree=False).query(registered[have],
                                                 distance_upper_bound=reach)[0] <= reach
    # past the rim: the nearest target point is a rim point more than a spacing away (inside
    # the surface a point lies within about half a spacing of its nearest sample)
    d, j = target.tree.query(registered[have])
    past = target.rim[j] & (d > spacing_m)
    cand = have[near | past]
    if len(cand):
        reach = CUT_LOST_SPACINGS * spacing_m
        lost = cKDTree(source[~supported], balanced_tree=False).query(
            source[cand], distance_upper_bound=reach)[0]
        out[cand[lost <= reach]] = True
    return out


def _mean_operator(nb: np.ndarray, m: int) -> sparse.csr_matrix:
    """(P, m) sparse: row i the mean over the columns nb[i] (P, k)."""
    p, k = nb.shape
    return sparse.csr_matrix((np.full(p * k, 1.0 / k), nb.ravel(), np.arange(0, p * k + 1, k)),
                             shape=(p, m))
