"""Shifting vs deforming on a narrow stereo baseline (issue 24, real breathing): depth noise
of the displacement must not read as deformation, lateral deformation still must, and the
run states the smallest bend along the lines of sight it counts (its deformation floor).
Expected labels and magnitudes come from the constructed truth."""

from __future__ import annotations

import numpy as np

from surgrecon_cli.config import ClassifyConfig
from surgrecon_cli.core.classify.departure import (
    deform_floor_mm,
    field_noise_scale,
    resolved_rms_mm,
)
from surgrecon_cli.core.classify.labels import (
    DEFORMING,
    SHIFTING,
    UNKNOWN,
    label_rule,
    radius_neighbourhoods,
)
from surgrecon_cli.core.classify.rules import (
    Evidence,
    RegisteredFrame,
    classify_frame,
    displacement_covariance,
    rigid_rms_mm,
    template_neighbourhoods,
)


def _patch() -> np.ndarray:
    """A 30 x 30 mm patch on a 2 mm grid, 65 mm in front of the camera (metres)."""
    g = np.arange(-15, 15, 2) * 1e-3
    xx, yy = np.meshgrid(g, g)
    return np.column_stack([xx.ravel(), yy.ravel(), np.full(xx.size, 0.065)])


def _depth_cov(n: int, depth_m: float, lateral_m: float) -> np.ndarray:
    return np.broadcast_to(np.diag([lateral_m**2, lateral_m**2, depth_m**2]), (n, 3, 3)).copy()


def test_displacement_covariance_removes_the_shared_template_error():
    template = _depth_cov(2, 1.0e-3, 0.04e-3)
    tracked = _depth_cov(2, 1.1e-3, 0.05e-3)
    tracked[1] = template[1] * 0.25  # a measurement four times better than the template
    out = displacement_covariance(tracked, template)
    # the tracking's own part: Σ_x − Σ_p where x carries all of p's error
    assert np.allclose(np.diag(out[0]), [0.05e-3**2 - 0.04e-3**2] * 2 + [1.1e-3**2 - 1e-3**2],
                       rtol=1e-3)
    # x carries at most its own error: the difference of the variances, as displacement_sigma
    assert np.allclose(np.diag(out[1]), np.diag(template[1]) * 0.75, rtol=1e-3)
    rotated = np.linalg.qr(np.random.default_rng(0).normal(size=(3, 3)))[0]
    turned = displacement_covariance(rotated @ tracked @ rotated.T, rotated @ template @ rotated.T)
    assert np.allclose(turned, rotated @ out @ rotated.T, atol=1e-14)


def test_resolved_rms_is_the_rigid_fit_rms_without_noise():
    rng = np.random.default_rng(1)
    template = _patch()
    moved = template + rng.normal(0.0, 0.3e-3, template.shape)
    nb = template_neighbourhoods(template, 5.0, 6, 128)
    rows = np.arange(len(template))
    plain = rigid_rms_mm(template, moved, nb, rows)
    resolved = resolved_rms_mm(template, moved, np.zeros((len(template), 3, 3)), nb, rows, 0.25)
    assert np.allclose(resolved, plain, rtol=1e-6)


def test_depth_noise_of_a_rigid_shift_is_not_deformation_lateral_bending_is():
    rng = np.random.default_rng(2)
    cfg = ClassifyConfig()
    template = _patch()
    n = len(template)
    depth, lateral = 0.5e-3, 0.03e-3  # a 4 mm baseline at 65 mm: depth ~15x worse
    shift = template + np.array([0.002, 0.0, -0.0015])
    noise = rng.normal(0.0, 1.0, template.shape) * np.array([lateral, lateral, depth])
    nb = template_neighbourhoods(template, cfg.neighbourhood_mm, cfg.min_neighbours,
                                 cfg.max_neighbours)
    cov = _depth_cov(n, depth, lateral)
    rows = np.arange(n)
    # plain RMS of the noisy rigid shift is well above deform_mm, the resolved one is not
    assert np.median(rigid_rms_mm(template, shift + noise, nb, rows)) > 1.5 * cfg.deform_mm
    assert np.mean(resolved_rms_mm(template, shift + noise, cov, nb, rows, cfg.deform_mm)
                   >= cfg.deform_mm) < 0.05
    evidence = Evidence(sigma=np.full(n, depth), template_sigma=np.zeros(n),
                        measured=shift + noise, measured_sigma=np.full(n, depth),
                        displacement_cov=cov, departure_cov=cov)
    labels = classify_frame(template, RegisteredFrame(shift + noise), nb, cfg,
                            evidence=evidence).labels
    assert (labels == DEFORMING).mean() < 0.05
    assert (labels == SHIFTING).mean() > 0.9
    # a lateral bend (1.5 mm wide bulge sideways) on the same noise is still deforming
    r2 = (template[:, :2] ** 2).sum(1)
    bent = shift.copy()
    bent[:, 0] += 0.0015 * np.exp(-r2 / (2 * 0.003**2))
    index, mask = radius_neighbourhoods(template, cfg.neighbourhood_mm * 1e-3)
    truth = label_rule(template, bent, index, mask, cfg.static_mm, cfg.deform_mm)
    evidence = Evidence(sigma=np.full(n, depth), template_sigma=np.zeros(n),
                        measured=bent + noise, measured_sigma=np.full(n, depth),
                        displacement_cov=cov, departure_cov=cov)
    labels = classify_frame(template, RegisteredFrame(bent + noise), nb, cfg,
                            evidence=evidence).labels
    core = r2 < 0.003**2
    assert (truth[core] == DEFORMING).all()
    assert (labels[core] == DEFORMING).mean() > 0.8
    far = r2 > 0.012**2
    assert (truth[far] == SHIFTING).all()
    assert (labels[far] == DEFORMING).mean() < 0.1


def test_a_dent_the_tool_hides_is_deforming_where_the_tool_touches_it():
    """Points under the tool have no target: their registered positions carry the
    extrapolation's σ (0.6 mm a direction here), which no departure exceeds. The tool
    touching them is the evidence; it does not make a rigid shift deform."""
    cfg = ClassifyConfig()
    template = _patch()
    n = len(template)
    r2 = (template[:, :2] ** 2).sum(1)
    shift = template + np.array([0.005, 0.0, 0.0])
    dented = shift.copy()
    dented[:, 2] += 0.0015 * np.exp(-r2 / (2 * 0.002**2))  # pressed 1.5 mm along the view
    hidden = r2 < 0.007**2
    cov = _depth_cov(n, 0.1e-3, 0.03e-3)
    cov[hidden] = np.eye(3) * 0.6e-3**2
    nb = template_neighbourhoods(template, cfg.neighbourhood_mm, cfg.min_neighbours,
                                 cfg.max_neighbours)
    index, mask = radius_neighbourhoods(template, cfg.neighbourhood_mm * 1e-3)
    truth = label_rule(template, dented, index, mask, cfg.static_mm, cfg.deform_mm)
    core = r2 < 0.0025**2
    assert (truth[core] == DEFORMING).all()

    def labels(positions: np.ndarray, touched: np.ndarray | None) -> np.ndarray:
        evidence = Evidence(sigma=np.sqrt(np.trace(cov, axis1=1, axis2=2)),
                            template_sigma=np.zeros(n), measured=positions,
                            measured_sigma=np.sqrt(np.trace(cov, axis1=1, axis2=2)),
                            displacement_cov=cov, departure_cov=cov, touched=touched)
        return classify_frame(template, RegisteredFrame(positions), nb, cfg,
                              evidence=evidence).labels

    assert (labels(dented, None)[core] == SHIFTING).mean() > 0.8
    touched = r2 < 0.0025**2
    assert (labels(dented, touched)[core] == DEFORMING).all()
    far = r2 > 0.012**2
    assert (truth[far] == SHIFTING).all() and (labels(dented, touched)[far] == SHIFTING).all()
    assert (labels(shift, touched) == SHIFTING).all()


def test_a_dent_along_the_lines_of_sight_counts_fully_where_the_field_is_smoother_than_its_noise():
    """The 6-camera rig's case: depth known 5x worse than across (0.15 / 0.03 mm), a dent
    pressed along the view. Weighted by that covariance, the dent's RMS is discounted below
    deform_mm; the registered field here has no scatter at all, so its covariance overstates
    its noise and the dent counts at its plain RMS. A field as noisy as its covariance keeps
    the weights."""
    cfg = ClassifyConfig()
    template = _patch()
    n = len(template)
    r2 = (template[:, :2] ** 2).sum(1)
    dented = template + np.array([0.003, 0.0, -0.001])
    dented[:, 2] += 0.002 * np.exp(-r2 / (2 * 0.003**2))
    depth, lateral = 0.15e-3, 0.03e-3
    cov = _depth_cov(n, depth, lateral)
    nb = template_neighbourhoods(template, cfg.neighbourhood_mm, cfg.min_neighbours,
                                 cfg.max_neighbours)
    index, mask = radius_neighbourhoods(template, cfg.neighbourhood_mm * 1e-3)
    truth = label_rule(template, dented, index, mask, cfg.static_mm, cfg.deform_mm)
    deforming = truth == DEFORMING
    assert deforming.sum() >= 10
    rows = np.arange(n)
    weighted = resolved_rms_mm(template, dented, cov, nb, rows, cfg.deform_mm)
    assert (weighted[deforming] >= cfg.deform_mm).mean() < 0.5
    scale = field_noise_scale(template, dented, cov, nb, rows)
    assert scale < 0.01
    evidence = Evidence(sigma=np.full(n, depth), template_sigma=np.zeros(n), measured=dented,
                        measured_sigma=np.full(n, depth), displacement_cov=cov,
                        departure_cov=cov)
    labels = classify_frame(template, RegisteredFrame(dented), nb, cfg,
                            evidence=evidence).labels
    assert (labels[deforming] == DEFORMING).all()
    assert (labels[~deforming] != DEFORMING).all()
    noise = np.random.default_rng(3).normal(0.0, 1.0, template.shape) * [lateral, lateral, depth]
    assert field_noise_scale(template, template + noise, cov, nb, rows) > 0.7

def _nb(template: np.ndarray, cfg: ClassifyConfig):
    return template_neighbourhoods(template, cfg.neighbourhood_mm, cfg.min_neighbours,
                                   cfg.max_neighbours)


# --- the labels' sensitivity along the lines of sight (`departure.deform_floor_mm`): the
# smallest departure along each member's least-known direction that the classifier counts as
# deformation; dents built with a known plain rigid-fit RMS (the spec's rule on the
# constructed positions), the floor must say which of them the classifier can see.


def test_the_floor_is_deform_mm_where_every_direction_is_measured_well():
    cfg = ClassifyConfig()
    template = _patch()
    n, nb = len(template), _nb(template, cfg)
    rows = np.arange(n)
    for cov in (np.zeros((n, 3, 3)), _depth_cov(n, 0.01e-3, 0.01e-3)):
        floor = deform_floor_mm(template, cov, nb, rows, cfg.deform_mm)
        assert np.allclose(floor, cfg.deform_mm, rtol=1e-6)
    # never below deform_mm, whatever the covariances' shape
    a = np.random.default_rng(4).normal(0.0, 0.3e-3, (n, 3, 3))
    floor = deform_floor_mm(template, a @ a.transpose(0, 2, 1), nb, rows, cfg.deform_mm)
    assert (floor >= cfg.deform_mm * (1 - 1e-9)).all()
    # a member without a covariance or a position carries no weight; fewer than 3: NaN
    assert np.isnan(deform_floor_mm(template, np.full((n, 3, 3), np.nan), nb, rows,
                                    cfg.deform_mm)).all()
    unseen = np.full_like(template, np.nan)
    assert np.isnan(deform_floor_mm(unseen, _depth_cov(n, 0.4e-3, 0.03e-3), nb, rows,
                                    cfg.deform_mm)).all()
    # members left out are not counted: a neighbourhood whose badly measured members are
    # unseen has the floor of its well measured ones
    cov = _depth_cov(n, 0.01e-3, 0.01e-3)
    bad = np.arange(n) % 2 == 1
    cov[bad] = _depth_cov(int(bad.sum()), 0.4e-3, 0.03e-3)
    positions = np.where(bad[:, None], np.nan, template)
    kept = deform_floor_mm(positions, cov, nb, rows, cfg.deform_mm)
    assert np.allclose(kept[np.isfinite(kept)], cfg.deform_mm, rtol=1e-6)
    assert (deform_floor_mm(template, cov, nb, rows, cfg.deform_mm) > cfg.deform_mm).all()


def test_a_dent_along_the_view_counts_from_the_floor_not_below():
    """A 4 mm stereo baseline at 65 mm: depth known to 0.4 mm, across to 0.03 mm. A bump
    along the view (the least-known direction) whose true rigid-fit RMS is 1.3x the floor
    counts as deformation at the bump; at 0.7x it does not."""
    cfg = ClassifyConfig()
    template = _patch()
    n, nb = len(template), _nb(template, cfg)
    rows = np.arange(n)
    cov = _depth_cov(n, 0.4e-3, 0.03e-3)
    floor = deform_floor_mm(template, cov, nb, rows, cfg.deform_mm)
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
    cov = _depth_cov(n, depth, lateral)
    shift = template + np.array([0.003, 0.0, 0.0])
    noise = np.random.default_rng(5).normal(0.0, 1.0, template.shape) * [lateral, lateral, depth]
    full = deform_floor_mm(template, cov, nb, np.arange(n), cfg.deform_mm)

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
