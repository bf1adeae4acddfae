"""Config section `[registration]`: the sparse non-rigid registration of
core/registration/ (also `surgrecon register-pair` and the library call)."""

from __future__ import annotations

from dataclasses import dataclass

from .fields import _doc, _require, check_bounds


@dataclass(frozen=True)
class RegistrationConfig:
    """Sparse non-rigid registration (per-point affine transforms, ADMM); defaults are ours."""

    k_neighbors: int = _doc(8, "neighbours per node in the smoothness graph", bounds=(2, 64))
    max_nodes: int = _doc(
        400, "nodes solved for; each point's affine blends its nearest nodes' (0 = one per point)",
        bounds=(0, 100_000)
    )
    interp_neighbors: int = _doc(4, "nodes blended into each point's transform", bounds=(1, 64))
    alpha: float = _doc(0.05, "weight of the neighbour-difference term (final, after annealing)",
        bounds=(0, 1e6))
    alpha_start: float = _doc(1.0, "stiff initial smoothness weight of the annealing schedule",
        bounds=(0, 1e6))
    beta: float = _doc(0.0, "weight keeping each linear part near a rotation (0 = off)",
        bounds=(0, 1e6))
    data_penalty: str = _doc("l1", "'l1' (heavy-tailed, the paper's model) or 'l2' (Gaussian)")
    smooth_penalty: str = _doc("l1", "'l1' or 'l2' on neighbour differences")
    admm_iterations: int = _doc(5, "largest number of ADMM iterations per outer step",
        bounds=(1, 100_000))
    final_admm_iterations: int = _doc(
        300, "largest number of ADMM iterations of the last outer step (run to convergence)",
        bounds=(1, 100_000))
    outer_iterations: int = _doc(
        6, "correspondence/annealing outer steps (each lets colour-decided matches slide "
        "the surface further)", bounds=(1, 1000))
    mu: float = _doc(2.0, "ADMM penalty (in units of the reference node spacing)", bounds=(0, 1e6))
    mu_growth: float = _doc(1.0, "multiply mu by this every ADMM iteration (>1 refactorises)",
        bounds=(1, 100))
    relaxation: float = _doc(1.6, "ADMM over-relaxation factor, in [1, 2)", bounds=(1, 2))
    tolerance_mm: float = _doc(
        0.02, "ADMM stop: primal residual RMS and largest node step below this (mm), and the "
        "energy settled", bounds=(0, 100))
    extrapolation_growth: float = _doc(
        0.12, "uncertainty of a point without data grows by this many mm per mm of distance "
        "from the nearest point with data (measured on tuning logs: the 95th percentile of "
        "error / distance is 0.20-0.29 at 5-20 mm, i.e. 2 sigma)", bounds=(0, 100))
    color_weight_mm: float = _doc(
        0.0, "mm of position equivalent to a full RGB unit difference; 0 = automatic, from the "
        "target's texture: a slide along the surface costs 7.5x its length where the colour "
        "changes by more than its noise over max_correspondence_mm, else colour is not used",
        bounds=(0, 1e6))
    max_correspondence_mm: float = _doc(
        5.0, "nearest-neighbour correspondences farther are dropped (mm)", bounds=(0, 1000)
    )
    mutual_spacings: float = _doc(
        3.0, "drop a match whose target's nearest source is this many spacings away (0 = off)",
        bounds=(0, 1000)
    )
    reweight_mm: float = _doc(1.0, "l1 data reweighting w = e / (|r| + e), e in mm (0 = off)",
        bounds=(0, 1000))
    outlier_mm: float = _doc(1.0, "final correspondence residual above this flags an outlier (mm)",
        bounds=(0, 1000))
    rigid_iterations: int = _doc(30, "trimmed-ICP iterations of the rigid pre-alignment",
        bounds=(0, 10_000))
    rigid_trim: float = _doc(0.8, "fraction of closest pairs kept by the trimmed ICP",
        bounds=(0, 1))
    global_init: str = _doc(
        "auto", "coarse rotation + scale search before the ICP: 'auto' (when the clouds start "
        "farther apart than max_correspondence_mm), 'on' or 'off'")
    template_update_every: int = _doc(
        2, "re-base the template every N_T frames (0 = keep frame 0); frames are tracked and "
        "registered from their base, so N_T also bounds the tracking baseline and the chain "
        "of frames that must run in order", bounds=(0, 1_000_000))

    def __post_init__(self) -> None:
        key = "registration."
        _require(self.k_neighbors >= 2, key + "k_neighbors", "must be >= 2")
        _require(self.max_nodes == 0 or self.max_nodes >= 8, key + "max_nodes", "must be 0 or >= 8")
        _require(self.interp_neighbors >= 1, key + "interp_neighbors", "must be >= 1")
        for name in ("data_penalty", "smooth_penalty"):
            _require(getattr(self, name) in ("l1", "l2"), key + name, "must be 'l1' or 'l2'")
        _require(
            self.alpha > 0 and self.alpha_start >= self.alpha,
            key + "alpha",
            "need 0 < alpha <= alpha_start",
        )
        _require(self.beta >= 0, key + "beta", "must be >= 0")
        _require(self.admm_iterations > 0, key + "admm_iterations", "must be > 0")
        _require(self.final_admm_iterations > 0, key + "final_admm_iterations", "must be > 0")
        _require(self.extrapolation_growth >= 0, key + "extrapolation_growth", "must be >= 0")
        _require(self.outer_iterations > 0, key + "outer_iterations", "must be > 0")
        _require(self.mu > 0, key + "mu", "must be > 0")
        _require(self.mu_growth >= 1, key + "mu_growth", "must be >= 1")
        _require(1 <= self.relaxation < 2, key + "relaxation", "must be in [1, 2)")
        _require(self.tolerance_mm > 0, key + "tolerance_mm", "must be > 0")
        for name in ("color_weight_mm", "mutual_spacings", "reweight_mm"):
            _require(getattr(self, name) >= 0, key + name, "must be >= 0")
        for name in ("max_correspondence_mm", "outlier_mm"):
            _require(getattr(self, name) > 0, key + name, "must be > 0")
        _require(self.rigid_iterations >= 0, key + "rigid_iterations", "must be >= 0")
        _require(0 < self.rigid_trim <= 1, key + "rigid_trim", "must be in (0, 1]")
        _require(self.global_init in ("auto", "on", "off"), key + "global_init",
                 "must be 'auto', 'on' or 'off'")
        _require(self.template_update_every >= 0, key + "template_update_every", "must be >= 0")
        check_bounds(self, "registration")
