"""Per-frame contact and indentation figures of a sequence (issue 17), from the geometry of
core/measure/deformation.py. Pure numpy, no I/O; metres in, the figures in mm, mm², mm³ and N.

Per frame k (`measure_frame`):
- contact: the tool's clearance (core/dent.tool_clearance, min over the points) is at
  most the tolerance max(contact_floor_mm, contact_sigmas × σ/√3), σ the median 3D RMS of the
  frame's points (σ/√3 their 1D uncertainty along the normal). Not the σ of the points
  nearest the tool: under a hovering tool they are hidden and extrapolated, their σ large,
  and a tolerance from it would call a tool 1 mm away touching; in contact the registration
  keeps the tissue out of the tool (core/frame_step.register_with_contact), so the hidden
  surface is pushed to zero clearance whatever its σ. But it cannot pull the tissue after a
  retreating tool: hidden under it, the tissue that springs back with the tool is
  extrapolated from its visible neighbours, which rise less than the centre of the dent,
  so it lags behind the tool by up to that extrapolation's error. Hence a hysteresis: once
  in contact (the last frame with a tool pose was), the tool stays in contact until its
  clearance exceeds contact_sigmas × the 1D σ of the frame's median point extrapolated as
  far as the nearest point is from its support (the registration's error model of a point
  without data, core/registration/frame_step.py: σ² = σ_s² + (g d)², here with the frame's
  median σ for σ_s: a single support's σ, inflated by its residual, would hold the contact
  through a lift-off; `contact_tolerance`). A hovering tool never touched, so its tolerance
  stays the onset's. Onset is the first frame in contact, release the first frame out of
  contact after the last frame in contact;
- depth under the tip, along the tool axis: −u·a of the points under the tip, read at the
  axis; along the surface normal: −u·(R n), n the point's frame-0 normal turned by its ring's
  rotation. Computed in every frame (so breathing alone can be checked: it should stay within
  its noise, `depth_sigma_mm`, the weighted mean 1D σ_u of those points); `indentation_mm` is
  the axial depth in contact and 0 without;
- kinematic penetration: how far the tip is below the frame-0 surface carried by the rings'
  rigid motion (the positions x − u), along the axis: the robot's view of the indentation;
- deformed area (mm²) of the deformed region seeded at the most displaced point under the
  tip, and indented volume (mm³) Σ area_i max(0, −u_i·R_i n_i) over it; 0 without contact;
- force proxy (N): Hertz (`hertz_force`) of the indentation with the working end's radius
  (the shaft's, or half the jaw's width), only when youngs_modulus_kpa > 0 (NaN otherwise):
  a model output, not a measurement.
Several tools (`measure_tools`): each is measured alone at its working end (core/geometry/tool.py
working_end), on the same compensated field; the field's deformed region is every tool's.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, fields
from typing import Any

import numpy as np

from ...config import DeformationConfig, ToolConfig
from ..geometry.tool import working_end
from .deformation import CompensatedField, ReferenceSurface, compensated_field
from .dent import (
    deformed_region,
    patch_triangles,
    share_above,
    tool_clearance,
    under_tip,
    value_at_axis,
)

# What the contact figures read where the tool pose is unknown (no robot in the log, or a
# gap in its stream): not measured, which is not "no contact".
NOT_MEASURED = "not measured"

SERIES_KEYS = ("contact", "clearance_mm", "tolerance_mm", "indentation_mm",
               "indentation_normal_mm", "depth_under_tip_mm", "depth_sigma_mm",
               "penetration_mm", "area_mm2", "volume_mm3", "force_n", "contact_point")

# The field's arrays (T, N) as stored.
FIELD_DTYPES = {"inward_mm": np.float32, "magnitude_mm": np.float32, "sigma_mm": np.float32,
                "deformed": bool}


@dataclass(frozen=True)
class DeformationSeries:
    """The per-frame figures, each (T,): contact bool; clearance_mm, tolerance_mm;
    indentation_mm (axial, 0 without contact) and indentation_normal_mm; depth_under_tip_mm
    (axial, every frame) and its 1D σ depth_sigma_mm; penetration_mm (kinematic); area_mm2;
    volume_mm3; force_n (NaN when the model is off); contact_point int (template index of
    the seed of the deformed region, −1: none). NaN where not measurable."""

    contact: np.ndarray
    clearance_mm: np.ndarray
    tolerance_mm: np.ndarray
    indentation_mm: np.ndarray
    indentation_normal_mm: np.ndarray
    depth_under_tip_mm: np.ndarray
    depth_sigma_mm: np.ndarray
    penetration_mm: np.ndarray
    area_mm2: np.ndarray
    volume_mm3: np.ndarray
    force_n: np.ndarray
    contact_point: np.ndarray

    @property
    def n_frames(self) -> int:
        return len(self.contact)

    def rows(self) -> list[dict[str, Any]]:
        """One dict per frame (frame, contact 0/1, then the figures; NaN as None)."""
        out = []
        for k in range(self.n_frames):
            row: dict[str, Any] = {"frame": k}
            for name in SERIES_KEYS:
                value = getattr(self, name)[k]
                row[name] = int(value) if name in ("contact", "contact_point") else (
                    float(value) if np.isfinite(value) else None)
            out.append(row)
        return out


@dataclass(frozen=True)
class DeformationField:
    """Per frame and template point (T, N): inward_mm the compensated displacement into the
    tissue along the normal (−u·R n), magnitude_mm |u|, sigma_mm its 3D RMS uncertainty
    (NaN without noise model) and deformed (bool) the deformed region."""

    inward_mm: np.ndarray
    magnitude_mm: np.ndarray
    sigma_mm: np.ndarray
    deformed: np.ndarray


@dataclass(frozen=True)
class Deformation:
    """A measured sequence: the per-frame series and the per-point field."""

    series: DeformationSeries
    field: DeformationField


@dataclass(frozen=True)
class SurfaceEstimate:
    """The registered surface of one frame: positions (N, 3) m (NaN: unknown), sigma (N,) m
    3D RMS or None, extrapolation (N,) m each point's extrapolation error
    (registration.extrapolation_growth × its frame-0 distance to the nearest point with data;
    None: 0), which the contact's hysteresis allows for."""

    positions: np.ndarray
    sigma: np.ndarray | None = None
    extrapolation: np.ndarray | None = None


@dataclass(frozen=True)
class _FrameField:
    """One frame's registered surface, its `compensated_field` and inward (N,) m."""

    estimate: SurfaceEstimate
    comp: CompensatedField
    inward: np.ndarray


def measure_frame(surface: ReferenceSurface, estimate: SurfaceEstimate, tool_pose: np.ndarray,
                  cfg: DeformationConfig, tool: ToolConfig, held: bool = False
                  ) -> tuple[dict[str, float], dict]:
    """`measure_tools` of one tool (pose (4, 4)): its figures and the field."""
    figs, field = measure_tools(surface, estimate, np.asarray(tool_pose)[None], cfg, [tool],
                                [held])
    return figs[0], field


def measure_tools(surface: ReferenceSurface, estimate: SurfaceEstimate, tool_poses: np.ndarray,
                  cfg: DeformationConfig, tools: Sequence[ToolConfig],
                  held: Sequence[bool] | None = None) -> tuple[list[dict[str, float]], dict]:
    """One frame: each tool's figures {SERIES_KEYS: value} and the field {inward_mm,
    magnitude_mm, sigma_mm, deformed (every tool's deformed region): (N,)}. tool_poses
    (K, 4, 4) (NaN: unknown) with one config each; held (K,): each tool in contact in the
    last frame with its pose (`held_contact`; None: none was). A tool is measured at its
    working end (core/tool.working_end: the jaw's end when it has one), along its shaft axis."""
    positions, sigma = estimate.positions, estimate.sigma
    comp = compensated_field(surface.points, positions, surface.rings, sigma)
    u = comp.displacement
    inward = -(u * np.einsum("nij,nj->ni", comp.rotation, surface.normals)).sum(1)
    frame = _FrameField(estimate, comp, inward)
    field = {"inward_mm": inward * 1e3, "magnitude_mm": np.linalg.norm(u, axis=1) * 1e3,
             "sigma_mm": comp.sigma * 1e3, "deformed": np.zeros(len(surface.points), bool)}
    figs = []
    held = [False] * len(tools) if held is None else held
    for tool_pose, tool, was in zip(np.asarray(tool_poses, float), tools, held, strict=True):
        fig = dict.fromkeys(SERIES_KEYS, float("nan"))
        fig.update(contact=0.0, contact_point=-1.0, indentation_mm=0.0,
                   indentation_normal_mm=0.0, area_mm2=0.0, volume_mm3=0.0)
        radius = tool.shaft_radius_m
        if np.isfinite(tool_pose).all():
            _contact(fig, frame, tool_pose, tool, cfg, bool(was))
            end, radius = working_end(tool_pose, tool)
            field["deformed"] |= _under_tool(fig, surface, frame, end, radius, cfg)
        if cfg.youngs_modulus_kpa > 0:
            fig["force_n"] = float(hertz_force(fig["indentation_mm"] * 1e-3, radius,
                                               cfg.youngs_modulus_kpa * 1e3, cfg.poisson_ratio))
        figs.append(fig)
    return figs, field


def _under_tool(fig: dict[str, float], surface: ReferenceSurface, frame: _FrameField,
                end: np.ndarray, radius: float, cfg: DeformationConfig) -> np.ndarray:
    """Fill a tool's depth, indentation, area, volume and penetration figures (module docstring)
    under its working end `end` (4, 4; z up the shaft) of `radius` m; returns its dent (N,) bool."""
    positions, sigma, comp = frame.estimate.positions, frame.estimate.sigma, frame.comp
    u, axis = comp.displacement, end[:3, 2]
    deformed = np.zeros(len(surface.points), bool)
    tip = under_tip(positions, end, cfg.tip_radius_mm * 1e-3, radius)
    if len(tip.rows):
        fig["depth_under_tip_mm"] = value_at_axis(tip, -(u[tip.rows] @ axis)) * 1e3
        normal_depth = value_at_axis(tip, frame.inward[tip.rows]) * 1e3
        if sigma is not None:
            s = comp.sigma[tip.rows] / np.sqrt(3.0)
            ok = np.isfinite(s)
            if ok.any():
                w = tip.weights[ok]
                fig["depth_sigma_mm"] = float((w * s[ok]).sum() / w.sum()) * 1e3
        size = np.where(np.isfinite(u[tip.rows]).all(1),
                        np.linalg.norm(u[tip.rows], axis=1), -np.inf)
        seed = int(tip.rows[np.argmax(size)]) if np.isfinite(size).any() else -1
        if fig["contact"] and np.isfinite(fig["depth_under_tip_mm"]):
            fig["indentation_mm"] = fig["depth_under_tip_mm"]
            fig["indentation_normal_mm"] = normal_depth
            fig["contact_point"] = float(seed)
            deformed, fig["area_mm2"], fig["volume_mm3"] = _dent(surface, frame, seed, cfg)
    carried = under_tip(positions - u, end, cfg.tip_radius_mm * 1e-3, cfg.ring_inner_mm * 1e-3)
    if len(carried.rows):
        fig["penetration_mm"] = value_at_axis(carried, carried.h) * 1e3
    return deformed


def contact_tolerance(sigma: np.ndarray | None, extrapolation: np.ndarray | None,
                      nearest: int, held: bool, cfg: DeformationConfig) -> float:
    """The contact tolerance (m) of a frame whose clearance is that of point `nearest`:
    max(contact_floor_mm, contact_sigmas × σ_m/√3), σ_m the median of sigma (N,) m, the
    points' 3D RMS (None: noiseless, the floor). `held` (the tool was in contact in the last
    frame with its pose): σ_m combined with the nearest point's extrapolation error,
    extrapolation (N,) m (g × its distance to the nearest point with data; None: 0), so
    that a release needs a clearance beyond what extrapolating the hidden surface under the
    tool explains (module docstring)."""
    tolerance = cfg.contact_floor_mm * 1e-3
    if sigma is None:
        return tolerance
    s = np.asarray(sigma, float)
    finite = s[np.isfinite(s)]
    if not finite.size:
        return tolerance
    typical = float(np.median(finite))
    if held and extrapolation is not None and np.isfinite(extrapolation[nearest]):
        typical = float(np.hypot(typical, extrapolation[nearest]))
    return max(tolerance, cfg.contact_sigmas * typical / np.sqrt(3.0))


def _contact(fig: dict[str, float], frame: _FrameField, pose: np.ndarray, tool: ToolConfig,
             cfg: DeformationConfig, held: bool) -> None:
    """Fill clearance_mm, tolerance_mm and contact (module docstring; `held`: in contact
    in the last frame with the tool's pose)."""
    positions = frame.estimate.positions
    clearance = tool_clearance(positions, pose, tool)
    ok = np.flatnonzero(np.isfinite(clearance))
    if not len(ok):
        return
    nearest = int(ok[np.argmin(clearance[ok])])
    tolerance = contact_tolerance(frame.estimate.sigma, frame.estimate.extrapolation, nearest,
                                  held, cfg)
    fig["clearance_mm"] = float(clearance[nearest]) * 1e3
    fig["tolerance_mm"] = tolerance * 1e3
    fig["contact"] = float(clearance[nearest] <= tolerance)


def held_contact(held: Sequence[bool], figs: Sequence[dict[str, float]]) -> list[bool]:
    """Each tool's contact state after a frame of figures (`measure_tools`): its contact
    where its clearance was measured, else (no pose, no points) the state before, `held`."""
    return [bool(f["contact"]) if np.isfinite(f["clearance_mm"]) else bool(h)
            for h, f in zip(held, figs, strict=True)]


def _dent(surface: ReferenceSurface, frame: _FrameField, seed: int, cfg: DeformationConfig
          ) -> tuple[np.ndarray, float, float]:
    """The deformed region (N,) bool around the contact point `seed`, its area mm² and
    indented volume mm³. Inside the contact point's ring (frame-0 distance below
    ring_inner_mm) every point is compensated by that one ring's rigid motion (so that
    points nearer a breathing edge, whose own rings straddle it, do not join the dent);
    area and volume over the triangles of the frame-0 points that touch the region
    (core/measure/deformation.py)."""
    reference, normals, comp = surface.points, surface.normals, frame.comp
    n = len(reference)
    centre = int(surface.rings.nearest[seed, 0])
    if not comp.centre_used[centre]:
        return np.zeros(n, bool), float("nan"), float("nan")
    R, t = comp.centre_rotation[centre], comp.centre_translation[centre]
    distance = np.linalg.norm(reference - reference[seed], axis=1)
    local = distance < cfg.ring_inner_mm * 1e-3
    u = np.full((n, 3), np.nan)
    u[local] = frame.estimate.positions[local] - (reference[local] @ R.T + t)
    sigma = None if frame.estimate.sigma is None else comp.sigma
    region = deformed_region(u, sigma, seed, surface.nb, cfg.threshold_mm * 1e-3,
                             cfg.significance)
    if not region.any():
        return region, 0.0, 0.0
    rows = np.flatnonzero(distance <= distance[region].max() + cfg.max_edge_mm * 1e-3)
    tri, area = patch_triangles(reference, rows, cfg.max_edge_mm * 1e-3)
    touching = region[tri].any(1)
    tri, area = tri[touching], area[touching]
    size = np.linalg.norm(u, axis=1)[tri]
    depth = -np.einsum("fci,fci->fc", u[tri], normals[tri] @ R.T)
    depth = np.clip(np.nan_to_num(depth), 0.0, None).mean(1)
    return (region, float((area * share_above(size, cfg.threshold_mm * 1e-3)).sum()) * 1e6,
            float((area * depth).sum()) * 1e9)


def measure_sequence(surface: ReferenceSurface, positions: np.ndarray,
                     sigma: np.ndarray | None, tool_poses: np.ndarray, cfg: DeformationConfig,
                     tool: ToolConfig) -> Deformation:
    """Every frame: positions (T, N, 3) m (frame 0 normally the reference itself), sigma
    (T, N) m or None, tool_poses (T, 4, 4) (module docstring)."""
    figs, fields_ = [], []
    held = False
    for k in range(len(positions)):
        estimate = SurfaceEstimate(positions[k], None if sigma is None else sigma[k])
        fig, field = measure_frame(surface, estimate, tool_poses[k], cfg, tool, held)
        held = held_contact([held], [fig])[0]
        figs.append(fig)
        fields_.append(field)
    stacked = DeformationField(**{key: np.stack([f[key] for f in fields_]).astype(
        FIELD_DTYPES[key]) for key in FIELD_DTYPES})
    return Deformation(series_of(figs), stacked)


def series_of(figs: list[dict[str, float]]) -> DeformationSeries:
    """The series (T,) of every frame's figures (`measure_frame`), frames in order."""
    return DeformationSeries(**{
        key: np.array([f[key] for f in figs],
                      bool if key == "contact" else int if key == "contact_point" else float)
        for key in SERIES_KEYS})


def hertz_force(depth_m: np.ndarray | float, radius_m: float, youngs_pa: float,
                poisson: float) -> np.ndarray:
    """Hertzian contact force (...,) N of a rigid sphere of `radius_m` pressed `depth_m`
    (...,) m into an elastic half-space (Young's modulus Pa, Poisson's ratio):
    F = 4/3 E/(1 − ν²) √R δ^{3/2} (δ ≤ 0: no force). A model output, valid for δ ≪ R."""
    depth = np.clip(np.asarray(depth_m, float), 0.0, None)
    return 4.0 / 3.0 * youngs_pa / (1.0 - poisson**2) * np.sqrt(radius_m) * depth**1.5


def camera_viewpoint(camera_poses: np.ndarray, usable: np.ndarray,
                     points: np.ndarray) -> np.ndarray:
    """Where the surface is seen from (3,) m: the mean centre of the usable cameras
    (camera_poses (C, 4, 4) camera-to-world, usable (C,) bool), so that normals point out of
    the tissue; above the centroid of points (N, 3) m when no camera is usable."""
    centres = np.asarray(camera_poses, float)[np.asarray(usable, bool), :3, 3]
    centres = centres[np.isfinite(centres).all(1)]
    if len(centres):
        return centres.mean(0)
    return np.asarray(points, float).mean(0) + np.array([0.0, 0.0, 1.0])


def tool_known(tool_poses: np.ndarray) -> np.ndarray:
    """Frames (T,) bool whose tool pose (T, 4, 4) is known (finite): where contact can be
    measured at all."""
    return np.isfinite(np.asarray(tool_poses, float)).all(axis=(1, 2))


def contact_events(contact: np.ndarray) -> tuple[int | None, int | None]:
    """Onset (first frame in contact) and release (first frame out of contact after the
    last frame in contact; None when contact lasts to the end) of contact (T,) bool."""
    frames = np.flatnonzero(np.asarray(contact, bool))
    if not len(frames):
        return None, None
    last = int(frames[-1])
    return int(frames[0]), (last + 1 if last + 1 < len(contact) else None)


def summarise(series: DeformationSeries, cfg: DeformationConfig,
              tool: ToolConfig) -> dict[str, Any]:
    """The sequence at a glance: contact onset and release, frames in contact, the deepest
    indentation (its frame, axial and normal depth, σ), the largest area, volume and force,
    what the breathing check sees out of contact, and the settings behind them."""
    onset, release = contact_events(series.contact)
    contact = np.asarray(series.contact, bool)
    depth = np.where(contact, series.indentation_mm, -np.inf)
    deepest = int(np.argmax(depth)) if contact.any() else None

    def largest(values: np.ndarray) -> float | None:
        v = np.asarray(values, float)[contact]
        v = v[np.isfinite(v)]
        return float(v.max()) if v.size else None

    free = ~contact & np.isfinite(series.depth_under_tip_mm)
    return {
        "onset_frame": onset, "release_frame": release,
        "contact_frames": [int(k) for k in np.flatnonzero(contact)],
        "deepest_frame": deepest,
        "max_indentation_mm": None if deepest is None else float(series.indentation_mm[deepest]),
        "max_indentation_normal_mm": (None if deepest is None
                                      else float(series.indentation_normal_mm[deepest])),
        "max_indentation_sigma_mm": (None if deepest is None
                                     or not np.isfinite(series.depth_sigma_mm[deepest])
                                     else float(series.depth_sigma_mm[deepest])),
        "max_area_mm2": largest(series.area_mm2), "max_volume_mm3": largest(series.volume_mm3),
        "max_penetration_mm": largest(series.penetration_mm),
        "max_force_n": largest(series.force_n) if cfg.youngs_modulus_kpa > 0 else None,
        "free_depth_max_abs_mm": (float(np.abs(series.depth_under_tip_mm[free]).max())
                                  if free.any() else None),
        "force_model": None if cfg.youngs_modulus_kpa <= 0 else {
            "model": "Hertz: rigid sphere of the shaft radius on an elastic half-space "
                     "(a model output, not a measurement; valid for indentation << radius)",
            "youngs_modulus_kpa": cfg.youngs_modulus_kpa, "poisson_ratio": cfg.poisson_ratio,
            "radius_mm": tool.shaft_radius_m * 1e3},
        "settings": {f.name: getattr(cfg, f.name) for f in fields(cfg)},
    }
