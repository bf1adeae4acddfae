"""The Foxglove messages of a frame's cameras and tool: transforms, the tool's capsule and
the cameras' frusta, calibrations, images and image annotations.

Frames: `world` (the tracker's), `camera_CC` (optical: x right, y down, z forward; CC the
camera's index in the sorted id list) and each tool's (`core.geometry.tool.tool_name`:
`tool`, `tool_1`, ...; the kinematic frame, where core/geometry/tool.py's model of the
shaft and jaw is drawn).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.CompressedVideo_pb2 import CompressedVideo
from foxglove_schemas_protobuf.CylinderPrimitive_pb2 import CylinderPrimitive
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations
from foxglove_schemas_protobuf.LinePrimitive_pb2 import LinePrimitive
from foxglove_schemas_protobuf.Point3_pb2 import Point3
from foxglove_schemas_protobuf.SceneEntity_pb2 import SceneEntity
from foxglove_schemas_protobuf.SceneEntityDeletion_pb2 import SceneEntityDeletion
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from foxglove_schemas_protobuf.SpherePrimitive_pb2 import SpherePrimitive
from google.protobuf.timestamp_pb2 import Timestamp

from ...config import ToolConfig
from ...core.classify.labels import CLASS_COLOURS, CLASS_NAMES, UNKNOWN, rgba255
from ...core.geometry.cameras import CameraModel, in_image, project
from ...core.geometry.tool import ray_segment_distance, tool_capsules, tool_name
from .foxglove_pack import color, points_annotation, pose, quaternion, timestamp, vector3

WORLD_FRAME = "world"

CLASS_LABELS = {**CLASS_NAMES, UNKNOWN: "unknown"}
# Class colours (RGBA 0-255), those of the report's figures (core/classify/labels.py).
CLASS_RGBA = {code: rgba255(CLASS_COLOURS[name]) for code, name in CLASS_LABELS.items()}
ANNOTATION_STEP_PX = 1 / 16
_TOOL_RGBA = (0.75, 0.78, 0.82, 0.6)
_FRUSTUM_RGBA = (1.0, 0.8, 0.1, 1.0)
# Foxglove's distortion model names for ours.
_DISTORTION = {"plumb_bob": "plumb_bob", "rational_polynomial": "rational_polynomial",
               "equidistant": "kannala_brandt"}


def camera_frame(index: int) -> str:
    return f"camera_{index:02d}"


def class_colours(labels: np.ndarray) -> np.ndarray:
    """(N, 4) uint8 RGBA of labels (N,); codes without a colour get the unknown one."""
    table = np.tile(np.array(CLASS_RGBA[UNKNOWN], np.uint8), (256, 1))
    for code, rgba in CLASS_RGBA.items():
        table[code] = rgba
    return table[np.asarray(labels, np.uint8)]


def frame_transforms(stamp: int, camera_poses: np.ndarray, tool_poses: np.ndarray
                     ) -> FrameTransforms:
    """world -> camera_CC for every camera with a finite pose (C, 4, 4) camera-to-world, and
    world -> each tool's frame (`tool_name`) whose pose ((4, 4) or (K, 4, 4)) is finite."""
    children = [(camera_frame(c), p) for c, p in enumerate(camera_poses)]
    children += [(tool_name(k), p)
                 for k, p in enumerate(np.asarray(tool_poses, float).reshape(-1, 4, 4))]
    ts = timestamp(stamp)
    return FrameTransforms(transforms=[
        FrameTransform(timestamp=ts, parent_frame_id=WORLD_FRAME, child_frame_id=name,
                       translation=vector3(p[:3, 3]), rotation=quaternion(p))
        for name, p in children if np.isfinite(p).all()])


def _frustum(model: CameraModel, depth: float) -> LinePrimitive:
    """The edges of a camera's view pyramid to `depth` m (pinhole, distortion ignored)."""
    K = model.K
    corners = [((u - K[0, 2]) / K[0, 0] * depth, (v - K[1, 2]) / K[1, 1] * depth, depth)
               for u, v in ((0, 0), (model.width, 0), (model.width, model.height),
                            (0, model.height))]
    apex = (0.0, 0.0, 0.0)
    segments = [p for c in corners for p in (apex, c)]
    segments += [p for i in range(4) for p in (corners[i], corners[(i + 1) % 4])]
    return LinePrimitive(type=LinePrimitive.LINE_LIST, pose=pose(), thickness=1.5,
                         scale_invariant=True, color=color(_FRUSTUM_RGBA),
                         points=[Point3(x=x, y=y, z=z) for x, y, z in segments])


def _capsule(a: np.ndarray, b: np.ndarray, radius: float
             ) -> tuple[CylinderPrimitive, list[SpherePrimitive]]:
    """A capsule of `radius` m around the segment a-b (3,) m as a cylinder (its z axis along
    a -> b) and a sphere at each end."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    length = float(np.linalg.norm(b - a))
    z = (b - a) / length if length > 0 else np.array([0.0, 0.0, 1.0])
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    middle = np.eye(4)
    middle[:3, :3] = np.column_stack([x, np.cross(z, x), z])
    middle[:3, 3] = (a + b) / 2
    d = 2 * radius
    ends = []
    for centre in (a, b):
        at = np.eye(4)
        at[:3, 3] = centre
        ends.append(SpherePrimitive(pose=pose(at), size=vector3((d, d, d)),
                                    color=color(_TOOL_RGBA)))
    return (CylinderPrimitive(pose=pose(middle), size=vector3((d, d, length)), bottom_scale=1.0,
                              top_scale=1.0, color=color(_TOOL_RGBA)), ends)


def tool_entity(ts: Timestamp, index: int, tool: ToolConfig) -> SceneEntity:
    """Tool `index` (0 = `[tool]`, k = the k-th `[[tools]]`) in its own frame: one capsule
    per part of core/geometry/tool.py's model (the shaft, and the jaw/wrist part if it has one);
    cylinders and spheres in the parts' order, the spheres two a part (near end first)."""
    name = tool_name(index)
    cylinders, spheres = [], []
    for a, b, radius in tool_capsules(np.eye(4), tool):
        cylinder, ends = _capsule(a, b, radius)
        cylinders.append(cylinder)
        spheres += ends
    return SceneEntity(timestamp=ts, frame_id=name, id=name, frame_locked=True,
                       cylinders=cylinders, spheres=spheres)


def scene_update(stamp: int, models: Sequence[CameraModel], cameras_posed: np.ndarray,
                 tools_posed: Sequence[bool], tools: Sequence[ToolConfig],
                 frustum_depth_m: float) -> SceneUpdate:
    """Everything drawn anew: each posed camera's frustum (cameras_posed (C,) bool) and each
    posed tool (`Config.tool_configs()` order); entities are locked to their frames (they
    follow /tf)."""
    ts = timestamp(stamp)
    entities = [SceneEntity(timestamp=ts, frame_id=camera_frame(c), id=camera_frame(c),
                            frame_locked=True, lines=[_frustum(m, frustum_depth_m)])
                for c, m in enumerate(models) if cameras_posed[c]]
    entities += [tool_entity(ts, k, tool)
                 for k, (posed, tool) in enumerate(zip(tools_posed, tools, strict=True)) if posed]
    return SceneUpdate(deletions=[SceneEntityDeletion(timestamp=ts,
                                                      type=SceneEntityDeletion.ALL)],
                       entities=entities)


def camera_calibration(stamp: int, index: int, model: CameraModel) -> CameraCalibration:
    """The intrinsics of camera `index` (images as recorded: distorted, R = I, P = [K | 0])."""
    K = model.K
    P = np.zeros((3, 4))
    P[:, :3] = K
    return CameraCalibration(timestamp=timestamp(stamp), frame_id=camera_frame(index),
                             width=model.width, height=model.height,
                             distortion_model=_DISTORTION[model.model],
                             D=[float(v) for v in model.dist], K=[float(v) for v in K.ravel()],
                             R=[float(v) for v in np.eye(3).ravel()],
                             P=[float(v) for v in P.ravel()])


def compressed_image(stamp: int, index: int, data: bytes, extension: str) -> CompressedImage:
    """A stored image's bytes as recorded (`extension` jpg / jpeg / png / webp)."""
    fmt = {"jpg": "jpeg"}.get(extension.lower(), extension.lower())
    return CompressedImage(timestamp=timestamp(stamp), frame_id=camera_frame(index),
                           data=data, format=fmt)


def compressed_video(stamp: int, index: int, data: bytes, fmt: str) -> CompressedVideo:
    """One recorded video packet (an H.264 / H.265 access unit, Annex B) as is."""
    return CompressedVideo(timestamp=timestamp(stamp), frame_id=camera_frame(index),
                           data=data, format=fmt)


def projected_labels(points: np.ndarray, labels: np.ndarray, cam_to_world: np.ndarray,
                     model: CameraModel, tool_poses: np.ndarray | None = None,
                     tools: ToolConfig | Sequence[ToolConfig] | None = None
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (M, 2) and labels (M,) of the points (N, 3) m in front of the camera that
    project into its image and, given the tools' poses ((4, 4) or (K, 4, 4)) and models, are
    not behind a tool (the ray from the camera passes a capsule's axis, shaft or jaw, closer
    than its radius before the point)."""
    points = np.asarray(points, float)
    keep = np.isfinite(points).all(1)
    uv, z = project(points, cam_to_world, model)
    with np.errstate(invalid="ignore"):
        keep &= (z > 0) & np.isfinite(uv).all(1) & in_image(uv, model)
    capsules = [] if tools is None or tool_poses is None else tool_capsules(tool_poses, tools)
    if capsules and keep.any():
        origin = cam_to_world[:3, 3]
        rays = points[keep] - origin
        depth = np.linalg.norm(rays, axis=1)
        hidden = np.zeros(len(rays), bool)
        for a, b, radius in capsules:
            dist, along = ray_segment_distance(origin, rays / depth[:, None], a, b)
            hidden |= (dist < radius) & (along < depth)
        keep[np.flatnonzero(keep)[hidden]] = False
    return uv[keep], np.asarray(labels)[keep]


def image_annotations(stamp: int, uv: np.ndarray, labels: np.ndarray,
                      size_px: float = 4.0) -> ImageAnnotations:
    """One POINTS annotation per class present, in the class colours. Pixels are rounded to
    1/16 px (`ANNOTATION_STEP_PX`): doubles with few significant bits compress 3x better,
    and a 16th of a pixel is far below what a viewer can show."""
    uv = np.round(np.asarray(uv, float) / ANNOTATION_STEP_PX) * ANNOTATION_STEP_PX
    groups = []
    for code, rgba in CLASS_RGBA.items():
        sel = labels == code
        if sel.any():
            fill = tuple(v / 255 for v in rgba)
            groups.append(points_annotation(stamp, uv[sel], fill, (0, 0, 0, 0.6), size_px))
    return ImageAnnotations(timestamp=timestamp(stamp), points=groups)
