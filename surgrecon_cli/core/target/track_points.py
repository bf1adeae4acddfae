"""Where the template points are in a frame's images: tracks chained from the frame
tracked from (small motion), guided by each camera's measured image motion, and points
lost there re-acquired from the template's own images. Pure OpenCV/numpy on arrays.

Per camera:
1. chain: the points visible at their latest positions are tracked from the previous
   image (where they were found there, else their projection if another camera saw them
   there: a point no camera saw has no measured position to project). In the first camera that
   can, they start at their latest position projected now or where they were (the prior
   whose pilot sample tracks more points), moved by the image motion measured on that
   pilot sample (core/tracking.track_adaptive); in every later camera, at their latest
   positions moved by the scene's rigid motion that the first camera's tracks show
   (`scene_motion`), without pilots (piloted after all where fewer than
   MIN_PREDICTED_SHARE of them are found: that camera moved otherwise). So a camera or
   scene moving 6-15 px a frame is followed whether or not the poses say so, mostly by one
   forward pass at full resolution; the tracks that failed, or slid beyond the reach of
   the pass's pyramid depth, are tracked again from their guesses moved by their found
   neighbours' flow (core/target/tracking.retrack_from_neighbours);
2. anchor: the points not found so (lost in the previous frame, newly back in view, or
   failed) are tracked from the template's image of that camera, starting at their
   template pixel moved by the template-to-now image motion fitted on the chained tracks
   or, with too few of those (tracking lost), on ORB matches (core/target/reacquire.py):
   points lost for a while come back (from the base's own images where the base is
   the template's frame: a chain that lost its way gets a second start). The chained
   tracks are kept as they are: tracked again from the template's appearance after a
   sweep of 10 deg or more, KLT's
   translation-only window is biased by the changed perspective and shading (measured on
   `rig-sweep` after 4 frames: 0.35 px median, 1.1 px p95; chained 0.2 px, 0.6 px), more
   than the chain's drift over the same frames (step 3 aligns the frame-0 patch warped
   to the current view instead);
3. lock: every found point with a frame-0 pixel in that camera is moved to where its
   frame-0 patch, warped by the local image map of its neighbouring tracks, matches best
   (core/target/template_lock.py): the drift the chain and the base's tracks carried is
   taken out; cameras of one narrow stereo head share each point's correction (the mean of
   their views', `shared_drift`), which keeps the pair's disparity. The chained pixels held
   for the next frame (`rig.chains`) stay as tracked, so that a frame tracked again through
   its previous frame finds the same ones. A frame one step from its base that is no
   later frame's base is not locked (`FrameInput.lock`): nothing starts from its tracks,
   so their one step of drift goes no further (on real-texture SurgT clips turned 3.5° a
   frame their error rose from ~0.085 to ~0.10 px, which the frame's measured tracking
   noise follows; no registered position or label moved, docs/tracking-speed.md);
4. stereo: the two views of a point in a narrow stereo pair (a `lock_groups` group of two
   cameras) are moved apart so that their disparity is the one the pair's images of this
   instant show (core/target/stereo_check.py): a view that slipped along its epipolar line
   no longer makes millimetres of false depth.

A frame whose previous frame is not its base (re-basing every N_T >= 2 frames) is chained
through the previous frame's images (base -> previous -> frame, `_via`: the previous
frame's chained pixels are held in `Rig.chains` when this process tracked it, else tracked
again), with the points lost on the way tracked directly from the base (`_direct`: guided
by the scene's motion the first camera's chained tracks show, those that fail tracked again
from the flow of the chained tracks around them): one frame's step of tissue pressed by a
tool. Points lost in the chain are tracked again from their guess moved by the median
departure of the tracks found around them (core/target/tracking.neighbour_flow), and the
anchor step's guesses are moved the same way by the chained tracks around them.
"""

from __future__ import annotations

from dataclasses import replace
from functools import partial

import cv2
import numpy as np

from ..geometry.cameras import CameraModel, in_image, project, undistort_pixels
from ..geometry.poses import invert_pose
from ..geometry.tool import tool_pixel_mask
from ..noise.model import localisation_variance_px2
from .frame_inputs import FrameInput, Rig, Sighting, TemplateData
from .reacquire import descriptor_motion
from .stereo_check import disparity_errors, stereo_match
from .template_lock import lock_groups, lock_to_template, shared_drift
from .tracking import (
    TrackingView,
    TrackPrior,
    apply_motion,
    image_motion,
    neighbour_flow,
    retrack_from_neighbours,
    track_adaptive,
    track_first,
)

KLT_BORDER_PX = 8.0  # a track starts this far inside the image at least (px)
MIN_SCENE_FIT = 12  # tracks of one camera needed to measure the scene's motion (PnP)
SCENE_FIT_PX = 2.0  # RANSAC inlier bound of that fit (px)
MIN_PREDICTED_SHARE = 0.8  # ours: a camera tracking fewer from the predicted guesses is piloted


def visible_points(
    points: np.ndarray,
    camera: CameraModel,
    pose: np.ndarray,
    occlusion_depth_m: float,
    cell_px: int = 8,
    border: float = KLT_BORDER_PX,
):
    """Predicted pixels (N, 2) and visibility (N,) of points in one camera: in front, inside
    the image (with a KLT border), and not behind other points of the cloud (a z-buffer on
    `cell_px` cells, tolerance `occlusion_depth_m` m)."""
    uv, z = project(points, pose, camera)
    ok = (z > 0) & in_image(uv, camera, border) & np.isfinite(points).all(1)
    cells_x = camera.width // cell_px + 1
    cell = np.full(len(points), -1)
    cell[ok] = (uv[ok, 1] // cell_px).astype(int) * cells_x + (uv[ok, 0] // cell_px).astype(int)
    zbuf = np.full(cells_x * (camera.height // cell_px + 1), np.inf)
    np.minimum.at(zbuf, cell[ok], z[ok])
    ok[ok] &= z[ok] <= zbuf[cell[ok]] + occlusion_depth_m
    return uv, ok


def scene_motion(latest: np.ndarray, pixels: np.ndarray, model: CameraModel,
                 pose: np.ndarray) -> tuple[np.ndarray, float] | None:
    """The motion (4, 4) of the scene in the world that moves points at `latest` (K, 3) m
    to where one camera (cam-to-world `pose`) found them, pixels (K, 2), robustly
    (RANSAC PnP on the undistorted rays, SCENE_FIT_PX), with its inliers' 95th-percentile
    residual px; None with fewer than MIN_SCENE_FIT inliers. A rig moving without the
    poses saying so, or the scene moving as a whole, moves every camera's image by this
    one motion: the tracks found in one camera predict the others'."""
    if len(latest) < MIN_SCENE_FIT or not np.isfinite(pose).all():
        return None
    rays = undistort_pixels(pixels, model)
    world_to_cam = invert_pose(pose)
    rvec0 = cv2.Rodrigues(world_to_cam[:3, :3])[0]
    focal = float(model.K[0, 0])
    found, rvec, tvec, inliers = cv2.solvePnPRansac(
        latest.astype(np.float64), rays.astype(np.float64), np.eye(3), None, rvec0.copy(),
        world_to_cam[:3, 3].reshape(3, 1).copy(), useExtrinsicGuess=True,
        reprojectionError=SCENE_FIT_PX / focal, iterationsCount=50,
        flags=cv2.SOLVEPNP_ITERATIVE)
    if not found or inliers is None or len(inliers) < MIN_SCENE_FIT:
        return None
    seen = np.eye(4)  # world -> camera as the tracks see it
    seen[:3, :3], seen[:3, 3] = cv2.Rodrigues(rvec)[0], tvec.ravel()
    motion = pose @ seen
    moved = latest[inliers.ravel()] @ motion[:3, :3].T + motion[:3, 3]
    error = np.linalg.norm(project(moved, pose, model)[0] - pixels[inliers.ravel()], axis=1)
    return motion, float(np.percentile(error, 95))


def _starts(latest: np.ndarray, base: Sighting, model: CameraModel, c: int) -> np.ndarray:
    """Where the points (N, 3) m at `latest` start in the base's image of camera c (N, 2)
    px (NaN: not tracked): where they were found there, else, for a point another camera
    found, its position projected there."""
    start = base.pixels[:, c].copy()
    # A point seen by no camera of the base frame has only the registration's extrapolated
    # position there: projected into the previous image, a stale one (a point back from
    # out of view after the view turned) starts KLT on another point's texture, which it
    # then tracks consistently in every camera (measured on SurgT turned 2°/frame: 5-10 %
    # of the points 40 px off for good). Those are re-acquired from the template (_anchor).
    missing = ~np.isfinite(start).all(1) & np.isfinite(base.pixels).all(2).any(1)
    if missing.any() and np.isfinite(base.poses[c]).all():
        start[missing] = project(latest[missing], base.poses[c], model)[0]
    return start


def _chain(latest: np.ndarray, base: Sighting, frame: FrameInput, rig: Rig, c: int,
           predicted: tuple[np.ndarray, float] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Step 1 for camera c: pixels (N, 2) (NaN = not found) and found (N,). `predicted`:
    the scene's motion measured in another camera (`scene_motion`) and its residual px:
    the guesses are the latest positions moved by it, without pilot tracks; where fewer
    than MIN_PREDICTED_SHARE of them are found, this camera moved otherwise (its pose is
    off) and its points are tracked again, piloted."""
    idx, start, prior = _chain_inputs(latest, base, frame, rig, c, predicted)
    prev, cur = base.views[c], frame.views[c]
    assert prev is not None and cur is not None  # find_points skips unusable cameras
    tracked, ok, _ = track_adaptive(prev, cur, start, prior, rig.cfg)
    if predicted is not None and ok.sum() < MIN_PREDICTED_SHARE * len(ok):
        return _chain(latest, base, frame, rig, c)
    pixels = np.full((len(latest), 2), np.nan)
    pixels[idx[ok]] = tracked[ok]
    return pixels, np.isfinite(pixels).all(1)


def _chain_inputs(latest: np.ndarray, base: Sighting, frame: FrameInput, rig: Rig, c: int,
                  predicted: tuple[np.ndarray, float] | None
                  ) -> tuple[np.ndarray, np.ndarray, TrackPrior]:
    """What `_chain` tracks in camera c: the rows (K,) of the points, their start pixels
    (K, 2) in the base image and their prior."""
    cur_pose, model, cfg = frame.poses[c], rig.models[c], rig.cfg
    guess, visible = visible_points(latest, model, cur_pose, cfg.occlusion_depth_m)
    if predicted is not None:
        motion = predicted[0]
        guess = project(latest @ motion[:3, :3].T + motion[:3, 3], cur_pose, model)[0]
        visible &= np.isfinite(guess).all(1) & in_image(np.nan_to_num(guess, nan=-1e9), model)
    start = _starts(latest, base, model, c)
    visible &= np.isfinite(start).all(1) & in_image(start, model, KLT_BORDER_PX)
    idx = np.flatnonzero(visible)
    # Two priors, piloted: the latest position projected with the current pose (the poses
    # know how the camera moved), or where the point was (its latest position is stale
    # where the registration lagged, or the poses miss the motion: an untracked camera).
    if predicted is not None:
        prior = TrackPrior(guess[idx], 2.0 * max(predicted[1], 1.0))
    else:
        prior = TrackPrior(guess[idx], alternative=start[idx])
    return idx, start[idx], prior


def _anchor(anchor: TrackingView, anchor_pixels: np.ndarray, pixels: np.ndarray,
            frame: FrameInput, rig: Rig, c: int) -> tuple[np.ndarray, np.ndarray]:
    """Step 2 for camera c: the chained pixels (N, 2) (NaN = not found) and found (N,),
    with the points not found re-acquired from the template's image `anchor` (the points
    at anchor_pixels (N, 2) px there), from where the image motion since the template puts
    them: fitted to the chained tracks, or where they are too few (tracking lost), to ORB
    matches between the two images (core/reacquire.descriptor_motion). A point guessed
    behind a tool (`_unmasked`) is not tracked: its track would have to leave the tool's
    mask, which the guesses' error does not reach (on the 5-camera frame-cost log, of ~20
    such points a frame that tracked, none ended outside the mask)."""
    cur, model = frame.views[c], rig.models[c]
    assert cur is not None  # find_points skips unusable cameras
    found = np.isfinite(pixels).all(1)
    has = np.isfinite(anchor_pixels).all(1) & in_image(
        np.nan_to_num(anchor_pixels, nan=-1e9), model, KLT_BORDER_PX)
    pairs = has & found
    motion = image_motion(anchor_pixels[pairs], pixels[pairs])
    if motion is None:
        motion = descriptor_motion(anchor, cur)
    if motion is None:
        return pixels, found
    guess = apply_motion(motion, np.nan_to_num(anchor_pixels))
    # Tissue the tool pushed moved farther than the image motion says: the chained tracks
    # around a lost point say by how much (tracking.neighbour_flow).
    lost = np.flatnonzero(has & ~found)
    local = neighbour_flow(anchor_pixels[pairs], pixels[pairs] - guess[pairs],
                           anchor_pixels[lost])
    near = np.isfinite(local).all(1)
    guess[lost[near]] += local[near]
    idx = np.flatnonzero(has & ~found & in_image(guess, model, KLT_BORDER_PX))
    idx = idx[_unmasked(guess[idx], frame, rig, c)]
    tracked, ok, _ = track_adaptive(anchor, cur, anchor_pixels[idx], TrackPrior(guess[idx]),
                                    rig.cfg)
    pixels = pixels.copy()
    pixels[idx[ok]] = tracked[ok]
    return pixels, np.isfinite(pixels).all(1)


def _via(latest: np.ndarray, base: Sighting, frame: FrameInput, rig: Rig) -> Sighting:
    """The sighting to chain `frame` from when its previous frame (`frame.previous`) lies
    between it and the base: the points tracked from the base into the previous frame's
    images (`find_points` without anchoring; held in `rig.chains` when the previous frame
    was tracked in this process, else tracked again). Tissue pressed by a tool deforms its
    texture: a KLT window tracked over two frames of the press drifts off where one frame's
    step does not (measured on the `stereo` simulator from frame 2 to 4 with the true start
    and guess: 6.9 px median; from 3 to 4: 0.9 px). The base itself where the previous
    frame is unusable."""
    prev = frame.previous
    assert prev is not None
    if any((v is None) != (w is None) for v, w in zip(prev.views, frame.views, strict=True)):
        return base
    held = None if rig.chains is None else rig.chains.get(rig.chains.key(latest, base, prev.index))
    if held is None:
        held, _, _ = find_points(latest, base, prev, rig)
    return Sighting(prev.views, prev.poses, held)


def _direct(latest: np.ndarray, base: Sighting, frame: FrameInput, rig: Rig, c: int,
            lost: tuple[np.ndarray, tuple[np.ndarray, float] | None, np.ndarray]
            ) -> tuple[np.ndarray, np.ndarray]:
    """`_chain` from the base straight into `frame` for camera c of the points lost (N,)
    bool on the way through the previous frame (lost[0]), guided by the scene's motion
    (lost[1], `scene_motion`; None: piloted); those that fail are tracked again from their
    guesses moved by the flow of the tracks the chain found around them (lost[2], (N, 2)
    px, NaN = not found; their departures from the same straight guesses), as
    `retrack_from_neighbours` does. Pixels (N, 2) of the lost points (NaN = not found),
    found (N,)."""
    rows, predicted, chained = lost
    prev, cur = base.views[c], frame.views[c]
    assert prev is not None and cur is not None
    # The chained tracks' departures from their own straight guesses guide the retries;
    # not after pilots (no predicted motion), whose image motion moved the lost points'
    # guesses and not theirs. A point's start and guess are the same in any subset: the
    # lost points and the chained ones are set up at once.
    around = np.isfinite(chained).all(1) if predicted is not None else np.zeros_like(rows)
    both, start, prior = _straight_inputs(latest, base, frame, rig, c,
                                          (rows | around, predicted))
    mine = rows[both]
    idx, near = both[mine], both[~mine]
    alternative = None if prior.alternative is None else prior.alternative[mine]
    tracked, ok, guess = track_first(prev, cur, start[mine], TrackPrior(
        prior.guess[mine], prior.motion_px, alternative), rig.cfg)
    if predicted is not None and not ok.all():
        tracked, ok = retrack_from_neighbours(
            (prev, cur), np.vstack([start[mine], start[~mine]]),
            np.vstack([guess, prior.guess[~mine]]),
            (np.vstack([tracked, chained[near]]),
             np.concatenate([ok, np.ones(len(near), bool)])), rig.cfg)
        tracked, ok = tracked[:len(idx)], ok[:len(idx)]
    pixels = np.full((len(latest), 2), np.nan)
    pixels[idx[ok]] = tracked[ok]
    return pixels, np.isfinite(pixels).all(1)


def _straight_inputs(latest: np.ndarray, base: Sighting, frame: FrameInput, rig: Rig, c: int,
                     subset: tuple[np.ndarray, tuple[np.ndarray, float] | None]
                     ) -> tuple[np.ndarray, np.ndarray, TrackPrior]:
    """What `_chain` from the base straight into `frame` tracks in camera c of the points
    subset[0] (N,) bool, guided by subset[1] (`_chain_inputs`): their rows (K,), start
    pixels (K, 2) and prior. Each point's start and guess are the same in any subset."""
    rows, predicted = subset
    only = Sighting(base.views, base.poses, np.where(rows[:, None, None], base.pixels, np.nan))
    return _chain_inputs(latest, only, replace(frame, previous=None), rig, c, predicted)


def _unmasked(pixels: np.ndarray, frame: FrameInput, rig: Rig, c: int) -> np.ndarray:
    """(M,) bool: pixels (M, 2) of camera c inside its image (2 px in) and off the tools."""
    tools = frame.tool_pose if frame.camera_tool_pose is None else frame.camera_tool_pose[c]
    return in_image(pixels, rig.models[c], 2.0) & ~tool_pixel_mask(
        pixels, rig.models[c], frame.poses[c], tools, rig.tools)


def _scene(latest: np.ndarray, pixels: np.ndarray, found: np.ndarray, model: CameraModel,
           pose: np.ndarray) -> tuple[np.ndarray, float] | None:
    """`scene_motion` of the found (N,) tracks at pixels (N, 2) of points at latest (N, 3)."""
    fit = found & np.isfinite(latest).all(1)
    return scene_motion(latest[fit], pixels[fit], model, pose)


def find_points(latest: np.ndarray, base: Sighting, frame: FrameInput, rig: Rig,
                anchor_views: list[TrackingView | None] | None = None,
                template: TemplateData | None = None):
    """Pixels (N, C, 2) where the template points are found in `frame`'s images (NaN = not
    found), found (N, C) bool and each found pixel's localisation variance (N, C) px² (inf
    where not found).

    latest (N, 3) m: positions at the base frame; `base`: the base frame's views, poses and
    where each point was found in its images (NaN: not found); rig: the cameras, the target
    config, the tools (masked out) and the memo of chained tracks (`rig.chains`: a frame
    tracked straight from its base leaves its chained pixels there for the next frame's
    `_via`); anchor_views: the template's images, template: where its points are in them
    (`TemplateData.pixels` (N, C, 2)) and their nearest others there (`TemplateData.
    neighbours`, the lock's local maps) (either None: no anchoring). When the base is the
    template's frame,
    the anchor step is a second try from the same images, from the image motion fitted to
    the tracks that were found or, with too few (measured: SurgT at 320x256 turned 7° since
    the template, 5 % of the points found), to ORB matches."""
    models, cur_poses, cfg = rig.models, frame.poses, rig.cfg
    n, n_cams = len(latest), len(models)
    direct = None  # the base, where the frame is chained through its previous frame
    if frame.previous is not None:
        via = _via(latest, base, frame, rig)
        direct, base = (base, via) if via is not base else (None, base)
    pixels = np.full((n, n_cams, 2), np.nan)
    found = np.zeros((n, n_cams), bool)
    localisation = np.full((n, n_cams), np.inf)
    chained = np.full((n, n_cams, 2), np.nan)  # by the chain alone (for rig.chains)
    predicted = None  # the scene's motion the first camera's chained tracks show
    drift = np.full((n, n_cams, 2), np.nan)  # the lock's corrections (NaN: none)
    for c in range(n_cams):
        cur, prev = frame.views[c], base.views[c]
        if cur is None or prev is None:
            continue
        px, ok = _chain(latest, base, frame, rig, c, predicted)
        chain_ok = ok.copy()
        if predicted is None:  # the first camera whose tracks show it
            predicted = _scene(latest, px, ok, models[c], cur_poses[c])
        if direct is not None:  # lost on the way through the previous frame: tracked directly
            back, back_ok = _direct(latest, direct, frame, rig, c,
                                    (~ok, predicted, np.where(ok[:, None], px, np.nan)))
            back_ok[back_ok] = _unmasked(back[back_ok], frame, rig, c)
            px[back_ok], ok[back_ok] = back[back_ok], True
        anchor = None if anchor_views is None else anchor_views[c]
        if anchor is not None and template is not None:
            px, ok = _anchor(anchor, template.pixels[:, c], px, frame, rig, c)
            if frame.lock:
                drift[:, c] = lock_to_template(anchor, cur, template.pixels[:, c],
                                               np.where(ok[:, None], px, np.nan),
                                               cfg.klt_window_px, template.neighbours[c])
        rows = np.flatnonzero(ok)
        rows = rows[_unmasked(px[rows], frame, rig, c)]
        pixels[rows, c] = px[rows]
        found[rows, c] = True
        localisation[rows, c] = localisation_variance_px2(
            cur.grey_f32, px[rows], cfg.klt_window_px, cur.noise_sigma)
        mine = rows[chain_ok[rows]]
        chained[mine, c] = px[mine]
    if frame.previous is None and rig.chains is not None:
        rig.chains.put(rig.chains.key(latest, base, frame.index), chained)
    if anchor_views is not None and template is not None:  # not without anchors (`_via`)
        groups = lock_groups(cur_poses[:, :3, 3], latest)
        pixels += np.where(found[..., None], shared_drift(drift, groups), 0.0)
        for pair in (g for g in groups if len(g) == 2):
            _stereo_disparity(pixels, found, pair, frame, rig,
                              (anchor_views, None if template is None else template.pixels))
    return pixels, found, localisation


def _stereo_disparity(pixels: np.ndarray, found: np.ndarray, pair: np.ndarray,
                      frame: FrameInput, rig: Rig,
                      anchors: tuple[list[TrackingView | None] | None, np.ndarray | None]
                      ) -> None:
    """Step 4, in place on pixels (N, C, 2): the two views of each point of a narrow stereo
    pair (cameras `pair`) are moved apart by half the error of their disparity each
    (core/target/stereo_check.py), their mean kept. The template's own match is made once
    per run (`rig.pair_matches`). anchors: the template's views and pixels (N, C, 2)."""
    anchor_views, anchor_pixels = anchors
    a, b = int(pair[0]), int(pair[1])
    view_a, view_b = frame.views[a], frame.views[b]
    if anchor_views is None or anchor_pixels is None or view_a is None or view_b is None:
        return
    anchor_a, anchor_b = anchor_views[a], anchor_views[b]
    if anchor_a is None or anchor_b is None:
        return
    at_anchor = anchor_pixels[:, [a, b]]
    template_match = partial(stereo_match, (anchor_a, anchor_b), at_anchor, rig.cfg)
    anchor_match = (template_match() if rig.pair_matches is None
                    else rig.pair_matches.get((a, b), template_match))
    current = np.where(found[:, [a, b], None], pixels[:, [a, b]], np.nan)
    error = disparity_errors((view_a, view_b), current, at_anchor, anchor_match, rig.cfg)
    fix = np.isfinite(error).all(1)
    pixels[fix, a] -= error[fix] / 2
    pixels[fix, b] += error[fix] / 2
