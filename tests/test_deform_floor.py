"""The labels' sensitivity along the lines of sight (`departure.deform_floor_mm`): the
smallest departure along each member's least-known direction that the classifier counts as
deformation. Dents are built with a known plain rigid-fit RMS (the spec's rule on the
constructed positions); the floor must say which of them the classifier can see."""

from __future__ import annotations

import numpy as np

from surgrecon_cli.config import ClassifyConfig
from surgrecon_cli.core.classify.departure import deform_floor_mm, resolved_rms_mm
from surgrecon_cli.core.classify.labels import UNKNOWN
from surgrecon_cli.core.classify.rules import (
    Evidence,
    RegisteredFrame,
    classify_frame,
    rigid_rms_mm,
    template_neighbourhoods,
)


def _patch() -> np.ndarray:
    """A 30 x 30 mm patch on a 2 mm grid, 65 mm in front of the camera (metres)."""
    g = np.arange(-15, 15, 2) * 1e-3
    xx, yy = np.meshgrid(g, g)
    return np.column_stack([xx.ravel(), yy.ravel(), np.full(xx.size, 0.065)])


def _cov(n: int, depth_m: float, lateral_m: float) -> np.ndarray:
    return np.broadcast_to(np.diag([lateral_m**2, lateral_m**2, depth_m**2]), (n, 3, 3)).copy()


def _nb(template: np.ndarray, cfg: ClassifyConfig):
    return template_neighbourhoods(template, cfg.neighbourhood_mm, cfg.min_neighbours,
                                   cfg.max_neighbours)


def test_the_floor_is_deform_mm_where_every_direction_is_measured_well():
    cfg = ClassifyConfig()
    template = _patch()
    n, nb = len(template), _nb(template, cfg)
    rows = np.arange(n)
    for cov in (np.zeros((n, 3, 3)), _cov(n, 0.01e-3, 0.01e-3)):
        assert np.allclose(deform_floor_mm(cov, nb, rows, cfg.deform_mm), cfg.deform_mm,
                           rtol=1e-6)
    # never below deform_mm, whatever the covariances' shape
    a = np.random.default_rng(4).normal(0.0, 0.3e-3, (n, 3, 3))
    floor = deform_floor_mm(a @ a.transpose(0, 2, 1), nb, rows, cfg.deform_mm)
    assert (floor >= cfg.deform_mm * (1 - 1e-9)).all()
    # a member without a covariance carries no weight; fewer than 3 left: NaN
    cov = np.full((n, 3, 3), np.nan)
    assert np.isnan(deform_floor_mm(cov, nb, rows, cfg.deform_mm)).all()


def test_a_dent_along_the_view_counts_from_the_floor_not_below():
    """A 4 mm stereo baseline at 65 mm: depth known to 0.4 mm, across to 0.03 mm. A bump
    along the view (the least-known direction) whose true rigid-fit RMS is 1.3x the floor
    counts as deformation at the bump; at 0.7x it does not."""
    cfg = ClassifyConfig()
    template = _patch()
    n, nb = len(template), _nb(template, cfg)
    rows = np.arange(n)
    cov = _cov(n, 0.4e-3, 0.03e-3)
    floor = deform_floor_mm(cov, nb, rows, cfg.deform_mm)
    assert np.nanmin(floor) > 2 * cfg.deform_mm  # depth noise far above deform_mm/√3
    r2 = (template[:, :2] ** 2).sum(1)
    core = r2 < 0.0025**2
    bump = np.zeros_like(template)
    bump[:, 2] = np.exp(-r2 / (2 * 0.003**2))
    unit_rms = rigid_rms_mm(template, template + 1e-3 * bump, nb, rows)  # per mm of height
    height_mm = floor[core].mean() / unit_rms[core].mean()
    for factor, counts in ((1.3, True), (0.7, False)):
        dented = template + factor * height_mm * 1e-3 * bump
        true_rms = rigid_rms_mm(template, dented, nb, rows)[core]
        assert np.allclose(true_rms / floor[core], factor, rtol=0.1)
        resolved = resolved_rms_mm(template, dented, cov, nb, rows, cfg.deform_mm)[core]
        assert ((resolved >= cfg.deform_mm) == counts).all(), (factor, resolved)


def test_classify_frame_reports_the_floor_of_its_labelled_points():
    """A rigid shift whose registered field scatters as its covariance says: the floor is
    the covariance's. The same shift without any scatter: the covariance overstates the
    field's noise (`field_noise_scale`) and the floor falls to deform_mm."""
    cfg = ClassifyConfig()
    template = _patch()
    n, nb = len(template), _nb(template, cfg)
    depth, lateral = 0.4e-3, 0.03e-3
    cov = _cov(n, depth, lateral)
    shift = template + np.array([0.003, 0.0, 0.0])
    noise = np.random.default_rng(5).normal(0.0, 1.0, template.shape) * [lateral, lateral, depth]
    full = deform_floor_mm(cov, nb, np.arange(n), cfg.deform_mm)

    def classes(positions: np.ndarray, with_evidence: bool = True):
        positions = positions.copy()
        positions[:5] = np.nan  # not found: unknown, no floor
        evidence = Evidence(sigma=np.full(n, depth), template_sigma=np.zeros(n),
                            measured=positions, measured_sigma=np.full(n, depth),
                            displacement_cov=cov, departure_cov=cov)
        return classify_frame(template, RegisteredFrame(positions), nb, cfg,
                              evidence=evidence if with_evidence else None)

    out = classes(shift + noise)
    labelled = out.labels != UNKNOWN
    assert not labelled[:5].any() and labelled[5:].all()
    assert np.isnan(out.floor_mm[~labelled]).all()
    assert np.allclose(out.floor_mm[labelled], full[labelled], rtol=0.1)
    assert (out.floor_mm[labelled] > 2 * cfg.deform_mm).all()
    smooth = classes(shift)
    assert np.allclose(smooth.floor_mm[labelled], cfg.deform_mm, rtol=0.01)
    # without noise evidence the plain rule holds: the floor is deform_mm itself
    assert np.allclose(classes(shift, with_evidence=False).floor_mm[labelled], cfg.deform_mm)
