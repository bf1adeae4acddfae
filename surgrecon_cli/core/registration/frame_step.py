"""One frame of the registration pipeline (Su et al. 2019, Fig. 2), `FrameRegistrar.step`:
target cloud -> data weights -> the scene's robust rigid motion, then the non-rigid
remainder with the tool-contact constraint -> composition with the base's transforms ->
per-point uncertainty of the result. The registrar is built once per run (template,
cameras, noise model, config); the stage (stages/register.py) only loads the inputs and
writes the outputs.

Uncertainty of a registered position (σ, metres, RMS of the 3D error):
- a point with a target: σ² = σ_target² + r² (+ σ_template² for a re-triangulated
  target), r its distance to that target after the registration (the data did not pin it
  where the field put it: the difference is error); the template's own uncertainty counts
  because it decides which material point a template point is (its error along the
  surface is not seen by any later measurement);
- a point without one (unobserved, outlier): σ² = σ_s² + (g d)², d its frame-0 distance to
  the nearest point with a target, σ_s that point's σ and g = `registration.
  extrapolation_growth`: how fast an extrapolated displacement field loses accuracy with
  distance from its support.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import cKDTree

from ...config import Config
from ...errors import GeometryError
from ..classify.labels import INTER, INTRA, UNOBSERVED
from ..geometry.cameras import CameraModel
from ..geometry.poses import compose_affines
from ..geometry.tool import push_out_of_tool
from ..noise.model import NoiseModel, covariance_sigma
from ..target.cloud import TargetCloud, build_target, new_target_points
from ..target.frame_inputs import ChainMemo, FrameInput, PairMemo, Rig, Sighting, TemplateData
from ..target.tracking import TrackingView
from ..template.build import TemplateFrame, build_template
from . import RegistrationResult, register
from .rigid_fit import robust_rigid

FOLLOW_FROM_M = 3e-3  # ours: points without data this far from the data start to follow ...
FOLLOW_FULL_M = 8e-3  # ... the blend of the data's displacements, fully from this far
RIGID_INLIER_SIGMAS = 3.0  # ours: a target within 3 σ of the rigid motion follows it
RIGID_INLIER_FLOOR_M = 0.5e-3  # ... or within 0.5 mm (σ may be under-estimated)


@dataclass(frozen=True)
class BaseState:
    """What a frame is registered against: the base frame's index, its transforms from the
    frame-0 template (N, 3, 4), registered points (N, 3) m, latest positions (N, 3) m
    (target where observed, else registered) and its images, poses and the pixels where
    the points were seen there (N, C, 2)."""

    frame: int
    transforms: np.ndarray
    source: np.ndarray
    latest: np.ndarray
    seen: Sighting


@dataclass(frozen=True)
class DataTerm:
    """The registration's data: target points (M, 3) m with colours (M, 3) uint8 and the
    template index each one is (M,) (-1: a new point, matched by nearest neighbour), and
    the data weight of every template point (N,) (`data_weights`)."""

    xyz: np.ndarray
    rgb: np.ndarray
    ids: np.ndarray
    weights: np.ndarray


@dataclass(frozen=True)
class FrameResult:
    """One registered frame: transforms (N, 3, 4) from the frame-0 template, registered
    (N, 3) m, sigma (N,) m (module docstring), residual (N,) m to the point's target (NaN
    without one), support_mm (N,) frame-0 distance to the nearest point with a target; the
    target cloud; counts and timings."""

    transforms: np.ndarray
    registered: np.ndarray
    sigma: np.ndarray
    residual: np.ndarray
    support_mm: np.ndarray
    target: TargetCloud
    new_points: int
    contact_points: int
    converged: bool
    seconds_target: float
    seconds_register: float


def unregistered(n_points: int, n_cams: int) -> FrameResult:
    """The result of a frame that could not be registered: no position (NaN), no target,
    every point unobserved (nothing was seen of it: a black or blurred frame is not 100 %
    outliers) with unbounded uncertainty (so classified unknown)."""
    nan3 = np.full((n_points, 3), np.nan)
    target = TargetCloud(
        positions=nan3, status=np.full(n_points, UNOBSERVED, np.uint8),
        views=np.zeros(n_points, np.int64), pixels=np.full((n_points, n_cams, 2), np.nan),
        covariance=np.full((n_points, 3, 3), np.nan), pose_covariance=np.zeros((n_points, 3, 3)),
        sigma=np.full(n_points, np.nan),
        noise=NoiseModel(np.nan, np.nan, np.nan, np.nan))
    return FrameResult(
        transforms=np.full((n_points, 3, 4), np.nan), registered=nan3,
        sigma=np.full(n_points, np.inf), residual=np.full(n_points, np.nan),
        support_mm=np.full(n_points, np.inf), target=target, new_points=0, contact_points=0,
        converged=False, seconds_target=0.0, seconds_register=0.0)


def data_weights(target: TargetCloud, has_new: bool) -> np.ndarray:
    """Data weight (N,) per template point: a tracked point (intra/inter) weighs by its
    precision relative to the frame's median, w = σ_median / σ (the l1 data term's scale
    is σ), capped at 1; unobserved points 0, so they follow their neighbours, unless new
    points were triangulated this frame: then they may match one by nearest neighbour
    (weight 1, gated). Outliers always 0."""
    status, sigma = target.status, target.sigma
    tracked = (status == INTRA) | (status == INTER)
    weights = np.zeros(len(status))
    if tracked.any():
        reference = float(np.median(sigma[tracked]))
        weights[tracked] = np.minimum(1.0, reference / np.maximum(sigma[tracked], 1e-12))
    if has_new:
        weights[status == UNOBSERVED] = 1.0
    return weights


def predicted_positions(source: np.ndarray, target_xyz: np.ndarray, target_ids: np.ndarray,
                        k: int) -> np.ndarray:
    """Where the registration will roughly put each source point (N, 3) m: moved by the
    inverse-distance blend of the displacements (target - source) of its k nearest points
    with a known target (target_ids >= 0; their own displacement for themselves). With no
    such point: the source itself."""
    known = target_ids >= 0
    if not known.any():
        return np.array(source, dtype=float)
    anchors = target_ids[known]
    shift = target_xyz[known] - source[anchors]
    k = min(k, len(anchors))
    d, j = cKDTree(source[anchors]).query(source, k=k)
    d, j = d.reshape(len(source), k), j.reshape(len(source), k)
    w = 1.0 / np.maximum(d, 1e-9)
    return source + np.einsum("nk,nkj->nj", w / w.sum(1, keepdims=True), shift[j])


def register_with_contact(source: np.ndarray, source_rgb: np.ndarray, data: DataTerm,
                          tool_pose: np.ndarray, config: Config) -> tuple[RegistrationResult, int]:
    """Register source (N, 3) m (colours (N, 3) uint8) to the data with the tissue kept out
    of the tool (robot kinematics, Su et al. 2019 section II.C), in one solve: points
    without data (weight 0: under the tool, hidden by it) predicted inside the tool's
    capsule (`predicted_positions`: moved with their tracked neighbours) get a target on
    the capsule's surface, pushed along the shaft, so that the field around the tool
    follows the contact; after the solve, the other points without data farther than
    FOLLOW_FROM_M from any data point move towards the inverse-distance blend of their
    nearest data points' displacements (`predicted_positions` on the registered positions),
    fully from FOLLOW_FULL_M on: far from its support, the solve's affine field, fitted to
    the data's noise, would amplify it with distance; near it, the field follows a dent
    better than a blend. Every point without data still inside the capsule (the l1 fit
    leaves a contact target a little short of it, and the prediction can miss a point) is
    moved onto the surface, its transform translated by the same push. tool_pose (K, 4, 4):
    every tool's pose (`config.tool_configs()`). Returns the result and the number of
    points in contact."""
    target_xyz, target_ids, weights = data.xyz, data.ids, data.weights
    guess = predicted_positions(source, target_xyz, target_ids,
                                config.registration.interp_neighbors)
    without_data = weights == 0
    inside, pushed = push_out_of_tool(guess, tool_pose, config.tool_configs())
    predicted = inside & without_data
    contact = np.flatnonzero(predicted)
    result = register(source, np.concatenate([target_xyz, pushed[contact]]),
                      source_rgb=source_rgb,
                      target_rgb=np.concatenate([data.rgb, source_rgb[contact]]),
                      config=config.registration,
                      target_ids=np.concatenate([target_ids, contact]),
                      weights=np.where(predicted, 1.0, weights))
    anchors = np.flatnonzero(~without_data)
    free = np.flatnonzero(without_data & ~predicted)
    registered = result.registered.copy()
    if len(anchors) and len(free):
        follow = predicted_positions(source, result.registered[anchors], anchors,
                                     config.registration.interp_neighbors)
        distance, _ = cKDTree(source[anchors]).query(source[free])
        share = np.clip((distance - FOLLOW_FROM_M) / (FOLLOW_FULL_M - FOLLOW_FROM_M), 0, 1)
        registered[free] += share[:, None] * (follow[free] - registered[free])
    inside, pushed = push_out_of_tool(registered, tool_pose, config.tool_configs())
    moved = inside & without_data
    registered = np.where(moved[:, None], pushed, registered)
    transforms = result.transforms.copy()
    transforms[:, :, 3] += registered - result.registered
    return (replace(result, transforms=transforms, registered=registered),
            int((moved | predicted).sum()))


def rigid_start(source: np.ndarray, target: TargetCloud) -> np.ndarray:
    """The scene's rigid motion (3, 4) from the base's cloud source (N, 3) m to the frame's
    target: a robust fit (core/rigid_fit.robust_rigid) on the points with a target, inliers
    within RIGID_INLIER_SIGMAS of their median σ (at least RIGID_INLIER_FLOOR_M). The
    registration then only solves what is not rigid, and points without data follow the
    rigid motion (with their neighbours' remainder) instead of staying behind."""
    has = ((target.status == INTRA) | (target.status == INTER)) & np.isfinite(target.sigma)
    scale = float(np.median(target.sigma[has])) if has.any() else 0.0
    R, t, _ = robust_rigid(source[has], target.positions[has],
                           max(RIGID_INLIER_SIGMAS * scale, RIGID_INLIER_FLOOR_M))
    return np.concatenate([R, t[:, None]], axis=1)


def register_rigid_first(source: np.ndarray, source_rgb: np.ndarray, target: TargetCloud,
                         data: DataTerm, tool_pose: np.ndarray,
                         config: Config) -> tuple[RegistrationResult, int]:
    """`register_with_contact` of source (N, 3) m moved first by the scene's rigid motion to
    `target` (`rigid_start`): the non-rigid registration solves the remainder, and points
    without data follow the rigid motion plus their neighbours' remainder. The result's
    transforms (N, 3, 4) include the rigid motion (source -> registered)."""
    rigid = rigid_start(source, target)
    moved = source @ rigid[:, :3].T + rigid[:, 3]
    result, n_contact = register_with_contact(moved, source_rgb, data, tool_pose, config)
    transforms = compose_affines(result.transforms, np.broadcast_to(rigid, result.transforms.shape))
    return replace(result, transforms=transforms), n_contact


def registered_sigma(template: np.ndarray, template_sigma: np.ndarray, registered: np.ndarray,
                     target: TargetCloud,
                     growth: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """σ (N,) m of registered positions (module docstring; template_sigma (N,) m), the
    residual (N,) m to the target (NaN without one) and the support distance (N,) mm."""
    n = len(template)
    has = np.isfinite(target.sigma) & np.isfinite(target.positions).all(1)
    residual = np.full(n, np.nan)
    residual[has] = np.linalg.norm(registered[has] - target.positions[has], axis=1)
    sigma = np.full(n, np.inf)
    support = np.full(n, np.inf)
    identity = np.where(target.status == INTER, template_sigma, 0.0)
    sigma[has] = np.sqrt(target.sigma[has] ** 2 + residual[has] ** 2 + identity[has] ** 2)
    support[has] = 0.0
    rest = np.flatnonzero(~has)
    if has.any() and len(rest):
        anchors = np.flatnonzero(has)
        distance, nearest = cKDTree(template[anchors]).query(template[rest])
        sigma[rest] = np.hypot(sigma[anchors[nearest]], growth * distance)
        support[rest] = distance * 1e3
    return sigma, residual, support


class FrameRegistrar:
    """The frame step of one run, built once from its template, cameras, noise model and
    config: `step(frame, base)` registers a frame against its base. `anchor`: the
    template's frame-0 tracking views, against which tracks are corrected and lost points
    re-acquired (core/target/track_points.py; None: tracks from the base only); their
    gradient images, which the template lock samples, are built here, once (~30 ms a
    1280×1024 view), not by the first locked frame."""

    def __init__(self, template: TemplateData, models: list[CameraModel], noise: NoiseModel,
                 config: Config, anchor: list[TrackingView | None] | None = None) -> None:
        self.template = template
        self.rig = Rig(list(models), noise, config.target, config.tool_configs(), ChainMemo(),
                       PairMemo())
        self.config = config
        self.anchor = anchor
        for view in anchor or []:
            if view is not None:
                view.gradients  # noqa: B018 (a cached property: built now)
        self.template_sigma = covariance_sigma(template.covariance)

    def step(self, frame: FrameInput, base: BaseState) -> FrameResult:
        """Target cloud and registration of `frame` against `base`: the base's cloud is
        moved by the scene's robust rigid motion to the target, the registration solves
        the non-rigid remainder. Raises GeometryError when the frame cannot be registered
        (e.g. too few tracked points)."""
        start = time.perf_counter()
        target = build_target(self.template, self.rig, base.latest, base.seen, frame,
                              self.anchor)
        data = self.data_term(target, frame)
        seconds_target = time.perf_counter() - start
        start = time.perf_counter()
        result, n_contact = register_rigid_first(base.source, self.template.rgb, target, data,
                                                 frame.tool_pose, self.config)
        seconds_register = time.perf_counter() - start
        sigma, residual, support = registered_sigma(
            self.template.points, self.template_sigma, result.registered, target,
            self.config.registration.extrapolation_growth)
        return FrameResult(
            transforms=compose_affines(result.transforms, base.transforms),
            registered=result.registered, sigma=sigma, residual=residual,
            support_mm=support, target=target, new_points=int((data.ids < 0).sum()),
            contact_points=n_contact,
            converged=bool(result.stats[-1].get("converged", False)),
            seconds_target=seconds_target, seconds_register=seconds_register)

    def data_term(self, target: TargetCloud, frame: FrameInput) -> DataTerm:
        """The tracked points' targets, and with `frame.images` the frame's new features
        triangulated away from them (index -1); raises GeometryError under 3 points."""
        ids = np.flatnonzero((target.status == INTRA) | (target.status == INTER))
        xyz, rgb = target.positions[ids], self.template.rgb[ids]
        n_new = 0
        if frame.images is not None:
            new_xyz, new_rgb = self._new_points(frame.images, frame, xyz)
            n_new = len(new_xyz)
            xyz, rgb = np.concatenate([xyz, new_xyz]), np.concatenate([rgb, new_rgb])
            ids = np.concatenate([ids, np.full(n_new, -1)])
        if len(xyz) < 3:
            counts = ", ".join(f"{name} {n}" for name, n in target.counts().items())
            raise GeometryError(f"{len(ids)} template point(s) tracked into this frame "
                                f"({counts}); need >= 3")
        return DataTerm(xyz, rgb, ids, data_weights(target, has_new=n_new > 0))

    def _new_points(self, images: list[np.ndarray | None], frame: FrameInput,
                    tracked: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """New features of the frame's `images` triangulated as in the template build, away
        from the tracked points (K, 3) m: (M, 3) m and colours (M, 3) uint8."""
        try:
            fresh = build_template(TemplateFrame(images, frame.poses, frame.seen_tools),
                                   self.rig.models, self.config.template, self.rig.tools)
        except GeometryError:
            return np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
        return new_target_points(fresh.points, fresh.rgb, tracked,
                                 self.config.target.new_point_spacing_mm * 1e-3)
