"""Checks of a stereo run built from its images alone, as a user without ground truth would
(used by benchmarks/real.py): the run's cameras 0 and 1 are rectified with the run's own
calibration (intrinsics and the relative pose of the two cameras at each frame).

- `ncc_localisation_px`: an independent localisation check. Every template point seen by
  camera 0 is matched into the rectified right image by normalised cross-correlation
  (cv2.matchTemplate, 11x11 patch, parabolic sub-pixel peak), a different method from the
  pipeline's detector and tracker. On a rectified pair the true vertical disparity is 0, so
  the matched row offset samples the two images' localisation errors: σ per image and axis
  = 1.4826 median|dy| / √2 (about 0, not the median: a calibration's vertical offset is
  error the pipeline's triangulation sees too; SurgT's is 0.36 px).
- `disparity_localisation_px`: the run's own localisation error where it makes depth, along
  the epipolar lines: its disparities against NCC's and StereoSGBM's on the rectified
  frame-0 pair, the three errors separated by the three-cornered hat (the function's
  docstring). Unlike the row offsets above it measures the run's matches, not NCC's.
- `ground_truth_localisation_px` (simulator only): the detected pixel in camera 0 cast onto
  the true surface with the true pose, projected into camera 1 with its true pose, against
  the pixel detected there: two localisation errors, σ = 1.4826 MAD / √2 per axis.
- `rigid_tracking_px`: an independent check of the tracking noise on a rigid scene seen by a
  moving camera (the SurgT clip): in each camera, the template pixels and the pixels tracked
  at frame k obey one fundamental matrix (on undistorted pixels: RANSAC at 1 px for the
  inliers, then the normalised 8-point least squares on them; RANSAC's own model alone is
  fitted to 8 tracks and scatters the residuals by frame); a track's distance to its
  epipolar line is its tracking error across that line (the frame-0 pixel's own error
  moves with the track). σ = 1.4826 median |d| over a frame's tracks and cameras (the 7
  parameters fitted to hundreds of tracks take ~1 % of it), then the median over frames, as
  the run reports its tracking_px.
- `ground_truth_tracking_px` (simulator only): each camera's frame-0 pixel cast onto the true
  surface with the true pose, the material point it hits followed to frame k and projected
  with the true pose there, against the pixel tracked at frame k: σ = 1.4826 MAD per axis
  in each frame, then the median over frames.
- `rigid_scene_motion`: the rigid motion of a rigid scene seen by a moving endoscope: SIFT
  matches of frame 0 and frame k (rectified left images), frame 0's put in 3D by
  StereoSGBM, and the PnP pose (RANSAC, 1 px) of frame k's pixels.
- `reference_positions`: a dense reference of every template point over time: DIS optical
  flow on camera 0 (frame to frame, kept where forward-backward agree within 0.5 px) and
  StereoSGBM depth on each rectified pair, back in the world frame with camera 0's pose.
"""

from __future__ import annotations

import cv2
import numpy as np

from surgrecon_cli.core.geometry.cameras import CameraModel, pixel_rays, project
from surgrecon_cli.core.noise.model import MAD_TO_SIGMA
from surgrecon_cli.io.run.ingest_store import IngestedLog

PATCH = 11  # px, side of the NCC patch
SEARCH = (4, 24)  # px searched around the expected match: rows, columns
FB_PX = 0.5  # forward-backward flow disagreement beyond which a track is dropped (px)


def _mad_sigma(values: np.ndarray, centre: bool = True) -> float:
    """σ from the median absolute deviation, about the median (centre) or about 0."""
    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    if not v.size:
        return float("nan")
    return float(MAD_TO_SIGMA * np.median(np.abs(v - (np.median(v) if centre else 0.0))))


class Rectified:
    """Rectification of cameras 0 and 1 of a run at one frame (their poses (2, 4, 4))."""

    def __init__(self, models: tuple[CameraModel, ...], poses: np.ndarray) -> None:
        m0, m1 = models[0], models[1]
        rel = np.linalg.inv(poses[1]) @ poses[0]  # camera 0 -> camera 1
        size = (m0.width, m0.height)
        self.r0, self.r1, self.p0, self.p1, self.q, _, _ = cv2.stereoRectify(
            m0.K, m0.dist, m1.K, m1.dist, size, rel[:3, :3], rel[:3, 3], alpha=0)
        self.models, self.pose0 = (m0, m1), poses[0]
        self.maps = [cv2.initUndistortRectifyMap(m.K, m.dist, r, p, size, cv2.CV_32FC1)
                     for m, r, p in ((m0, self.r0, self.p0), (m1, self.r1, self.p1))]

    def images(self, left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rectified grey images of an RGB pair."""
        return tuple(cv2.remap(cv2.cvtColor(im, cv2.COLOR_RGB2GRAY), mx, my, cv2.INTER_LINEAR)
                     for im, (mx, my) in zip((left, right), self.maps, strict=True))

    def left_pixels(self, pixels: np.ndarray) -> np.ndarray:
        """Camera-0 pixels (M, 2) in the rectified left image."""
        m = self.models[0]
        pts = np.asarray(pixels, np.float64).reshape(-1, 1, 2)
        return cv2.undistortPoints(pts, m.K, m.dist, R=self.r0, P=self.p0).reshape(-1, 2)

    def world(self, rect_xy: np.ndarray, disparity: np.ndarray) -> np.ndarray:
        """World points (M, 3) m of rectified left pixels (M, 2) with disparities (M,)."""
        h = np.column_stack([rect_xy, disparity, np.ones(len(rect_xy))]) @ self.q.T
        cam = (h[:, :3] / h[:, 3:4]) @ self.r0  # rectified camera 0 -> camera 0 (R0ᵀ x)
        return cam @ self.pose0[:3, :3].T + self.pose0[:3, 3]


def _sample(image: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Bilinear samples (M, ...) of an image (H, W[, K]) at (M, 2) px (NaN outside)."""
    img = np.asarray(image, np.float32)
    h, w = img.shape[:2]
    x, y = xy[:, 0], xy[:, 1]
    ok = np.isfinite(xy).all(1) & (x >= 0) & (y >= 0) & (x <= w - 2) & (y <= h - 2)
    out = np.full((len(xy), *img.shape[2:]), np.nan)
    x0, y0 = np.floor(x[ok]).astype(int), np.floor(y[ok]).astype(int)
    fx, fy = x[ok] - x0, y[ok] - y0
    if img.ndim == 3:
        fx, fy = fx[:, None], fy[:, None]
    out[ok] = ((1 - fx) * (1 - fy) * img[y0, x0] + fx * (1 - fy) * img[y0, x0 + 1]
               + (1 - fx) * fy * img[y0 + 1, x0] + fx * fy * img[y0 + 1, x0 + 1])
    return out


def _disparity(left: np.ndarray, right: np.ndarray, max_disp: int) -> np.ndarray:
    n = int(np.ceil(max(max_disp, 16) / 16) * 16)
    sgbm = cv2.StereoSGBM_create(minDisparity=0, numDisparities=n, blockSize=5,
                                 P1=8 * 25, P2=32 * 25, uniquenessRatio=10,
                                 mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)
    d = sgbm.compute(left, right).astype(np.float32) / 16.0
    d[d <= 0] = np.nan
    return d


def _ncc_matches(left: np.ndarray, right: np.ndarray, xy: np.ndarray, disparity: np.ndarray
                 ) -> np.ndarray:
    """NCC matches (M, 2) of rectified left pixels xy (M, 2) in the right image, searched
    SEARCH around the expected disparity (M,): the right pixel's row offset from the left
    one and its disparity (px), NaN where the search fails (edge, flat peak, NCC < 0.8).
    The left patch is sampled at the sub-pixel position itself, the peak by parabolas."""
    half, (sr, sc) = PATCH // 2, SEARCH
    out = np.full((len(xy), 2), np.nan)
    left_f = left.astype(np.float32)
    for i, ((x, y), dd) in enumerate(zip(xy, disparity, strict=True)):
        if not np.isfinite(dd):
            continue
        yi, xr = round(float(y)), round(float(x - dd))
        if (min(xr, yi) - half - sc < 0 or yi + half + sr >= left.shape[0]
                or max(round(float(x)), xr) + half + sc >= left.shape[1] or x < half):
            continue
        patch = cv2.getRectSubPix(left_f, (PATCH, PATCH), (float(x), float(y)))
        window = right[yi - half - sr:yi + half + sr + 1,
                       xr - half - sc:xr + half + sc + 1].astype(np.float32)
        score = cv2.matchTemplate(window, patch, cv2.TM_CCOEFF_NORMED)
        r, c = np.unravel_index(int(np.argmax(score)), score.shape)
        if (not (0 < r < score.shape[0] - 1 and 0 < c < score.shape[1] - 1)
                or score[r, c] < 0.8):
            continue
        peak = []
        for a, b, e in ((score[r - 1, c], score[r, c], score[r + 1, c]),
                        (score[r, c - 1], score[r, c], score[r, c + 1])):
            peak.append(0.5 * (a - e) / (a - 2 * b + e) if a - 2 * b + e < 0 else 0.0)
        out[i] = (yi - sr + r + peak[0] - y, x - (xr - sc + c + peak[1]))
    return out


def ncc_localisation_px(log: IngestedLog, pixels0: np.ndarray, max_disp: int = 160) -> float:
    """Independent localisation σ (px) on frame 0 from NCC row offsets (module docstring);
    pixels0 (M, 2) camera-0 pixels of template points."""
    rect = Rectified(log.models, log.poses[0, :2])
    left, right = rect.images(*log.frame_images(0)[:2])
    xy = rect.left_pixels(pixels0)
    rows = _ncc_matches(left, right, xy, _sample(_disparity(left, right, max_disp), xy))[:, 0]
    return _mad_sigma(rows[np.isfinite(rows)], centre=False) / np.sqrt(2.0)


def disparity_localisation_px(log: IngestedLog, pixels: np.ndarray,
                              max_disp: int = 160) -> tuple[float, int]:
    """The run's own stereo localisation σ (px per image), measured along the epipolar
    lines, where it makes depth (module docstring): pixels (M, 2, 2) of template points in
    cameras 0 and 1. Three disparities of each point on the rectified frame-0 pair: the
    run's (its two observations), NCC's and StereoSGBM's (`_disparity`); with independent
    errors var(a - b) = σ_a² + σ_b², so σ_run² = (var(run - ncc) + var(run - sgbm)
    - var(ncc - sgbm)) / 2 (the "three-cornered hat"; robust variances, 1.4826 MAD about the
    median). NCC and SGBM both match blocks on the same images, so their errors are partly
    shared: var(ncc - sgbm) is then low and σ_run high, a conservative check of a σ that
    could be too small. Returns σ_run / √2 (one image's share of a disparity's error) and
    the points used."""
    rect = Rectified(log.models, log.poses[0, :2])
    left, right = rect.images(*log.frame_images(0)[:2])
    xy = rect.left_pixels(pixels[:, 0])
    m1 = rect.models[1]
    right_xy = cv2.undistortPoints(np.asarray(pixels[:, 1], np.float64).reshape(-1, 1, 2),
                                   m1.K, m1.dist, R=rect.r1, P=rect.p1).reshape(-1, 2)
    run = xy[:, 0] - right_xy[:, 0]
    sgbm = _sample(_disparity(left, right, max_disp), xy)
    ncc = _ncc_matches(left, right, xy, sgbm)[:, 1]
    ok = np.isfinite(run) & np.isfinite(sgbm) & np.isfinite(ncc)
    if ok.sum() < 10:
        return float("nan"), int(ok.sum())
    var = [_mad_sigma(a[ok] - b[ok]) ** 2 for a, b in ((run, ncc), (run, sgbm), (ncc, sgbm))]
    return float(np.sqrt(max(var[0] + var[1] - var[2], 0.0) / 2.0) / np.sqrt(2.0)), int(ok.sum())


def ground_truth_localisation_px(true_poses: np.ndarray, models: list[CameraModel],
                                 vertices: np.ndarray, faces: np.ndarray,
                                 pixels: np.ndarray) -> float:
    """Localisation σ (px) from the simulator's truth (module docstring): true poses (2, 4, 4)
    of cameras 0 and 1 at frame 0, the true surface (V, 3) m / (F, 3), and pixels (M, 2, 2)
    of points seen by both cameras."""
    from surgrecon_cli.sim.render import cast_rays, mesh_scene

    origin, dirs = pixel_rays(pixels[:, 0], models[0], true_poses[0])
    origin = np.broadcast_to(origin, dirs.shape)
    rays = np.concatenate([origin, dirs], 1)
    t = cast_rays(mesh_scene(vertices, faces), rays)["t_hit"].numpy().astype(float)
    hit = origin + dirs * t[:, None]
    ok = np.isfinite(t)
    uv, _ = project(hit[ok], true_poses[1], models[1])
    err = uv - pixels[ok, 1]
    return float(np.sqrt(np.mean([_mad_sigma(err[:, a], centre=False) ** 2 for a in (0, 1)])
                         / 2.0))


def rigid_tracking_px(models: tuple[CameraModel, ...], template_px: np.ndarray,
                      tracked_px: np.ndarray) -> float:
    """Tracking σ (px) of a rigid scene from epipolar residuals (module docstring): template
    pixels (N, C, 2) at frame 0 and tracked pixels (F, N, C, 2) at frames 1..F (NaN = none)."""
    per_frame = []
    for cur_frame in tracked_px:
        distances = []
        for c, m in enumerate(models[:template_px.shape[1]]):
            cur = cur_frame[:, c]
            ok = np.isfinite(template_px[:, c]).all(1) & np.isfinite(cur).all(1)
            if ok.sum() < 20:
                continue
            p0, pk = (cv2.undistortPoints(np.ascontiguousarray(p[ok], np.float64).reshape(
                -1, 1, 2), m.K, m.dist, P=m.K).reshape(-1, 2) for p in (template_px[:, c], cur))
            _, inlier = cv2.findFundamentalMat(p0, pk, cv2.FM_RANSAC, 1.0, 0.999)
            if inlier is None or (inlier.ravel() > 0).sum() < 20:
                continue
            use = inlier.ravel() > 0
            F, _ = cv2.findFundamentalMat(p0[use], pk[use], cv2.FM_8POINT)
            if F is None or F.shape != (3, 3):
                continue
            lines = np.column_stack([p0, np.ones(len(p0))]) @ F.T  # epipolar lines in image k
            d = (np.column_stack([pk, np.ones(len(pk))]) * lines).sum(1)
            distances.append(d / np.maximum(np.hypot(lines[:, 0], lines[:, 1]), 1e-12))
        if distances:
            per_frame.append(_mad_sigma(np.concatenate(distances), centre=False))
    return float(np.median(per_frame)) if per_frame else float("nan")


def ground_truth_tracking_errors(true_poses: np.ndarray, models: list[CameraModel],
                                 vertices: np.ndarray, faces: np.ndarray,
                                 template_px: np.ndarray, tracked_px: np.ndarray) -> np.ndarray:
    """Tracking errors (F, N, C, 2) px from the simulator's truth (module docstring; NaN
    where not tracked): true camera poses (F + 1, C, 4, 4) and surface vertices
    (F + 1, C, V, 3) m at each camera's image of frames 0..F, faces (F', 3), template pixels
    (N, C, 2) and tracked pixels (F, N, C, 2)."""
    from surgrecon_cli.sim.render import cast_rays, mesh_scene

    errors = np.full(tracked_px.shape, np.nan)
    for c in range(template_px.shape[1]):
        seen = np.flatnonzero(np.isfinite(template_px[:, c]).all(1))
        origin, dirs = pixel_rays(template_px[seen, c], models[c], true_poses[0, c])
        origin = np.broadcast_to(origin, dirs.shape)
        hit = cast_rays(mesh_scene(vertices[0, c], faces), np.concatenate([origin, dirs], 1))
        tri = hit["primitive_ids"].numpy().astype(np.int64)
        ok = np.isfinite(hit["t_hit"].numpy()) & (tri < len(faces))
        uv = hit["primitive_uvs"].numpy().astype(float)[ok]
        bary = np.column_stack([1.0 - uv.sum(1), uv])  # open3d: weights of vertices 1 and 2
        corners = faces[tri[ok]]
        for k in range(1, len(true_poses)):
            material = np.einsum("mj,mjd->md", bary, vertices[k, c][corners])
            expected, _ = project(material, true_poses[k, c], models[c])
            errors[k - 1, seen[ok], c] = tracked_px[k - 1, seen[ok], c] - expected
    return errors


def ground_truth_tracking_px(true_poses: np.ndarray, models: list[CameraModel],
                             vertices: np.ndarray, faces: np.ndarray, template_px: np.ndarray,
                             tracked_px: np.ndarray) -> float:
    """Tracking σ (px, per axis) of `ground_truth_tracking_errors` (same arguments): the
    median over frames of each frame's 1.4826 MAD over points and cameras (as the run
    reports its tracking_px: the median of its frames')."""
    errors = ground_truth_tracking_errors(true_poses, models, vertices, faces, template_px,
                                          tracked_px)
    per_frame = []
    for err in errors.reshape(len(errors), -1, 2):
        err = err[np.isfinite(err).all(1)]
        if len(err):
            per_frame.append(np.sqrt(np.mean([_mad_sigma(err[:, a], centre=False) ** 2
                                              for a in (0, 1)])))
    return float(np.median(per_frame)) if per_frame else float("nan")


def reference_positions(log: IngestedLog, pixels0: np.ndarray,
                        max_disp: int = 160) -> np.ndarray:
    """Reference world positions (T, M, 3) m (NaN where flow or depth fail) of the points
    seen at camera-0 pixels (M, 2) at frame 0 (module docstring)."""
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    out = np.full((log.n_frames, len(pixels0), 3), np.nan)
    xy, prev = None, None
    for k in range(log.n_frames):
        if not log.usable[k, :2].all():
            xy = None
            continue
        rect = Rectified(log.models, log.poses[k, :2])
        left, right = rect.images(*log.frame_images(k)[:2])
        if xy is None and k == 0:
            xy = rect.left_pixels(pixels0)
        elif xy is not None and prev is not None:
            forward = dis.calc(prev, left, None)
            backward = dis.calc(left, prev, None)
            moved = xy + _sample(forward, xy)
            back = moved + _sample(backward, moved)
            xy = np.where((np.linalg.norm(back - xy, axis=1) <= FB_PX)[:, None], moved, np.nan)
        if xy is None:
            continue
        out[k] = rect.world(xy, _sample(_disparity(left, right, max_disp), xy))
        prev = left
    return out


def rigid_scene_motion(log: IngestedLog, max_disp: int = 160, inlier_px: float = 1.0,
                       seed: int = 0) -> np.ndarray:
    """The scene's rigid motion (T, 4, 4) in the world, frame 0 -> frame k (NaN where it
    cannot be fitted), for a rigid scene seen by a moving stereo endoscope, from the images
    alone and none of the pipeline's detector, tracker or registration: SIFT features of the
    rectified left images of frames 0 and k, matched directly (Lowe ratio 0.75); the frame-0
    ones put in 3D with StereoSGBM disparity, and the motion is the pose (RANSAC PnP within
    inlier_px, then refined on the inliers) that puts them on their frame-k pixels. (A 3D-3D
    fit with the frame-k depths too mistakes a turn of the camera for a shift: SGBM's depth
    noise leaves the rotation of a small patch loosely held; measured on a 2°/frame clip,
    half the turn.)"""
    sift = cv2.SIFT_create(4000)
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    out = np.full((log.n_frames, 4, 4), np.nan)
    if not log.usable[0, :2].all():
        return out
    rect0 = Rectified(log.models, log.poses[0, :2])
    left0, right0 = rect0.images(*log.frame_images(0)[:2])
    kp0, d0 = sift.detectAndCompute(left0, None)
    xy0 = np.array([p.pt for p in kp0], float).reshape(-1, 2)
    w0 = rect0.world(xy0, _sample(_disparity(left0, right0, max_disp), xy0))
    out[0] = np.eye(4)
    for k in range(1, log.n_frames):
        if not log.usable[k, 0]:
            continue
        rect = Rectified(log.models, log.poses[k, :2])
        left, _ = rect.images(*log.frame_images(k)[:2])
        kp, dk = sift.detectAndCompute(left, None)
        xyk = np.array([p.pt for p in kp], float).reshape(-1, 2)
        pairs = [m[0] for m in matcher.knnMatch(d0, dk, k=2)
                 if len(m) == 2 and m[0].distance < 0.75 * m[1].distance]
        i = np.array([m.queryIdx for m in pairs], int)
        j = np.array([m.trainIdx for m in pairs], int)
        ok = np.isfinite(w0[i]).all(1)
        if ok.sum() < 20:
            continue
        src, dst = w0[i[ok]], xyk[j[ok]]
        cam_k = np.eye(4)  # rectified camera 0 at frame k -> world
        cam_k[:3, :3] = log.poses[k, 0, :3, :3] @ rect.r0.T
        cam_k[:3, 3] = log.poses[k, 0, :3, 3]
        found, rvec, tvec, inliers = cv2.solvePnPRansac(
            src, dst, rect.p0[:, :3], None, reprojectionError=inlier_px,
            iterationsCount=500, confidence=0.999, flags=cv2.SOLVEPNP_EPNP)
        if not found or inliers is None or len(inliers) < 20:
            continue
        use = inliers.ravel()
        rvec, tvec = cv2.solvePnPRefineLM(src[use], dst[use], rect.p0[:, :3], None, rvec, tvec)
        seen = np.eye(4)  # world (frame 0) -> rectified camera at frame k
        seen[:3, :3], seen[:3, 3] = cv2.Rodrigues(rvec)[0], tvec.ravel()
        out[k] = cam_k @ seen
    return out
