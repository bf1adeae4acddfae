"""Pose-guided feature matching (core/template/matching.py) on synthetic features with known
correspondences: two tracked cameras see the same 3D points, each point carries one random
descriptor in both images (plus noise), so the right matches are known exactly; distractors
test the ratio test, the epipolar and depth gates and the mutual check.
"""

from __future__ import annotations

import numpy as np
import pytest

from surgrecon_cli.core.geometry.poses import invert_pose
from surgrecon_cli.core.template import matching
from surgrecon_cli.core.template.features import Features
from surgrecon_cli.core.template.matching import (
    CameraView,
    PairGates,
    build_tracks,
    epipolar_candidates,
    essential_matrix,
    match_pair,
    ray_depths,
)

FOCAL = 500.0  # px
RATIO, EPI_PX, DEPTHS = 0.8, 2.0, (0.01, 0.2)


def look_at(centre, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world pose (optical frame: z forward, y down) at `centre` facing `target`."""
    centre, target = np.asarray(centre, float), np.asarray(target, float)
    z = target - centre
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, y, z])
    T[:3, 3] = centre
    return T


def normalised(points: np.ndarray, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Normalised image coordinates (N, 2) and depths (N,) of world points in a camera."""
    T = invert_pose(pose)
    pc = points @ T[:3, :3].T + T[:3, 3]
    return pc[:, :2] / pc[:, 2:], pc[:, 2]


def features(xy: np.ndarray, desc: np.ndarray) -> Features:
    rgb = np.zeros((len(xy), 3), np.uint8)
    return Features(xy * FOCAL + 320.0, xy, desc.astype(np.float32), rgb)


@pytest.fixture(scope="module")
def scene():
    """Two cameras 30 mm apart, 60 mm from a patch of 60 points (depths 45..75 mm)."""
    rng = np.random.default_rng(11)
    pose_i = look_at([-0.015, 0.0, 0.06], [0.0, 0.0, 0.0], up=(0.0, 1.0, 0.0))
    pose_j = look_at([0.015, 0.0, 0.06], [0.0, 0.0, 0.0], up=(0.0, 1.0, 0.0))
    points = np.column_stack([rng.uniform(-0.01, 0.01, 60), rng.uniform(-0.01, 0.01, 60),
                              rng.uniform(-0.015, 0.015, 60)])
    desc = rng.uniform(0.0, 1.0, (60, 128))
    xi, zi = normalised(points, pose_i)
    xj, _ = normalised(points, pose_j)
    perm = rng.permutation(60)  # image j lists the points in another order
    fi = features(xi, desc + rng.normal(0, 0.01, desc.shape))
    fj = features(xj[perm], desc[perm] + rng.normal(0, 0.01, desc.shape))
    truth = {(int(p), j) for j, p in enumerate(perm)}  # (feature in i, feature in j)
    return dict(pose_i=pose_i, pose_j=pose_j, points=points, desc=desc, xi=xi, xj=xj, zi=zi,
                perm=perm, fi=fi, fj=fj, truth=truth, rng=rng)


def views(fi: Features, fj: Features, s: dict) -> tuple[CameraView, CameraView]:
    """The two cameras of the scene `s` with features fi and fj."""
    return CameraView(fi, s["pose_i"], FOCAL), CameraView(fj, s["pose_j"], FOCAL)


def run(fi: Features, fj: Features, s: dict, depth_range=DEPTHS) -> set[tuple[int, int]]:
    m = match_pair(*views(fi, fj, s), PairGates(RATIO, EPI_PX, depth_range))
    return {(int(a), int(b)) for a, b in m}


def with_extra(f: Features, xy: np.ndarray, desc: np.ndarray) -> Features:
    return features(np.vstack([f.normalized, xy]), np.vstack([f.descriptors, desc]))


def symmetric_epipolar_px(E, xi, xj):
    """Brute force (Ni, Nj): mean of the two point-to-epipolar-line distances in pixels."""
    hi = np.column_stack([xi, np.ones(len(xi))])
    hj = np.column_stack([xj, np.ones(len(xj))])
    lines_j = hi @ E.T  # lines in j of the points of i
    lines_i = hj @ E  # lines in i of the points of j
    alg = np.abs(hj @ lines_j.T).T  # |x_j' E x_i|, (Ni, Nj)
    d_j = FOCAL * alg / np.linalg.norm(lines_j[:, :2], axis=1)[:, None]
    d_i = FOCAL * alg / np.linalg.norm(lines_i[:, :2], axis=1)[None, :]
    return 0.5 * (d_i + d_j)


# ---- geometry -----------------------------------------------------------------------------


def test_essential_matrix_and_ray_depths_from_the_poses(scene):
    s = scene
    E = essential_matrix(s["pose_i"], s["pose_j"])
    hi = np.column_stack([s["xi"], np.ones(60)])
    hj = np.column_stack([s["xj"], np.ones(60)])
    np.testing.assert_allclose(np.einsum("ni,ij,nj->n", hj, E, hi), 0.0, atol=1e-12)
    # a point shifted off its epipolar line violates it
    assert np.abs(np.einsum("ni,ij,nj->n", hj + np.array([0.0, 0.01, 0.0]), E, hi)).min() > 1e-5
    np.testing.assert_allclose(ray_depths(s["xi"], s["xj"], s["pose_i"], s["pose_j"]), s["zi"],
                               rtol=1e-9)


def test_epipolar_candidates_are_exactly_the_pairs_within_tolerance(scene):
    """Every pair within the tolerance is found (the float32 screen never misses one) and
    nothing farther is returned, on many unrelated points."""
    s = scene
    rng = np.random.default_rng(12)
    xi = rng.uniform(-0.3, 0.3, (300, 2))
    xj = rng.uniform(-0.3, 0.3, (400, 2))
    E = essential_matrix(s["pose_i"], s["pose_j"])
    for tol in (0.5, 2.0, 10.0):
        ia, jb = epipolar_candidates(E, xi, xj, FOCAL, FOCAL, tol)
        d = symmetric_epipolar_px(E, xi, xj)
        expected = set(zip(*np.nonzero(d <= tol), strict=True))
        got = set(zip(ia.tolist(), jb.tolist(), strict=True))
        assert got == {(int(a), int(b)) for a, b in expected}
        assert len(got) > 50  # the test means something at every tolerance


# ---- matching -----------------------------------------------------------------------------


def test_recovers_the_known_correspondences(scene):
    assert run(scene["fi"], scene["fj"], scene) == scene["truth"]


@pytest.mark.parametrize("on_the_line", [True, False])
def test_ratio_test_drops_an_ambiguous_feature(scene, on_the_line):
    """A second feature in image j with (almost) the same descriptor as point 0's makes point
    0 ambiguous: it is dropped, whether the look-alike lies on point 0's epipolar segment
    (another depth along the ray) or anywhere else in the image."""
    s = scene
    if on_the_line:  # the same ray of camera i, 10 mm farther: on the epipolar segment
        ray = s["points"][0] - s["pose_i"][:3, 3]
        xy, _ = normalised(s["points"][:1] + 0.01 * ray / np.linalg.norm(ray), s["pose_j"])
    else:
        xy = np.array([[0.25, -0.2]])
    look_alike = s["desc"][:1] + s["rng"].normal(0, 0.01, (1, 128))
    got = run(s["fi"], with_extra(s["fj"], xy, look_alike), s)
    j0 = int(np.flatnonzero(s["perm"] == 0)[0])
    assert got == s["truth"] - {(0, j0)}


def test_a_clearly_different_distractor_changes_nothing(scene):
    s = scene
    xy, _ = normalised(s["points"][:1] + np.array([0.0, 0.0, 0.004]), s["pose_j"])
    other = s["rng"].uniform(0.0, 1.0, (1, 128))
    assert run(s["fi"], with_extra(s["fj"], xy, other), s) == s["truth"]


def test_epipolar_gate_rejects_a_feature_off_its_line(scene):
    """Point 5 seen 10 px off its epipolar line in image j (a wrong pose, a moving point):
    not matched, and not matched to anything else either."""
    s = scene
    j5 = int(np.flatnonzero(s["perm"] == 5)[0])
    E = essential_matrix(s["pose_i"], s["pose_j"])
    line = E @ np.append(s["xi"][5], 1.0)
    normal = line[:2] / np.linalg.norm(line[:2])  # perpendicular to the epipolar line in j
    xy = s["fj"].normalized.copy()
    xy[j5] += 10.0 / FOCAL * normal
    got = run(s["fi"], features(xy, s["fj"].descriptors), s)
    assert got == s["truth"] - {(5, j5)}


def test_depth_gate_keeps_only_matches_triangulating_inside_the_range(scene):
    s = scene
    near = (0.0, 0.06)  # the points are 45..75 mm from camera i
    got = run(s["fi"], s["fj"], s, depth_range=near)
    inside = {(i, j) for i, j in s["truth"] if s["zi"][i] <= near[1]}
    assert 0 < len(inside) < len(s["truth"])
    assert got == inside


def test_only_mutual_best_matches_are_kept(scene):
    """A second feature in image i on point 3's epipolar segment with a noisier copy of its
    descriptor passes its own ratio test (its best is point 3's feature in j, clearly), but
    that feature's best in i is the original: only the original is matched."""
    s = scene
    ray = s["points"][3] - s["pose_j"][:3, 3]
    xy, _ = normalised(s["points"][3:4] + 0.008 * ray / np.linalg.norm(ray), s["pose_i"])
    copy = s["desc"][3:4] + s["rng"].normal(0, 0.05, (1, 128))
    got = run(with_extra(s["fi"], xy, copy), s["fj"], s)
    assert got == s["truth"]  # nothing for the copy (index 60)


def test_too_few_features_give_no_matches(scene):
    s = scene
    one = features(s["xi"][:1], s["desc"][:1])
    assert match_pair(*views(one, s["fj"], s), PairGates(RATIO, EPI_PX, DEPTHS)).shape == (0, 2)


# ---- tracks -------------------------------------------------------------------------------


def test_tracks_chain_pairs_and_earlier_pairs_win_conflicts():
    """Three cameras with 3, 3, 4 features. Pairs (0,1) and (1,2) chain features into two
    tracks; the later pair (0,2) would put camera 0's feature 1 into the track that already
    holds camera 0's feature 0 (through camera 2's feature 0): refused."""
    matches = {
        (0, 1): np.array([[0, 0], [1, 1]]),
        (1, 2): np.array([[0, 0], [1, 2]]),
        (0, 2): np.array([[1, 0], [2, 3]]),  # first conflicts; second makes a new 2-track
    }
    ids, n = build_tracks([3, 3, 4], [(i, j, matches[(i, j)]) for i, j in [(0, 1), (1, 2), (0, 2)]])
    assert n == 3
    a, b, c = ids[0][0], ids[0][1], ids[0][2]
    assert len({a, b, c}) == 3 and min(a, b, c) >= 0
    np.testing.assert_array_equal(ids[1], [a, b, -1])
    np.testing.assert_array_equal(ids[2], [a, -1, b, c])
    # Another order: (0,2) first wins. Then (1,2) adds camera 1's feature 0 to the track of
    # (c0 f1, c2 f0) and starts (c1 f1, c2 f2); both (0,1) matches now conflict: c0 f0 is left
    # without a track.
    ids, n = build_tracks([3, 3, 4], [(i, j, matches[(i, j)]) for i, j in [(0, 2), (1, 2), (0, 1)]])
    assert n == 3
    assert ids[0][1] == ids[2][0] == ids[1][0] >= 0
    assert ids[1][1] == ids[2][2] >= 0 and ids[0][2] == ids[2][3] >= 0
    assert len({ids[0][1], ids[1][1], ids[0][2]}) == 3
    assert ids[0][0] == -1


# ---- bounded memory -----------------------------------------------------------------------


def dense_reference(fi: Features, fj: Features, s: dict, tol_px: float) -> set[tuple[int, int]]:
    """The matching rule on whole Ni x Nj matrices (what the blocked search must equal):
    candidates within the epipolar tolerance and depth range; a row's best candidate passes
    the ratio test against the next best of all other features of j, candidate or not, and
    must be its column's best candidate."""
    E = essential_matrix(s["pose_i"], s["pose_j"])
    epi = symmetric_epipolar_px(E, fi.normalized, fj.normalized)
    ia, jb = np.nonzero(epi <= tol_px)
    z = ray_depths(fi.normalized[ia], fj.normalized[jb], s["pose_i"], s["pose_j"])
    cand = np.zeros(epi.shape, bool)
    inside = (z >= DEPTHS[0]) & (z <= DEPTHS[1])
    cand[ia[inside], jb[inside]] = True
    d2 = ((fi.descriptors[:, None, :].astype(float) - fj.descriptors[None]) ** 2).sum(-1)
    in_cand = np.where(cand, d2, np.inf)
    found = set()
    for a in np.flatnonzero(cand.any(1)):
        b = int(np.argmin(in_cand[a]))
        runner_up = np.delete(d2[a], b).min()
        if d2[a, b] < RATIO**2 * runner_up and int(np.argmin(in_cand[:, b])) == a:
            found.add((int(a), b))
    return found


def test_blocked_search_equals_the_dense_reference(scene, monkeypatch):
    """300 x 400 features (60 true correspondences, look-alikes of them on and off their
    epipolar segments, random distractors), a wide 15 px band so rows have many candidates;
    blocks of 7 rows: the same matches as the dense rule."""
    s = scene
    rng = np.random.default_rng(21)
    look_i = s["desc"][rng.integers(0, 60, 15)] + rng.normal(0, 0.012, (15, 128))
    look_j = s["desc"][rng.integers(0, 60, 15)] + rng.normal(0, 0.012, (15, 128))
    fi = with_extra(s["fi"], rng.uniform(-0.3, 0.3, (240, 2)),
                    np.vstack([look_i, rng.uniform(0, 1, (225, 128))]))
    fj = with_extra(s["fj"], rng.uniform(-0.3, 0.3, (340, 2)),
                    np.vstack([look_j, rng.uniform(0, 1, (325, 128))]))
    monkeypatch.setattr(matching, "BLOCK_CELLS", 7 * len(fj))
    assert len(matching.row_blocks(len(fi), len(fj))) == 43
    got = {(int(a), int(b))
           for a, b in match_pair(*views(fi, fj, s), PairGates(RATIO, 15.0, DEPTHS))}
    expected = dense_reference(fi, fj, s, 15.0)
    assert got == expected
    # non-trivial: most true pairs survive, some are lost to look-alikes
    assert 30 <= len(got & s["truth"]) < 60


# ---- band search and lazy distances against brute force ---------------------------------


def random_pose(rng: np.random.Generator, centre: np.ndarray) -> np.ndarray:
    """Camera-to-world pose at `centre` looking at about the origin, rolled at random."""
    return look_at(centre, rng.normal(0.0, 0.01, 3), up=tuple(rng.normal(0.0, 1.0, 3)))


@pytest.mark.parametrize("motion", ["sideways", "forward", "oblique", "tiny"])
def test_band_search_returns_exactly_the_brute_force_candidates(motion):
    """Random points, two cameras in each kind of relative motion (the epipole far outside
    the image, inside it, in between; a 0.1 mm baseline), two focal lengths: the pairs the
    band search returns are exactly those every-pair testing finds within the tolerance."""
    rng = np.random.default_rng({"sideways": 1, "forward": 2, "oblique": 3, "tiny": 4}[motion])
    centre_i = np.array([0.0, -0.06, 0.02])
    step = {"sideways": [0.03, 0.0, 0.0], "forward": [0.0, 0.02, -0.005],
            "oblique": [0.02, 0.015, 0.01], "tiny": [1e-4, 0.0, 0.0]}[motion]
    pose_i = random_pose(rng, centre_i)
    pose_j = random_pose(rng, centre_i + np.array(step))
    E = essential_matrix(pose_i, pose_j)
    f_i, f_j = 700.0, 1100.0
    xi = rng.uniform(-0.4, 0.4, (500, 2))
    xj = rng.uniform(-0.4, 0.4, (600, 2))
    hi = np.column_stack([xi, np.ones(len(xi))])
    hj = np.column_stack([xj, np.ones(len(xj))])
    lines_j, lines_i = hi @ E.T, hj @ E
    alg = np.abs(lines_j @ hj.T)  # (Ni, Nj) |x_j' E x_i|
    distance = 0.5 * alg * (f_j / np.linalg.norm(lines_j[:, :2], axis=1)[:, None]
                            + f_i / np.linalg.norm(lines_i[:, :2], axis=1)[None, :])
    for tol in (0.5, 2.0, 20.0):
        ia, jb = epipolar_candidates(E, xi, xj, f_i, f_j, tol)
        expected = np.argwhere(distance <= tol)  # row-major: sorted by ia, then jb
        assert len(expected) > 30
        np.testing.assert_array_equal(np.column_stack([ia, jb]), expected)


@pytest.mark.parametrize("stride", [1, 8, 1000])
def test_lazy_ratio_matches_equal_the_dense_rule(stride, monkeypatch):
    """SIFT-like descriptors (integers 0..255; look-alike rows, exact duplicates for ties)
    and random candidate sets: the matches equal those of the rule on the whole distance
    matrix (best candidate; runner-up = nearest other feature of j, candidate or not;
    mutual among candidates, earliest row on ties), whichever columns the ratio test's
    first pass samples (all, every 8th, the first only)."""
    monkeypatch.setattr(matching, "SAMPLE_STRIDE", stride)
    rng = np.random.default_rng(5)
    db = rng.integers(0, 256, (300, 128)).astype(np.float32)
    da = rng.integers(0, 256, (250, 128)).astype(np.float32)
    near = rng.integers(0, 300, 150)
    da[:150] = np.clip(db[near] + rng.integers(-12, 13, (150, 128)), 0, 255)
    da[150:160] = da[140:150]  # identical rows: ties between rows
    db[290:] = db[near[:10]]  # identical columns: ties within a row
    cand = rng.random((250, 300)) < 0.08
    cand[np.arange(150), near] = rng.random(150) < 0.8  # most true pairs are candidates
    cand[200:] = False  # rows without candidates
    ia, jb = np.nonzero(cand)
    got = matching.ratio_mutual_matches(da, db, ia, jb, 0.8)
    d2 = ((da[:, None, :].astype(float) - db[None]) ** 2).sum(-1)
    in_cand = np.where(cand, d2, np.inf)
    expected = []
    for a in np.flatnonzero(cand.any(1)):
        b = int(np.argmin(in_cand[a]))
        runner_up = np.delete(d2[a], b).min()
        if d2[a, b] < 0.8**2 * runner_up and int(np.argmin(in_cand[:, b])) == a:
            expected.append((a, b))
    assert len(expected) > 40
    np.testing.assert_array_equal(got, np.array(expected).reshape(-1, 2))
