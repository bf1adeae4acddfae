"""Config schema: one frozen dataclass per TOML section, defaults, one-line docs (field
metadata "doc") and range checks (`ConfigError` naming the key) in `__post_init__`."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from .fields import _doc, _require, check_bounds
from .registration import RegistrationConfig

CAMERA_INFO_POSES = "camera_info"
"""topics.camera_pose naming no topic: the cameras are placed by their CameraInfo R and P."""


@dataclass(frozen=True)
class TopicsConfig:
    """Which topic plays which role; `{camera}` captures the camera id."""

    image: str = _doc("/endoscope_{camera}/color/compressed", "image topic pattern")
    image_rectified: str = _doc(
        "auto", "'yes': the images are rectified (ROS image_proc's image_rect*), modelled by "
        "their CameraInfo's P without distortion and turned by its R; 'no': raw; 'auto': "
        "'yes' when a part of the image topic name starts with image_rect")
    camera_info: str = _doc("/endoscope_{camera}/calibration", "intrinsics topic pattern")
    camera_pose: str = _doc(
        "/navigation/endoscope_{camera}/pose",
        "camera-to-world pose topic pattern, or the transform topic (e.g. /tf), or "
        "\"camera_info\": no poses, a stereo rig fixed in the world placed by its CameraInfo "
        "R and P (ROS stereo calibration: Tx = -fx' baseline), its first camera at the origin",
    )
    camera_frame: str = _doc(
        "endoscope_{camera}_optical",
        "camera optical frame pattern: its pose is the TF chain from it to world_frame",
    )
    tool_pose: str = _doc(
        "/raven/tool_tip", "tool tip pose topic (or transform topic); \"\" = no robot in the log"
    )
    tool_frame: str = _doc("raven_tool_tip", "tool tip frame when poses come as transforms")
    joint_states: str = _doc("/raven/joint_states", "robot joint states topic; \"\" = none")
    world_frame: str = _doc(
        "world", "frame the reconstruction is in; poses in other frames go through the TF tree"
    )
    camera_from_ecm: tuple[float, ...] = _doc(
        (), "hand-eye: each camera's pose in the frame of the poses on camera_pose when that is "
        "one topic for every camera (no {camera}; e.g. the dVRK ECM's /ECM/measured_cp): x y z "
        "qx qy qz qw (m) per camera in sorted camera-id order, or 7 numbers for all; empty = "
        "camera_pose is per camera", bounds=(-1000.0, 1000.0))

    @property
    def rectified(self) -> bool:
        """The images are rectified (`image_rectified`)."""
        if self.image_rectified == "auto":
            return any(part.startswith("image_rect") for part in self.image.split("/"))
        return self.image_rectified == "yes"

    @property
    def poses_from_camera_info(self) -> bool:
        """No pose topic: a fixed rig placed by its CameraInfo R and P (`CAMERA_INFO_POSES`)."""
        return self.camera_pose == CAMERA_INFO_POSES

    def __post_init__(self) -> None:
        check_bounds(self, "topics")
        _require(self.image_rectified in ("auto", "yes", "no"), "topics.image_rectified",
                 f"must be 'auto', 'yes' or 'no', got {self.image_rectified!r}")
        _require(len(self.camera_from_ecm) % 7 == 0, "topics.camera_from_ecm",
                 "must be x y z qx qy qz qw per camera (a multiple of 7 numbers)")
        for key in ("image", "camera_info"):
            _require(
                "{camera}" in getattr(self, key), f"topics.{key}", "needs a {camera} placeholder"
            )
        for key in ("camera_pose", "world_frame"):
            _require(bool(getattr(self, key)), f"topics.{key}", "must not be empty")


@dataclass(frozen=True)
class IngestConfig:
    """Time synchronisation and validation of the log."""

    sync_tolerance_ms: float = _doc(15.0, "images within this of each other form one frame (ms)",
        bounds=(0, 1e4))
    pose_gap_ms: float = _doc(
        100.0, "largest tracker/robot gap bridged by interpolation (ms); beyond: camera unusable",
        bounds=(0, 6e4)
    )
    time_source: str = _doc("header", "'header' (message stamp, else log_time) or 'log_time'")
    start_s: float = _doc(
        0.0, "keep the frames from this many seconds after the log's first frame (a part of a "
        "long recording)", bounds=(0, 1e7))
    duration_s: float = _doc(0.0, "keep this many seconds of frames from start_s (0: to the end)",
        bounds=(0, 1e7))
    every: int = _doc(1, "keep every N-th frame of those (a 30 Hz log at 10 Hz: 3)",
        bounds=(1, 1_000_000))

    def __post_init__(self) -> None:
        _require(self.sync_tolerance_ms > 0, "ingest.sync_tolerance_ms", "must be > 0")
        _require(self.pose_gap_ms > 0, "ingest.pose_gap_ms", "must be > 0")
        _require(
            self.time_source in ("header", "log_time"),
            "ingest.time_source",
            f"must be 'header' or 'log_time', got {self.time_source!r}",
        )
        check_bounds(self, "ingest")


def _is_number(word: str) -> bool:
    try:
        value = float(word)
    except ValueError:
        return False
    return math.isfinite(value)


@dataclass(frozen=True)
class ToolConfig:
    """Tool model: a shaft cylinder from the tip along the tool frame's +z axis (`shaft_axis`),
    and a jaw/wrist part beyond the frame (core/geometry/tool.py)."""

    shaft_radius_m: float = _doc(0.004, "shaft radius (m)", bounds=(0, 0.1))
    shaft_length_m: float = _doc(0.15, "shaft length from the tip (m)", bounds=(0, 2))
    shaft_axis: str = _doc(
        "+z", "axis of the tool frame pointing from the kinematic point up the shaft: +z, -z, "
        "+x, -x, +y or -y (-z for a frame whose z points out of the jaws)")
    jaw_offset_m: float = _doc(
        0.0, "start of the jaw/wrist part beyond the kinematic point, along the tool axis "
        "away from the shaft (m)", bounds=(0, 0.5))
    jaw_length_m: float = _doc(0.0, "length of the jaw/wrist part (m); 0 = none",
                               bounds=(0, 0.5))
    jaw_width_m: float = _doc(0.01, "width of the jaw/wrist part (m)", bounds=(0, 0.2))
    base_to_world: tuple[float, ...] = _doc(
        (), "robot base pose in the world: [x y z qx qy qz qw] (m); empty = tool pose is in world",
        bounds=(-1000.0, 1000.0)
    )
    mask_margin_px: float = _doc(6.0, "tool mask dilation in the images (px)", bounds=(0, 500))
    margin_m: float = _doc(
        0.0015, "3D points closer than radius + margin to the shaft axis are dropped (m)",
        bounds=(0, 0.1)
    )
    camera_offsets: tuple[str, ...] = _doc(
        (), "per camera, the tool's translation as that camera sees it (its hand-eye error): "
        "[\"CAMERA X Y Z\", ...] in the world (m); empty = none")

    def __post_init__(self) -> None:
        for entry in self.camera_offsets:
            words = entry.split()
            _require(len(words) == 4 and all(_is_number(w) and abs(float(w)) <= 10
                                             for w in words[1:]),
                     "tool.camera_offsets", f"expected \"CAMERA X Y Z\", got {entry!r}")
        _require(self.shaft_radius_m > 0, "tool.shaft_radius_m", "must be > 0")
        _require(self.shaft_length_m > 0, "tool.shaft_length_m", "must be > 0")
        _require(
            len(self.base_to_world) in (0, 7),
            "tool.base_to_world",
            "must be empty or [x, y, z, qx, qy, qz, qw]",
        )
        _require(self.mask_margin_px >= 0 and self.margin_m >= 0, "tool.margin_m", "must be >= 0")
        _require(self.shaft_axis in ("+z", "-z", "+x", "-x", "+y", "-y"), "tool.shaft_axis",
                 "must be one of +z -z +x -x +y -y")
        _require(self.jaw_offset_m >= 0 and self.jaw_length_m >= 0 and self.jaw_width_m > 0,
                 "tool.jaw_length_m", "jaw offset and length must be >= 0, width > 0")
        check_bounds(self, "tool")


@dataclass(frozen=True)
class ExtraToolConfig(ToolConfig):
    """One more tool (a `[[tools]]` table; e.g. a dVRK's second arm): its pose topic and
    geometry, masked and removed like the `[tool]` (`topics.tool_pose`) one."""

    pose: str = _doc("", "this tool's pose topic (PoseStamped / TransformStamped, or a "
                     "transforms topic with `frame`)")
    frame: str = _doc("", "this tool's TF child frame, when `pose` carries transforms")

    def __post_init__(self) -> None:
        super().__post_init__()
        _require(bool(self.pose), "tools.pose", "every [[tools]] table needs a pose topic")


@dataclass(frozen=True)
class TemplateConfig:
    """Template building: features, camera grouping / pair sequencing, triangulation."""

    max_features: int = _doc(6000, "SIFT keypoints per image", bounds=(1, 200_000))
    contrast_threshold: float = _doc(
        0.008, "SIFT contrast threshold (OpenCV default 0.04; tissue is low-contrast)",
        bounds=(0, 1)
    )
    min_features: int = _doc(
        2000, "images where SIFT finds fewer keypoints get Shi-Tomasi corners (upright SIFT "
        "descriptors) up to this many features: small or low-texture images (0: off)",
        bounds=(0, 200_000))
    detect_width_px: int = _doc(
        1280, "wider images: SIFT on the image scaled to this width (0: off)", bounds=(0, 9999)
    )
    ratio: float = _doc(
        0.9, "Lowe ratio test (against the runner-up inside or outside the epipolar segment)",
        bounds=(0, 1)
    )
    epipolar_px: float = _doc(2.0, "largest distance of a match to its epipolar line (px)",
        bounds=(0, 1000))
    refine_matches: bool = _doc(
        True, "re-locate each view of a match from a camera close to its first view's "
        "(baseline <= 0.18 x depth: a stereo endoscope) by the target's KLT (its window, no "
        "pyramid) from the first view's patch, to a tenth of a pixel instead of each "
        "keypoint's own error (moves of at most epipolar_px; a view KLT cannot follow is "
        "dropped)")
    max_reprojection_px: float = _doc(
        1.5, "largest reprojection error of a triangulated point (px)", bounds=(0, 1000)
    )
    min_angle_deg: float = _doc(
        1.0, "smallest triangulation angle between two rays (deg); a floor against degenerate "
        "rays only: depth accuracy decides through max_sigma_mm", bounds=(0, 90))
    max_sigma_mm: float = _doc(
        2.0, "largest 3D position uncertainty (RMS, from the measured pixel noise and the "
        "camera geometry) of a template point (mm)", bounds=(0, 1000))
    min_pair_matches: int = _doc(
        15, "verified matches for two cameras to be linked, at least (the floor; the minimum "
        "grows with the features: min_pair_match_fraction)", bounds=(0, 100_000))
    min_pair_match_fraction: float = _doc(
        0.01, "verified matches for two cameras to be linked, as a fraction of the features "
        "of the poorer image (when above min_pair_matches)", bounds=(0, 1))
    match_all_pairs: bool = _doc(
        True, "match every candidate camera pair; false: only a spanning tree of pairs, each "
        "camera also matched to the growing template by projection (a third of the pairs, "
        "about 2/3 of the points)")
    min_view_overlap: float = _doc(0.15, "predicted shared-view fraction to try matching a pair",
        bounds=(0, 1))
    depth_range: tuple[float, ...] = _doc(
        (0.4, 2.5), "matches must triangulate within [near, far] x the camera's working depth",
        bounds=(0, 1000)
    )
    working_distance_m: float = _doc(
        0.05, "scene depth (m) assumed for a camera whose optical axis meets no other's",
        bounds=(0, 10)
    )

    def __post_init__(self) -> None:
        _require(self.max_features > 0, "template.max_features", "must be > 0")
        _require(0 < self.ratio < 1, "template.ratio", "must be in (0, 1)")
        _require(self.epipolar_px > 0, "template.epipolar_px", "must be > 0")
        _require(self.max_reprojection_px > 0, "template.max_reprojection_px", "must be > 0")
        _require(0 <= self.min_angle_deg < 90, "template.min_angle_deg", "must be in [0, 90)")
        _require(self.max_sigma_mm > 0, "template.max_sigma_mm", "must be > 0")
        _require(self.min_pair_matches >= 1, "template.min_pair_matches", "must be >= 1")
        _require(0 <= self.min_pair_match_fraction < 1, "template.min_pair_match_fraction",
                 "must be in [0, 1)")
        _require(
            len(self.depth_range) == 2 and 0 < self.depth_range[0] < self.depth_range[1],
            "template.depth_range",
            "must be [near, far] with 0 < near < far",
        )
        _require(self.working_distance_m > 0, "template.working_distance_m", "must be > 0")
        check_bounds(self, "template")


@dataclass(frozen=True)
class TargetConfig:
    """Target cloud: tracking template points into new images, reprojection-error check."""

    significance: float = _doc(
        0.001, "reprojection-error check: a noise-only residual fails the chi-square gate with "
        "this probability (the gate is in units of the measured noise, not pixels)",
        bounds=(0, 0.5))
    klt_window_px: int = _doc(21, "KLT window size (px)", bounds=(5, 255))
    klt_levels: int = _doc(
        3, "deepest KLT pyramid (levels above the image); a frame uses the depth its "
        "measured motion needs, retrying failed tracks at this depth", bounds=(0, 10))
    klt_fb_px: float = _doc(0.7, "largest forward-backward KLT disagreement (px)", bounds=(0, 1000))
    min_ncc: float = _doc(
        0.5, "smallest normalised cross-correlation of a tracked patch with the one it left "
        "(photometric check against gross drift; median 0.96 on the sample; -1 = off)",
        bounds=(-1, 1))
    occlusion_depth_m: float = _doc(0.002, "depth tolerance of the visibility test (m)",
        bounds=(0, 1))
    new_points_every: int = _doc(
        0, "triangulate new features into G (no id) every N frames (0 = off; ~3 s a frame)",
        bounds=(0, 1_000_000)
    )
    new_point_spacing_mm: float = _doc(
        1.0, "a new point closer than this to a tracked template point is not added (mm)",
        bounds=(0, 1000)
    )

    def __post_init__(self) -> None:
        _require(0 < self.significance < 0.5, "target.significance", "must be in (0, 0.5)")
        _require(self.new_points_every >= 0, "target.new_points_every", "must be >= 0")
        _require(self.klt_window_px >= 5, "target.klt_window_px", "must be >= 5")
        _require(-1 <= self.min_ncc < 1, "target.min_ncc", "must be in [-1, 1)")
        check_bounds(self, "target")


@dataclass(frozen=True)
class ClassifyConfig:
    """Point classification (mm); thresholds are ours, see core/classify/rules.py for the
    reasoning."""

    static_mm: float = _doc(
        1.0, "motion tolerance: a displacement below this (or below what the noise explains) "
        "is static (mm; the spec's rule: 1.0)", bounds=(0, 1000)
    )
    significance: float = _doc(
        0.01, "false-alarm probability of the noise tests (moved beyond the noise; departure "
        "from one rigid motion beyond the noise): the main knob", bounds=(0, 0.5)
    )
    max_sigma_mm: float = _doc(
        1.0, "a point whose displacement from frame 0 is less certain than this (RMS, mm; "
        "the template's own error, which tracking carries into later measurements, cancels) "
        "is unknown, unless it moved beyond that uncertainty (default: the clinical 1 mm "
        "accuracy requirement)", bounds=(0, 1000)
    )
    status_band_mm: float = _doc(
        0.0, "within this of static_mm the reprojection check decides: intra-camera inlier "
        "static, inter-camera inlier dynamic (mm; 0 = displacement only)", bounds=(0, 1000)
    )
    measure: str = _doc(
        "rigid_rms", "shifting/deforming measure: 'rigid_rms' (RMS of the neighbourhood's best "
        "rigid fit to its registered positions) or 'transform_diff' (|(T_j - T_i) p_i|)"
    )
    deform_mm: float = _doc(
        0.25, "deformation tolerance: a significant departure from rigid motion whose "
        "registered rigid-fit RMS, each direction counted by how well it is measured, reaches this "
        "is deforming (mm; the spec's rule: 0.25)", bounds=(0, 1000)
    )
    neighbour_percentile: float = _doc(
        100.0, "transform_diff: percentile over the neighbours j (100 = max)", bounds=(0, 100)
    )
    neighbourhood_mm: float = _doc(5.0, "neighbours: template points within this at frame 0 (mm)",
        bounds=(0, 1000))
    min_neighbours: int = _doc(6, "fewer neighbours inside the radius: take this many nearest",
        bounds=(2, 1024))
    max_neighbours: int = _doc(128, "at most this many nearest neighbours inside the radius",
        bounds=(2, 4096))
    hysteresis_frames: int = _doc(
        0, "a label run shorter than this many frames is undone (0 = off)", bounds=(0, 1_000_000)
    )

    def __post_init__(self) -> None:
        key = "classify."
        for name in ("static_mm", "deform_mm", "neighbourhood_mm"):
            _require(getattr(self, name) > 0, key + name, "must be > 0")
        _require(0 < self.significance < 0.5, key + "significance", "must be in (0, 0.5)")
        _require(self.max_sigma_mm > 0, key + "max_sigma_mm", "must be > 0")
        _require(0 <= self.status_band_mm < self.static_mm, key + "status_band_mm",
                 "must be in [0, static_mm)")
        _require(self.measure in ("rigid_rms", "transform_diff"), key + "measure",
                 f"must be 'rigid_rms' or 'transform_diff', got {self.measure!r}")
        _require(0 < self.neighbour_percentile <= 100, key + "neighbour_percentile",
                 "must be in (0, 100]")
        _require(self.min_neighbours >= 2, key + "min_neighbours", "must be >= 2")
        _require(self.max_neighbours >= self.min_neighbours, key + "max_neighbours",
                 "must be >= min_neighbours")
        _require(self.hysteresis_frames >= 0, key + "hysteresis_frames", "must be >= 0")
        check_bounds(self, "classify")


@dataclass(frozen=True)
class LabelsConfig:
    """The spec's ground-truth label rule (section 6), shared by simulator and scoring."""

    static_mm: float = _doc(1.0, "a vertex that moved less than this is static (mm)",
        bounds=(0, 1000))
    neighbourhood_mm: float = _doc(5.0, "neighbourhood radius at frame 0 (mm)", bounds=(0, 1000))
    rigid_rms_mm: float = _doc(
        0.25, "RMS residual of the best rigid fit above this: deforming (mm)", bounds=(0, 1000)
    )

    def __post_init__(self) -> None:
        for key in ("static_mm", "neighbourhood_mm", "rigid_rms_mm"):
            _require(getattr(self, key) > 0, f"labels.{key}", "must be > 0")
        check_bounds(self, "labels")


@dataclass(frozen=True)
class RunConfig:
    """Where the stages' tasks (per camera, camera pair, frame and report figure) run
    (surgrecon_cli/executors); outputs do not depend on it."""

    executor: str = _doc("serial", "'serial', 'processes' (local worker pool) or 'dask'")
    workers: int = _doc(
        0, "worker processes for 'processes' or a Dask LocalCluster (0 = one per core)",
        bounds=(0, 1024))
    scheduler: str = _doc("", "Dask scheduler address, e.g. tcp://host:8786 (empty = LocalCluster)")
    retries: int = _doc(2, "Dask: reruns of a failed or lost task", bounds=(0, 100))

    def __post_init__(self) -> None:
        _require(self.executor in ("serial", "processes", "dask"), "run.executor",
                 f"must be 'serial', 'processes' or 'dask', got {self.executor!r}")
        _require(self.workers >= 0, "run.workers", "must be >= 0")
        _require(self.retries >= 0, "run.retries", "must be >= 0")
        _require(not self.scheduler or self.executor == "dask", "run.scheduler",
                 f"a scheduler address needs run.executor = 'dask', not {self.executor!r}")
        check_bounds(self, "run")


# [deformation]: tool-tissue contact and indentation measured from the reconstruction
# (core/measure/deformation.py explains every quantity).
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
        "sigma of the frame's points (the median; 1D sigma along the surface normal); once in "
        "contact, a release needs it beyond this many sigma of that median point extrapolated "
        "(registration.extrapolation_growth) as far as the nearest point is from data",
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


@dataclass(frozen=True)
class Config:
    """The whole configuration; one attribute per TOML section."""

    topics: TopicsConfig = field(default_factory=TopicsConfig)
    ingest: IngestConfig = field(default_factory=IngestConfig)
    tool: ToolConfig = field(default_factory=ToolConfig)
    template: TemplateConfig = field(default_factory=TemplateConfig)
    target: TargetConfig = field(default_factory=TargetConfig)
    registration: RegistrationConfig = field(default_factory=RegistrationConfig)
    classify: ClassifyConfig = field(default_factory=ClassifyConfig)
    deformation: DeformationConfig = field(default_factory=DeformationConfig)
    labels: LabelsConfig = field(default_factory=LabelsConfig)
    run: RunConfig = field(default_factory=RunConfig)
    tools: tuple[ExtraToolConfig, ...] = ()

    def tool_configs(self) -> tuple[ToolConfig, ...]:
        """Every tool's geometry: `[tool]`, then each `[[tools]]` (as tool poses stack)."""
        return (self.tool, *self.tools)
