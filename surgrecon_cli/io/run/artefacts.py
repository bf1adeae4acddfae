"""Typed readers and writers of the run folder's artefacts (paths: io/run/layout.py).

One dataclass per artefact: the template cloud, its observations, one registered frame,
the labels, the contact and indentation measures. Writers are atomic; readers check shapes
against the template and fail in one line naming the file and the stage to re-run.
"""

from __future__ import annotations

import json
import os
from dataclasses import MISSING, dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np

from ...core.classify.labels import STATIC
from ...core.measure.indentation import (
    SERIES_KEYS,
    Deformation,
    DeformationField,
    DeformationSeries,
)
from ...errors import RunFolderError
from .atomic import write_json, write_npz
from .layout import RunLayout
from .ply import read_ply, write_cloud_ply


def _load_npz(path: Path | str, stage: str, what: str) -> dict[str, np.ndarray]:
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except FileNotFoundError as exc:
        raise RunFolderError(f"{path}: {what} missing; run `surgrecon {stage}` on the run "
                             "folder") from exc
    except (OSError, ValueError) as exc:
        raise RunFolderError(f"{path}: unreadable ({exc}); re-run {stage}") from exc


def _check_shapes(path: Path | str, data: dict[str, np.ndarray], shapes: dict[str, tuple[int, ...]],
                  stage: str) -> None:
    for key, shape in shapes.items():
        if key not in data or data[key].shape != shape:
            got = data[key].shape if key in data else "missing"
            raise RunFolderError(f"{path}: {key} should be {shape}, got {got}; re-run {stage}")


def read_json(path: Path, stage: str) -> dict[str, Any]:
    """A JSON object written by `stage`; RunFolderError if missing or unreadable."""
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError as exc:
        raise RunFolderError(f"{path}: missing; run `surgrecon {stage}` first") from exc
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise RunFolderError(f"{path}: unreadable ({exc}); re-run {stage}") from exc
    if not isinstance(data, dict):
        raise RunFolderError(f"{path}: not a JSON object; re-run {stage}")
    return data


# ------------------------------------------------------------------------------ template
@dataclass(frozen=True)
class TemplateCloud:
    """The template P: points (N, 3) m, rgb (N, 3) uint8, n_views (N,) cameras that saw
    the point, reprojection_px (N,) RMS, sigma (N,) m RMS 3D position uncertainty."""

    points: np.ndarray
    rgb: np.ndarray
    n_views: np.ndarray
    reprojection_px: np.ndarray
    sigma: np.ndarray

    def extra(self) -> dict[str, np.ndarray]:
        """The per-point properties written beside position, colour and label."""
        return {"n_views": self.n_views.astype(np.uint8),
                "reprojection_px": self.reprojection_px.astype(np.float32),
                "sigma": self.sigma.astype(np.float32)}


def write_template(layout: RunLayout, cloud: TemplateCloud) -> None:
    n = len(cloud.points)
    write_cloud_ply(layout.template_ply, cloud.points, rgb=cloud.rgb,
                    point_id=np.arange(n, dtype=np.int32), label=np.full(n, STATIC, np.uint8),
                    residual=np.full(n, np.nan, np.float32), extra=cloud.extra())


def read_template(layout: RunLayout) -> TemplateCloud:
    """The template, ordered by point_id."""
    path = layout.template_ply
    if not path.is_file():
        raise RunFolderError(f"{path}: missing; run `surgrecon build-template "
                             f"{layout.root}` first")
    cloud = read_ply(path)
    order = np.argsort(cloud["point_id"])
    n = len(order)

    def column(name: str, default: float) -> np.ndarray:
        return cloud[name][order].astype(float) if name in cloud else np.full(n, default)

    return TemplateCloud(
        points=np.column_stack([cloud["x"], cloud["y"], cloud["z"]]).astype(float)[order],
        rgb=np.column_stack([cloud["red"], cloud["green"], cloud["blue"]]).astype(
            np.uint8)[order],
        n_views=column("n_views", 0).astype(np.int64),
        reprojection_px=column("reprojection_px", np.nan), sigma=column("sigma", np.nan))


@dataclass(frozen=True)
class TemplateObservations:
    """Where each template point was seen at frame 0 and how well it is known.

    point (M,), camera (M,) index pairs with pixels (M, 2) px; covariance (N, 3, 3) m² from
    image noise; pose_covariance (N, 3, 3) m² from the cameras' pose errors (including a
    shared tracker body's rigid error); pixel_noise_px the run's measured pixel noise."""

    point: np.ndarray
    camera: np.ndarray
    pixels: np.ndarray
    covariance: np.ndarray
    pose_covariance: np.ndarray
    pixel_noise_px: float

    def pixels_by_camera(self, n_points: int, n_cams: int) -> np.ndarray:
        """(N, C, 2) px, NaN where the camera did not see the point."""
        out = np.full((n_points, n_cams, 2), np.nan)
        out[self.point, self.camera] = self.pixels
        return out

    @property
    def total_covariance(self) -> np.ndarray:
        """(N, 3, 3) m²: image and pose errors."""
        return self.covariance + self.pose_covariance


def write_observations(layout: RunLayout, obs: TemplateObservations) -> None:
    write_npz(layout.observations, point=obs.point.astype(np.int32),
              camera=obs.camera.astype(np.int16), pixels=obs.pixels.astype(np.float32),
              covariance=obs.covariance.astype(np.float64),
              pose_covariance=obs.pose_covariance.astype(np.float64),
              pixel_noise_px=np.float64(obs.pixel_noise_px))


def read_observations(layout: RunLayout, n_points: int) -> TemplateObservations:
    path = layout.observations
    z = _load_npz(path, "build-template", "template observations")
    _check_shapes(path, z, {"covariance": (n_points, 3, 3),
                            "pose_covariance": (n_points, 3, 3)}, "build-template")
    return TemplateObservations(z["point"].astype(np.int64), z["camera"].astype(np.int64),
                                z["pixels"].astype(float), z["covariance"].astype(float),
                                z["pose_covariance"].astype(float), float(z["pixel_noise_px"]))


# -------------------------------------------------------------------------- registration
@dataclass(frozen=True)
class FrameRegistration:
    """One registered frame k >= 1 (RUN/registration/FFFFFF.npz), N template points, C cameras.

    transforms (N, 3, 4) per-point affines from the template; registered (N, 3) m (NaN
    when the frame failed); target (N, 3) m (NaN without one); status (N,) reprojection
    check; views (N,) cameras behind the target; residual (N,) m to the target (NaN
    without one); sigma (N,) m RMS uncertainty of the registered position; target_sigma
    (N,) m; target_covariance (N, 3, 3) m² from image noise; target_pose_covariance
    (N, 3, 3) m² from pose errors; support_mm (N,) distance to the nearest point with
    data; pixels (N, C, 2) tracked positions; tracking_px the frame's tracking noise, of
    which tracking_shared_px is common to a point's views (0 in files written without it);
    base the frame it was tracked and registered from; converged, failed, error say how
    the solve went; seconds_* its timings; new_points, contact_points its counts.
    """

    transforms: np.ndarray
    registered: np.ndarray
    target: np.ndarray
    status: np.ndarray
    views: np.ndarray
    residual: np.ndarray
    sigma: np.ndarray
    target_sigma: np.ndarray
    target_covariance: np.ndarray
    target_pose_covariance: np.ndarray
    support_mm: np.ndarray
    pixels: np.ndarray
    tracking_px: float
    base: int
    converged: bool
    failed: bool
    error: str
    seconds_target: float
    seconds_register: float
    new_points: int
    contact_points: int
    tracking_shared_px: float = 0.0

    @property
    def has_target(self) -> np.ndarray:
        """(N,) bool: the reprojection check gave the point a measured position."""
        return np.isfinite(self.target_sigma) & np.isfinite(self.target).all(1)


_SCALARS = {"float": float, "int": int, "bool": bool, "str": str}
_FLOAT32 = ("transforms", "residual", "sigma", "target_sigma", "target_covariance",
            "target_pose_covariance", "support_mm")


def write_registration(layout: RunLayout, frame: int, reg: FrameRegistration) -> None:
    arrays: dict[str, Any] = {}
    for f in fields(reg):
        value = getattr(reg, f.name)
        if f.name in _FLOAT32:
            value = np.asarray(value, np.float32)
        elif f.name == "error":
            value = np.array(value)
        elif f.name in ("status", "views"):
            value = np.asarray(value, np.uint8)
        arrays[f.name] = value
    write_npz(layout.registration_file(frame), **arrays)


def read_registration(layout: RunLayout, frame: int, n_points: int) -> FrameRegistration:
    """One registered frame; RunFolderError if missing or not of the N-point template."""
    path = layout.registration_file(frame)
    z = _load_npz(path, "register", f"frame {frame} is not registered:")
    n = n_points
    _check_shapes(path, z, {"registered": (n, 3), "transforms": (n, 3, 4), "status": (n,),
                            "sigma": (n,), "target": (n, 3), "target_sigma": (n,),
                            "target_covariance": (n, 3, 3),
                            "target_pose_covariance": (n, 3, 3)}, "register")
    kinds = {f.name: f.type for f in fields(FrameRegistration)}
    optional = {f.name for f in fields(FrameRegistration) if f.default is not MISSING}
    missing = [k for k in kinds if k not in z and k not in optional]
    if missing:
        raise RunFolderError(f"{path}: no {', '.join(missing)} (written by an older "
                             "surgrecon?); re-run register")
    values: dict[str, Any] = {}
    for key, kind in kinds.items():
        cast = _SCALARS.get(str(kind))
        if key in z:
            values[key] = cast(z[key].item()) if cast else z[key]
    return FrameRegistration(**values)


# ------------------------------------------------------------------------------- labels
@dataclass(frozen=True)
class FrameLabels:
    """Labels of every frame (T, N): labels after hysteresis, raw_labels before it,
    displacement_mm and deformation_mm (the measures behind them), floor_mm (the rigid-fit
    RMS a bend along the lines of sight needs to be labelled deforming; NaN at frame 0,
    where points are unknown, and in runs classified before it was stored), status
    (reprojection check; frame 0: intra)."""

    labels: np.ndarray
    raw_labels: np.ndarray
    displacement_mm: np.ndarray
    deformation_mm: np.ndarray
    floor_mm: np.ndarray
    status: np.ndarray


def write_labels(layout: RunLayout, labels: FrameLabels) -> None:
    write_npz(layout.labels, labels=labels.labels.astype(np.uint8),
              raw_labels=labels.raw_labels.astype(np.uint8),
              displacement_mm=labels.displacement_mm.astype(np.float32),
              deformation_mm=labels.deformation_mm.astype(np.float32),
              floor_mm=labels.floor_mm.astype(np.float32),
              status=labels.status.astype(np.uint8))


def read_labels(layout: RunLayout, shape: tuple[int, int]) -> FrameLabels:
    """The labels of a classified run of `shape` (T, N)."""
    path = layout.labels
    z = _load_npz(path, "classify", "labels")
    _check_shapes(path, z, {k: shape for k in ("labels", "raw_labels", "displacement_mm",
                                               "deformation_mm", "status")}, "classify")
    if "floor_mm" in z:
        _check_shapes(path, z, {"floor_mm": shape}, "classify")
    floor = z["floor_mm"].astype(float) if "floor_mm" in z else np.full(shape, np.nan)
    return FrameLabels(z["labels"], z["raw_labels"], z["displacement_mm"].astype(float),
                       z["deformation_mm"].astype(float), floor, z["status"])


# ---------------------------------------------------------------------- deformation
_FIELD = ("inward_mm", "magnitude_mm", "sigma_mm", "deformed")


def read_deformation(layout: RunLayout, shape: tuple[int, int]) -> Deformation:
    """The measures of a run of `shape` (T frames, N template points)."""
    path = layout.deformation
    z = _load_npz(path, "measure", "contact and indentation measures")
    _check_shapes(path, z, {**{k: shape[:1] for k in SERIES_KEYS},
                            **{k: shape for k in _FIELD}}, "measure")
    return Deformation(DeformationSeries(**{k: z[k] for k in SERIES_KEYS}),
                       DeformationField(**{k: z[k] for k in _FIELD}))


def read_deformation_summary(layout: RunLayout) -> dict[str, Any]:
    return read_json(layout.deformation_summary, "measure")


# ------------------------------------------------------------------------------- clouds
def write_frame_cloud(layout: RunLayout, frame: int, positions: np.ndarray, rgb: np.ndarray,
                      labels: np.ndarray, residual: np.ndarray,
                      extra: dict[str, np.ndarray]) -> None:
    """One frame's labelled cloud (N points by point_id), atomically; `residual` (N,) m is
    NaN where the point had no target."""
    n = len(positions)
    write_cloud_ply(layout.cloud_file(frame), positions, rgb=rgb,
                    point_id=np.arange(n, dtype=np.int32), label=labels.astype(np.uint8),
                    residual=np.asarray(residual, np.float32), extra=extra)


def read_frame_cloud(layout: RunLayout, frame: int) -> dict[str, np.ndarray]:
    """One frame's labelled cloud as written by `write_frame_cloud`: {property: (M,)} in
    point_id order, M <= N (points without a finite position are not in the file)."""
    path = layout.cloud_file(frame)
    if not os.path.isfile(path):
        raise RunFolderError(f"{path}: missing; run `surgrecon classify {layout.root}` first")
    cloud = read_ply(path)
    if "point_id" not in cloud or "label" not in cloud:
        raise RunFolderError(f"{path}: no point_id or label property; re-run classify")
    return cloud


def write_template_summary(layout: RunLayout, summary: dict[str, Any]) -> None:
    write_json(layout.template_summary, summary)


def read_template_summary(layout: RunLayout) -> dict[str, Any] | None:
    """The template's counts and pair plan; None if build-template wrote none."""
    path = layout.template_summary
    return read_json(path, "build-template") if path.is_file() else None


# ---------------------------------------------------------------------------- evaluation
def read_evaluation(layout: RunLayout) -> dict[str, Any] | None:
    """The scores against ground truth; None if the run was not evaluated."""
    path = layout.evaluation_json
    return read_json(path, "evaluate") if path.is_file() else None


def read_evaluation_errors(layout: RunLayout) -> dict[str, np.ndarray] | None:
    """The per-point errors behind the scores (template_error_mm (N,), on_tool (N,) bool,
    registration_error_mm (T, N), true_labels (T, N)); None if not written."""
    path = layout.evaluation_errors
    return _load_npz(path, "evaluate", "evaluation errors") if path.is_file() else None
