"""The simulated surgical cavity: a textured tissue dome, its motion, the tool and the cameras.

World frame: z up, metres. The tissue is a heightfield dome over a disk; every mesh vertex
is a material point whose frame-0 (x, y) indexes the texture. Motion (all ours, chosen to
resemble an insufflated abdomen, not taken from the paper):
- breathing: the part of the dome with x > `breath_edge` shifts rigidly by up to
  `breath_amplitude` (smooth-step transition of width `breath_width`), cos² in time;
- swelling (`swell_amplitude` > 0): a local Gaussian bump rises along +z in phase with the
  breathing (non-rigid: the rest of the breathing region moves rigidly);
- tool: a cylindrical shaft approaches a contact point in the still part of the dome and
  indents it along its axis by up to `indent_depth` (Gaussian dent of width `indent_sigma`),
  then releases `release` of the dent (>= 1: all of it, and the tool lifts off); the tip
  follows the tissue's breathing at the contact point and keeps `tool_clearance` above it.

Rig and scene variants (all off by default; `sim/variants.py` names presets of them):
- `stereo_baseline` > 0: cameras 0 and 1 are a rigid stereo head (one tracker marker):
  camera 1 = camera 0 shifted by the baseline along camera 0's x axis, same orientation,
  looking obliquely at the dome from 30-80 mm;
- `rigid_scene`: the whole tissue moves as one rigid body (a few degrees and a few mm over
  the log, as still tissue seen by an untracked sweeping endoscope); no breathing, no
  indentation, the tool hovers well above the tissue;
- `sweep_deg` > 0: every camera pans (rotation about an axis through its centre) by up to
  this angle over the log, all views sliding the same way, so that much of the frame-0
  tissue leaves every view;
- `rig_sweep_deg` > 0 (with `rigid_scene` and a stereo head): the head sweeps about a pivot
  half-way to the tissue by 2/3-4/3 of this many degrees a frame while its logged pose
  stays fixed (no tracker), i.e. the tissue moves rigidly about that pivot in the rig's
  frame (the truth is written in that frame) and slides through the view.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import overload

import numpy as np

from . import LENSES


@dataclass(frozen=True)
class SimConfig:
    """Simulator settings (metres, seconds, pixels)."""

    cameras: int = 6
    frames: int = 20
    width: int = 640
    height: int = 480
    seed: int = 7
    frame_rate: float = 5.0  # camera frame rate (Hz)
    tracker_rate: float = 40.0  # navigation tracker rate (Hz)
    robot_rate: float = 100.0  # robot tool pose / joint state rate (Hz)
    tracker_noise_pos: float = 0.1e-3  # tracker position noise, norm (m)
    tracker_noise_deg: float = 0.05  # tracker rotation noise (deg)
    image_noise: float = 2.0  # Gaussian pixel noise (of 255)
    jpeg_quality: int = 92
    dome_radius: float = 0.05  # disk radius of the tissue (m)
    dome_height: float = 0.012  # dome bulge at the centre (m)
    grid_spacing: float = 0.001  # mesh vertex spacing (m)
    breath_edge: float = -0.004  # x of the breathing region's edge (m)
    breath_width: float = 0.008  # width of the smooth transition (m)
    breath_amplitude: float = 0.003  # peak breathing shift (m)
    breath_period: float = 5.0  # s
    # Local swelling that breathes with the tissue: a Gaussian bump (along +z, about the
    # dome's normal) of this peak height at the breathing peak (m; 0 = off), width and place.
    swell_amplitude: float = 0.0
    swell_sigma: float = 0.005  # m
    swell_xy: tuple[float, float] = (-0.010, 0.004)  # material centre (m)
    indent_depth: float = 0.007  # peak tool indentation (m)
    indent_sigma: float = 0.006  # dent width (m)
    contact_xy: tuple[float, float] = (-0.022, 0.010)  # material contact point (m)
    release: float = 0.6  # share of the dent released by the end; >= 1: released, then lifts off
    tool_clearance: float = 0.0  # tip stays this far above the tissue along its axis (m)
    tool_radius: float = 0.004  # shaft radius (m), matches [tool] defaults
    tool_length: float = 0.15  # shaft length (m)
    camera_ring_radius: float = 0.030  # cameras on a ring around the dome axis (m)
    camera_height: float = 0.055  # camera height above the dome base (m)
    separated: bool = False  # place one camera far away, seeing nothing shared (tests)
    # Stereo endoscope head (cameras 0 and 1); 0 = off.
    stereo_baseline: float = 0.0  # camera 1 = camera 0 moved this far along its x axis (m)
    stereo_distance: float = 0.046  # head to the tissue point it looks at (m)
    stereo_elevation_deg: float = 56.0  # viewing direction below the horizontal (deg)
    # Rigid scene: the tissue moves as one rigid body, nothing deforms.
    rigid_scene: bool = False
    rigid_rotation_deg: float = 4.0  # rotation reached at the last frame (deg)
    rigid_translation: float = 0.004  # translation reached at the last frame (m)
    rigid_tool_hover: float = 0.025  # tool tip height above the contact point, at least (m)
    # Sweeping cameras: pan angle reached at the last frame (deg); 0 = off.
    sweep_deg: float = 0.0
    # Untracked sweep of the stereo head: rotation per frame (deg, mean; 0 = off), see below.
    rig_sweep_deg: float = 0.0
    # Lens model of every camera: plumb_bob, rational_polynomial or equidistant (fisheye).
    lens: str = "plumb_bob"
    # The robot's kinematics (tool pose, joint states) in the log; False: a log without a
    # robot (the tool is still in the scene and the images, its pose is not recorded).
    robot: bool = True
    # Real-image difficulty (sim/degrade.py); 0 = off.
    warp_px: float = 0.0  # localisation error: RMS of a smooth random image warp (px)
    blur_px: float = 0.0  # Gaussian blur sigma (px)
    vignetting: float = 0.0  # share of brightness lost at the corners
    interlace_px: float = 0.0  # horizontal shift of the odd rows (px)

    def __post_init__(self) -> None:
        if self.lens not in LENSES:
            raise ValueError(f"lens must be one of {', '.join(LENSES)}, got {self.lens!r}")
        if self.stereo_baseline < 0 or self.sweep_deg < 0:
            raise ValueError("stereo_baseline and sweep_deg must be >= 0")
        if self.stereo_baseline > 0 and self.cameras < 2:
            raise ValueError(f"a stereo head needs at least 2 cameras, got {self.cameras}")
        if self.stereo_baseline > 0 and self.separated and self.cameras < 3:
            raise ValueError("separated moves the last camera: with a stereo head it needs "
                             "at least 3 cameras")
        if self.tracker_noise_pos < 0 or self.tracker_noise_deg < 0:
            raise ValueError("tracker noise must be >= 0")
        if min(self.warp_px, self.blur_px, self.vignetting) < 0 or self.vignetting > 1:
            raise ValueError("warp_px and blur_px must be >= 0, vignetting within 0..1")

    @property
    def duration(self) -> float:
        """Time from the first to the last frame (s), at least 1 µs."""
        return max((self.frames - 1) / self.frame_rate, 1e-6)


@overload
def smoothstep(x: float) -> float: ...
@overload
def smoothstep(x: np.ndarray) -> np.ndarray: ...
def smoothstep(x: float | np.ndarray) -> float | np.ndarray:
    """3 x^2 - 2 x^3 of x clipped to [0, 1] (a float, or an array of x's shape)."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


@dataclass(frozen=True)
class TissueMesh:
    """Triangle mesh of the tissue at rest: vertices (V, 3) m, faces (F, 3) int32."""

    vertices: np.ndarray
    faces: np.ndarray

    @property
    def material_xy(self) -> np.ndarray:
        return self.vertices[:, :2]


def dome_height(xy: np.ndarray, cfg: SimConfig, rng_bumps: np.ndarray) -> np.ndarray:
    """Dome profile (N,) m: a paraboloid cap plus a few low bumps (centres/amplitudes given)."""
    r2 = (xy**2).sum(1) / cfg.dome_radius**2
    z = cfg.dome_height * (1 - r2)
    for cx, cy, amp, sig in rng_bumps:
        z += amp * np.exp(-((xy[:, 0] - cx) ** 2 + (xy[:, 1] - cy) ** 2) / (2 * sig**2))
    return z


def make_tissue(cfg: SimConfig) -> TissueMesh:
    """A regular grid over the disk, triangulated, lifted to the dome profile."""
    rng = np.random.default_rng(cfg.seed + 101)
    n = round(2 * cfg.dome_radius / cfg.grid_spacing) + 1
    axis = np.linspace(-cfg.dome_radius, cfg.dome_radius, n)
    gx, gy = np.meshgrid(axis, axis, indexing="xy")
    xy = np.stack([gx.ravel(), gy.ravel()], 1)
    inside = (xy**2).sum(1) <= cfg.dome_radius**2 * 1.0001
    index = np.full(n * n, -1)
    index[inside] = np.arange(inside.sum())
    ii, jj = np.meshgrid(np.arange(n - 1), np.arange(n - 1), indexing="ij")
    a = (ii * n + jj).ravel()
    quads = np.stack([a, a + 1, a + n, a + n + 1], 1)
    tri = np.concatenate([quads[:, [0, 2, 1]], quads[:, [1, 2, 3]]])
    tri = index[tri]
    faces = tri[(tri >= 0).all(1)].astype(np.int32)
    bumps = np.column_stack(
        [
            rng.uniform(-0.03, 0.03, 6),
            rng.uniform(-0.03, 0.03, 6),
            rng.uniform(-0.002, 0.002, 6),
            rng.uniform(0.006, 0.012, 6),
        ]
    )
    xy = xy[inside]
    vertices = np.column_stack([xy, dome_height(xy, cfg, bumps)])
    return TissueMesh(vertices=vertices, faces=faces)


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals (V, 3), oriented upward (+z) for the dome."""
    v0, v1, v2 = (vertices[faces[:, k]] for k in range(3))
    fn = np.cross(v1 - v0, v2 - v0)
    normals = np.zeros_like(vertices)
    for k in range(3):
        np.add.at(normals, faces[:, k], fn)
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    return normals * np.where(normals[:, 2:3] < 0, -1.0, 1.0)
