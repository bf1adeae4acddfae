"""Which camera pairs link into the template, and whether separately linked groups agree.

Minimum of verified matches per pair: the larger of `min_pair_matches` (a floor) and
`min_pair_match_fraction` x the features of the poorer image of the pair.

- The floor makes a link of wrong matches alone implausible. A wrong match is kept only
  when its feature in the other image falls inside the short epipolar segment (±epipolar_px
  around the line, cut to the depth range) AND passes the ratio and mutual tests; the
  segment covers well under 1 % of an image. Measured: with two cameras of a 300x250 px
  simulator rig displaced by 3 mm (their epipolar geometry with the others wrong), those
  pairs kept 0-1 verified matches of 600-800 features (tests/test_template_gate.py), so a
  dozen is far in the tail of that count (Poisson with mean ~1: P(>= 12) < 1e-8). 12 is
  also well above the 5-8 correspondences that fix two views' relative geometry, so a link
  carries information. The default floor is 15.
- Wrong matches grow with the features (more candidates in each segment), so on large
  images the minimum grows with them: 1 % of the poorer image's features (30-36 on the
  simulator's 640x480 images with 2900-3600 features, whose pairs verify 96-721 matches;
  the former fixed minimum was 40; the floor, 15, on 300x250 images with 600-800 features,
  whose overlapping pairs verify 25-68 and were split into two groups by the fixed 40).

Groups: cameras linked by verified pairs reconstruct together; two groups are not linked,
so nothing ties their reconstructions but the poses. When a candidate pair across two groups
(they should share a view) has at least `min_pair_matches` descriptor matches, found without
the poses, that fit one epipolar geometry (a RANSAC fundamental matrix), the images do share
a view; if the poses put those matches far off their epipolar lines (median beyond
DISAGREE_EPIPOLAR x epipolar_px), the groups' poses or calibrations disagree and each
group reconstructs the surface elsewhere: reported with the groups, not merged silently.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from .features import Features
from .matching import CameraView, epipolar_distances_px, essential_matrix

DESCRIPTOR_RATIO = 0.8  # Lowe's ratio for matching without poses
DISAGREE_EPIPOLAR = 3.0  # ours: image-consistent matches this many x epipolar_px off disagree


def pair_minimums(n_features: Sequence[int], floor: int, fraction: float) -> np.ndarray:
    """(C, C) verified matches each pair needs to be linked (see the module docstring)."""
    n = np.asarray(n_features, float)
    poorer = np.minimum(n[:, None], n[None, :])
    return np.maximum(floor, np.ceil(fraction * poorer)).astype(int)


FEW_TO_LOWER = 8  # ours: below this many verified matches a lower minimum links nothing real
FEW_FEATURES = 50  # ours: an image with fewer features than this is blank (SurgT: ~4000)


def unlinked_message(counts: dict[tuple[int, int], int], minimums: np.ndarray,
                     names: Sequence[str], floor: int, fraction: float,
                     features: Sequence[int] = ()) -> str:
    """One line: no pair reached its minimum, with each pair's verified/needed matches and
    what to change. Lowering the minimum is suggested only when the best pair came close
    (FEW_TO_LOWER matches or more); cameras with fewer than FEW_FEATURES features (`features`,
    per camera) say the frame-0 images are blank, dark or blurred; no candidate pair, or next
    to no verified matches, says that the calibration or poses place the cameras' views apart
    (a baseline in the wrong unit, a wrong T): no minimum would link real matches then."""
    head = "no camera pair has enough verified matches to link at frame 0"
    few = [f"{names[c]} {n}" for c, n in enumerate(features) if n < FEW_FEATURES]
    if few and len(few) >= len(features) - 1:  # no two cameras with features to match
        return (f"{head}: frame 0's images have next to no features (camera features: "
                f"{', '.join(few)}): blank, dark or blurred; start the log where the views "
                "are clear (e.g. convert --frames N:)")
    if not counts:
        return (f"{head}: the poses and calibration put no two cameras' views over one "
                "surface (template.min_view_overlap, template.working_distance_m): check the "
                "calibration's baseline (T, and its unit: convert --units) and the poses")
    listed = ", ".join(f"{names[i]}-{names[j]} {n}/{minimums[i, j]}"
                       for (i, j), n in sorted(counts.items(), key=lambda kv: -kv[1]))
    best = max(counts.values())
    if best < FEW_TO_LOWER:
        return (f"{head} (pair verified/needed: {listed}): so few means the calibration or "
                "poses put the true matches off their epipolar lines or outside the depths "
                "searched (template.depth_range x template.working_distance_m): check the "
                "calibration's baseline (T, and its unit: convert --units), the eyes' order "
                "and the poses")
    return (f"{head} (pair verified/needed: {listed}); the minimum is "
            f"max(template.min_pair_matches = {floor}, template.min_pair_match_fraction = "
            f"{fraction} x the poorer image's features): lower them (e.g. "
            f"template.min_pair_matches = {max(min(counts.values()), FEW_TO_LOWER)}) if these "
            "pairs do share a view, or check the calibration and poses")


def link_warnings(groups: list[list[int]], counts: dict[tuple[int, int], int],
                  minimums: np.ndarray, names: Sequence[str],
                  disagreeing: list[tuple[list[int], list[int], float]]) -> list[str]:
    """One line per link problem a user must hear of: each pair of groups whose images match
    but whose poses do not (`disagreeing`, from `group_disagreements`); each camera in no
    verified pair (it gives no template point), with its best pair's verified matches
    (`counts` of pair (i, j)) against that pair's minimum; and, when the cameras form several
    linked groups that no check compared, that nothing ties them together."""
    lines = [f"cameras {' '.join(names[c] for c in a)} and cameras "
             f"{' '.join(names[c] for c in b)} are not linked: their images match (matches "
             f"found without the poses) but their poses put those matches {px:.1f} px "
             "(median) off the epipolar lines; they reconstruct the surface apart: check "
             "their calibrations / poses" for a, b, px in disagreeing]
    for group in groups:
        if len(group) != 1:
            continue
        c = group[0]
        pairs = sorted((n, p) for p, n in counts.items() if c in p)
        best = ""
        if pairs:
            n, (i, j) = pairs[-1]
            best = (f"; its best pair {names[i]}-{names[j]} has {n} matches of the "
                    f"{minimums[i, j]} needed (template.min_pair_matches, "
                    "template.min_pair_match_fraction)")
        lines.append(f"camera {names[c]} is linked to no other camera and gives no template "
                     f"point{best}")
    linked = [g for g in groups if len(g) >= 2]
    if len(linked) >= 2 and not disagreeing:
        lines.append(f"cameras form {len(linked)} separately linked groups ("
                     + "; ".join(" ".join(names[c] for c in g) for g in linked)
                     + "): no verified match ties them, each reconstructs in its own "
                     "cameras' poses, so a pose or calibration disagreement between the "
                     "groups goes unchecked")
    return lines


def group_disagreements(views: list[CameraView], groups: list[list[int]],
                        pairs: list[tuple[int, int]], floor: int,
                        epipolar_px: float) -> list[tuple[list[int], list[int], float]]:
    """Pairs of camera groups whose images agree but whose poses do not: (group a, group b,
    median epipolar distance px) for the candidate `pairs` (i, j) across two groups of two or
    more cameras (see the module docstring); views (C,) each camera's features, pose and
    focal length."""
    features = [v.features for v in views]
    poses = [v.pose for v in views]
    focal = [v.focal for v in views]
    multi = [g for g in groups if len(g) >= 2]
    member = {c: k for k, g in enumerate(multi) for c in g}
    worst: dict[tuple[int, int], float] = {}
    for i, j in pairs:
        a, b = member.get(i), member.get(j)
        if a is None or b is None or a == b:
            continue
        xi, xj = _consistent_matches(features[i], features[j], focal[i], focal[j], floor,
                                     epipolar_px)
        if len(xi) < floor:
            continue
        off = float(np.median(epipolar_distances_px(essential_matrix(poses[i], poses[j]),
                                                    xi, xj, focal[i], focal[j])))
        key = (min(a, b), max(a, b))
        if off > DISAGREE_EPIPOLAR * epipolar_px and off > worst.get(key, 0.0):
            worst[key] = off
    return [(multi[a], multi[b], round(px, 1)) for (a, b), px in sorted(worst.items())]


def _consistent_matches(fi: Features, fj: Features, f_i: float, f_j: float, floor: int,
                        epipolar_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Normalised points (M, 2) of each image of the mutual, ratio-tested descriptor matches
    (no pose used) that fit one fundamental matrix (RANSAC, `epipolar_px`), or none."""
    empty = (np.zeros((0, 2)), np.zeros((0, 2)))
    if len(fi) < floor or len(fj) < floor:
        return empty
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    pairs = [m for m in matcher.knnMatch(fi.descriptors, fj.descriptors, k=2)
             if len(m) == 2 and m[0].distance < DESCRIPTOR_RATIO * m[1].distance]
    back = {m.queryIdx: m.trainIdx for m in matcher.match(fj.descriptors, fi.descriptors)}
    ia = np.array([m[0].queryIdx for m in pairs if back.get(m[0].trainIdx) == m[0].queryIdx], int)
    jb = np.array([m[0].trainIdx for m in pairs if back.get(m[0].trainIdx) == m[0].queryIdx], int)
    if len(ia) < max(floor, 8):
        return empty
    xi, xj = fi.normalized[ia], fj.normalized[jb]
    _, inlier = cv2.findFundamentalMat(xi * f_i, xj * f_j, cv2.FM_RANSAC, epipolar_px, 0.999)
    if inlier is None:
        return empty
    keep = inlier.ravel().astype(bool)
    return xi[keep], xj[keep]
