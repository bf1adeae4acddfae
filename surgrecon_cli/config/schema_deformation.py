"""Config section `[deformation]`: tool-tissue contact and indentation measured from the
reconstruction (core/measure/deformation.py explains every quantity)."""

from __future__ import annotations

from dataclasses import dataclass

from .fields import _doc, _require, check_bounds


@dataclass(frozen=True)
class DeformationConfig:
    """Contact and indentation measures (mm, kPa); thresholds are ours."""

    ring_inner_mm: float = _doc(
        15.0, "rigid-motion compensation: a point's ring is the template points this far from "
        "it at frame 0, at least (mm; beyond the dent, so the ring's motion is the rigid one)",
        bounds=(0, 1000))
    ring_outer_mm: float = _doc(25.0, "... and at most this far (mm)", bounds=(0, 1000))
    ring_points: int = _doc(64, "ring members fitted per point (spread over the ring)",
        bounds=(6, 4096))
    contact_sigmas: float = _doc(
        2.5, "contact: the tool's clearance to the reconstructed surface is below this many "
        "sigma of the frame's points (the median; 1D sigma along the surface normal)",
        bounds=(0, 100))
    contact_floor_mm: float = _doc(
        0.2, "... or below this (mm; also the ground truth's tolerance, which has no noise)",
        bounds=(0, 100))
    threshold_mm: float = _doc(
        1.0, "deformed area: points whose compensated displacement reaches this (mm; the spec's "
        "static tolerance) and is significant, connected to the contact point", bounds=(0, 100))
    max_edge_mm: float = _doc(
        10.0, "areas: the template is triangulated around the contact point; a triangle with "
        "an edge longer than this (and than 8 median edges) spans a hole and counts no area (mm)",
        bounds=(0, 1000))
    significance: float = _doc(
        0.01, "false-alarm probability of the test 'the compensated displacement is more than "
        "the noise explains' (chi-square, 3 dof)", bounds=(0, 0.5))
    tip_radius_mm: float = _doc(
        3.0, "depth at the contact point: fitted to the points within this of the tool axis (mm)",
        bounds=(0, 100))
    youngs_modulus_kpa: float = _doc(
        0.0, "force proxy (a model output, not a measurement): Hertzian contact of a sphere of "
        "the shaft radius on an elastic half-space of this Young's modulus (kPa; 0 = off)",
        bounds=(0, 1e6))
    poisson_ratio: float = _doc(0.45, "Poisson's ratio of the tissue in the force proxy",
        bounds=(0, 0.5))

    def __post_init__(self) -> None:
        key = "deformation."
        _require(self.ring_inner_mm > 0, key + "ring_inner_mm", "must be > 0")
        _require(self.ring_outer_mm > self.ring_inner_mm, key + "ring_outer_mm",
                 "must be > ring_inner_mm")
        _require(self.ring_points >= 6, key + "ring_points", "must be >= 6")
        _require(self.contact_sigmas >= 0, key + "contact_sigmas", "must be >= 0")
        for name in ("contact_floor_mm", "threshold_mm", "max_edge_mm", "tip_radius_mm"):
            _require(getattr(self, name) > 0, key + name, "must be > 0")
        _require(0 < self.significance < 0.5, key + "significance", "must be in (0, 0.5)")
        _require(self.youngs_modulus_kpa >= 0, key + "youngs_modulus_kpa", "must be >= 0")
        _require(0 <= self.poisson_ratio < 0.5, key + "poisson_ratio", "must be in [0, 0.5)")
        check_bounds(self, "deformation")
