"""Real texture, known breathing: one real SurgT stereo frame, its tissue moved by a known smooth
3D motion and both eyes re-rendered from it, with the true surface at every frame written as a
ground truth (`NAME.gt.npz`, the simulator's format) so that `surgrecon evaluate` scores the
run. Used by benchmarks/surgt_clips.py (`breathe=A`).

The public real recordings we may use have no breathing tissue (SurgT: a rigid scene and a
moving endoscope; d-lfd: foam pulled by a grasper). This keeps the real images' texture,
specularities, compression and calibration, and adds a motion whose truth is known:

- The surface: StereoSGBM disparity of the rectified pair (left reference), holes filled by
  normalised convolution; every pixel of each eye is put in 3D on it, in the left camera's
  frame (the clip's world: `surgrecon convert` puts the rig, left camera first, at the
  origin): one surface for both eyes, so that the pair stays one 3D scene as it moves.
- The motion, in the left camera's frame (mm), with the breathing phase
  a(t) = (1 − cos 2πt/P) / 2: a rigid shift (0.6 A across, 0.4 A towards the scope), a broad
  rise of A towards the scope (Gaussian of σ 0.2 × the surface's extent, centred on it),
  and two local pulses of 0.5 A (σ 3 mm, a quarter extent off centre): mostly `shifting`,
  `deforming` where the pulses and the rise's flank bend the surface (spec's rule, true
  surface; at A = 4 mm about a tenth of the surface at the breath's peak).
- Each eye at frame t: every pixel's 3D point displaced and projected with the eye's
  calibration (distortion included) gives a smooth forward flow; the image is resampled
  through its inverse (fixed-point iterations on the smooth flow), so each moved point keeps
  its real texture in both eyes, with exact stereo geometry. Occlusion changes and shading
  are not modelled (the motion is smooth and a few mm).
- The truth: a grid mesh of the left eye's surface (every 16th rectified pixel, cells whose
  corners have a measured disparity and no depth jump) moved by the same motion, labelled by
  core/classify/labels.true_labels with the spec's thresholds.
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy.ndimage import map_coordinates

from surgrecon_cli.config.schema import LabelsConfig
from surgrecon_cli.core.classify.labels import true_labels

GRID_PX = 4  # px between the flow's samples (the flow is smooth)
MESH_PX = 16  # px between the truth mesh's vertices (rectified left image)
RIGHT_ITERATIONS = 20  # fixed-point steps from a right pixel to its left-surface point
RIPPLE_MM = 8.0  # mm between the ripple's bumps
SHIFT = np.array([0.6, 0.0, -0.4])  # rigid part per mm of amplitude (x across, -z towards)


class StereoSurface:
    """The tissue of one stereo frame in the left camera's frame (mm): calibration K (2, 3, 3),
    dist (2, 5), x_right = R x_left + T (mm); disparity maps of the rectified pair."""

    def __init__(self, left: np.ndarray, right: np.ndarray, calib: dict[str, np.ndarray]
                 ) -> None:
        h, w = left.shape[:2]
        self.size = (w, h)
        self.K = (calib["M1"], calib["M2"])
        self.dist = (calib["D1"].ravel(), calib["D2"].ravel())
        self.R, self.T = calib["R"], calib["T"].ravel()
        r1, r2, p1, p2, self.q, _, _ = cv2.stereoRectify(
            self.K[0], self.dist[0], self.K[1], self.dist[1], self.size, self.R, self.T,
            alpha=0)
        self.rect = ((r1, p1), (r2, p2))
        grey = []
        for k, image in enumerate((left, right)):
            mx, my = cv2.initUndistortRectifyMap(self.K[k], self.dist[k], *self.rect[k],
                                                 self.size, cv2.CV_32FC1)
            grey.append(cv2.remap(cv2.cvtColor(image, cv2.COLOR_BGR2GRAY), mx, my,
                                  cv2.INTER_LINEAR))
        expected = float(self.q[2, 3] / self.q[3, 2] / 65.0)  # f b / Z at 65 mm
        self.measured = _disparity(grey[0], grey[1], expected)
        self.filled = _fill(self.measured)

    def points(self, eye: int, pixels: np.ndarray) -> np.ndarray:
        """Left-camera points (M, 3) mm of eye's original pixels (M, 2): both eyes on the
        left eye's (hole-filled) surface, so that a point's texture moves alike in both.
        (Each eye on its own SGBM surface, right-referenced for the right eye, made the two
        eyes move one piece of texture as two points up to 8 mm apart in depth where the
        surfaces disagree: 5 % of the template points of the `breathe=10` 360x288 clip,
        registered up to 9 mm off a truth that the right eye did not show.)"""
        r, p = self.rect[eye]
        xy = cv2.undistortPoints(pixels.reshape(-1, 1, 2).astype(np.float64), self.K[eye],
                                 self.dist[eye], R=r, P=p).reshape(-1, 2)
        x_left = xy[:, 0].copy()
        d = _bilinear(self.filled, xy)
        if eye == 1:  # the left pixel x_l = x_r + d(x_l) of the surface point seen here
            for _ in range(RIGHT_ITERATIONS):  # a contraction where |dd/dx| < 1 (smooth)
                x_left = xy[:, 0] + d
                d = _bilinear(self.filled, np.column_stack([x_left, xy[:, 1]]))
            x_left = xy[:, 0] + d
        return self.rect_points(np.column_stack([x_left, xy[:, 1]]), d)

    def rect_points(self, xy: np.ndarray, disparity: np.ndarray) -> np.ndarray:
        """Left-camera points (M, 3) mm of rectified-left pixels (M, 2) with disparities."""
        h = np.column_stack([xy, disparity, np.ones(len(xy))]) @ self.q.T
        return (h[:, :3] / h[:, 3:4]) @ self.rect[0][0]  # rectified -> left camera: R1ᵀ x

    def project(self, eye: int, points: np.ndarray) -> np.ndarray:
        """Original pixels (M, 2) of left-camera points (M, 3) mm in eye."""
        rvec = np.zeros(3) if eye == 0 else cv2.Rodrigues(self.R)[0].ravel()
        tvec = np.zeros(3) if eye == 0 else self.T
        px, _ = cv2.projectPoints(points.reshape(-1, 1, 3), rvec, tvec, self.K[eye],
                                  self.dist[eye])
        return px.reshape(-1, 2)

    def mesh(self) -> tuple[np.ndarray, np.ndarray]:
        """Vertices (V, 3) mm and faces (F, 3) of the left eye's measured surface."""
        h, w = self.measured.shape
        ys, xs = np.mgrid[MESH_PX // 2:h:MESH_PX, MESH_PX // 2:w:MESH_PX]
        d = self.measured[ys, xs]
        pts = self.rect_points(np.column_stack([xs.ravel(), ys.ravel()]).astype(float),
                               d.ravel()).reshape(*xs.shape, 3)
        ok = np.isfinite(pts).all(-1)
        idx = np.arange(ok.size).reshape(ok.shape)
        corners = [idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]]
        z = pts[..., 2].ravel()
        cell = np.all([ok.ravel()[c] for c in corners], axis=0)
        with np.errstate(invalid="ignore"):
            zc = np.stack([z[c] for c in corners])
            cell &= (zc.max(0) - zc.min(0)) < 0.05 * np.nanmedian(z)
        a, b, c, e = (x[cell] for x in corners)
        faces = np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, e])])
        used = np.unique(faces)
        remap = np.full(ok.size, -1)
        remap[used] = np.arange(len(used))
        return pts.reshape(-1, 3)[used], remap[faces].astype(np.int32)


class Breathing:
    """The known motion (module docstring) of a surface whose points are `reference` (M, 3)
    mm: amplitude A mm, period P frames."""

    def __init__(self, reference: np.ndarray, amplitude_mm: float, period: float,
                 ripple: float = 0.0) -> None:
        ok = reference[np.isfinite(reference).all(1)]
        self.centre = np.median(ok, axis=0)
        extent = np.percentile(ok[:, 0], 95) - np.percentile(ok[:, 0], 5)
        self.broad, self.local = 0.2 * extent, 3.0
        self.pulses = self.centre[:2] + np.array([[0.25, 0.1], [-0.2, -0.15]]) * extent
        self.amplitude, self.period = amplitude_mm, period
        lo, hi = ok[:, :2].min(0), ok[:, :2].max(0)
        gx, gy = np.meshgrid(*(np.arange(a, b + RIPPLE_MM, RIPPLE_MM)
                               for a, b in zip(lo, hi, strict=True)))
        self.bumps = np.column_stack([gx.ravel(), gy.ravel()])
        sign = (-1.0) ** (np.arange(gx.shape[1])[None, :] + np.arange(gx.shape[0])[:, None])
        self.bump_heights = ripple * sign.ravel()

    def phase(self, t: int) -> float:
        return 0.5 * (1.0 - np.cos(2.0 * np.pi * t / self.period))

    def displacement(self, points: np.ndarray, t: int) -> np.ndarray:
        """(M, 3) mm at frame t."""
        a = self.amplitude * self.phase(t)
        lateral = points[:, :2]
        broad = np.exp(-((lateral - self.centre[:2]) ** 2).sum(1) / (2 * self.broad**2))
        local = np.exp(-((lateral[:, None] - self.pulses) ** 2).sum(2)
                       / (2 * self.local**2)).sum(1)
        bumps = (np.exp(-((lateral[:, None] - self.bumps) ** 2).sum(2) / (2 * self.local**2))
                 @ self.bump_heights) if np.any(self.bump_heights) else 0.0
        towards = -(broad + 0.5 * local + bumps)[:, None] * np.array([0.0, 0.0, 1.0])
        return a * (SHIFT + towards)


def breathing_frames(left: np.ndarray, right: np.ndarray, calib: dict[str, np.ndarray],
                     amplitude_mm: float, length: int, period: float, ripple: float = 0.0
                     ) -> tuple[list[tuple[np.ndarray, np.ndarray]], dict[str, np.ndarray]]:
    """`length` stereo frames (BGR left, right) of the pair breathing, and the ground truth
    (faces, vertices (T, V, 3) m, labels (T, V)) without its stamps."""
    surface = StereoSurface(left, right, calib)
    h, w = left.shape[:2]
    gy, gx = np.mgrid[0:h // GRID_PX, 0:w // GRID_PX]
    grid = np.column_stack([gx.ravel(), gy.ravel()]) * GRID_PX + (GRID_PX - 1) / 2.0
    points = [surface.points(eye, grid) for eye in (0, 1)]
    vertices, faces = surface.mesh()
    motion = Breathing(vertices, amplitude_mm, period, ripple)
    frames = []
    for t in range(length):
        frames.append(tuple(
            _warped(image, grid, surface.project(eye, p + motion.displacement(p, t)) - grid,
                    gx.shape)
            for eye, (image, p) in enumerate(((left, points[0]), (right, points[1])))))
    moved = np.stack([vertices + motion.displacement(vertices, t) for t in range(length)])
    truth = {"faces": faces, "vertices": moved * 1e-3, "labels": spec_labels(moved * 1e-3)}
    return frames, truth  # type: ignore[return-value]


def spec_labels(vertices: np.ndarray) -> np.ndarray:
    """The true labels (T, V) uint8 of vertices (T, V, 3) m by the spec's rule at the
    default thresholds (core/classify/labels.true_labels)."""
    cfg = LabelsConfig()
    return true_labels(vertices, cfg.static_mm, cfg.neighbourhood_mm,
                       cfg.rigid_rms_mm).astype(np.uint8)


def _warped(image: np.ndarray, grid: np.ndarray, flow: np.ndarray, shape: tuple[int, int]
            ) -> np.ndarray:
    """image resampled so that the pixel at grid + flow shows what the grid pixel showed."""
    h, w = image.shape[:2]
    coarse = _fill(flow[:, 0].reshape(shape)), _fill(flow[:, 1].reshape(shape))
    fx, fy = (cv2.resize(c.astype(np.float32), (w, h), interpolation=cv2.INTER_LINEAR)
              for c in coarse)
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    mx, my = xs - fx, ys - fy
    for _ in range(3):  # source m of target u: m + F(m) = u
        mx = xs - cv2.remap(fx, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        my = ys - cv2.remap(fy, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return cv2.remap(image, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)


def _disparity(left: np.ndarray, right: np.ndarray, expected: float) -> np.ndarray:
    """SGBM disparity (H, W) px of a rectified pair, NaN where not found."""
    n = int(np.ceil(max(2.5 * expected, 32) / 16) * 16)
    sgbm = cv2.StereoSGBM_create(minDisparity=0, numDisparities=n, blockSize=7,
                                 P1=8 * 49, P2=32 * 49, uniquenessRatio=10,
                                 speckleWindowSize=100, speckleRange=2,
                                 mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)
    d = sgbm.compute(left, right).astype(np.float32) / 16.0
    d[d <= 0] = np.nan
    return d


def _fill(values: np.ndarray, sigma_px: float = 15.0) -> np.ndarray:
    """NaNs filled by normalised convolution (repeated until none is left)."""
    out = values.astype(np.float32).copy()
    for _ in range(8):
        bad = ~np.isfinite(out)
        if not bad.any():
            break
        weight = cv2.GaussianBlur((~bad).astype(np.float32), (0, 0), sigma_px)
        total = cv2.GaussianBlur(np.where(bad, 0, out), (0, 0), sigma_px)
        with np.errstate(invalid="ignore", divide="ignore"):
            out[bad] = (total / weight)[bad]
        sigma_px *= 2
    return out


def _bilinear(image: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Samples (M,) of a (H, W) map at (M, 2) px (edge values beyond the border)."""
    return map_coordinates(image.astype(float), [xy[:, 1], xy[:, 0]], order=1, mode="nearest")
