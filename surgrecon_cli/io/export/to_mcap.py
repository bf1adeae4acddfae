"""`surgrecon export RUN --mcap OUT.mcap`: a classified run as an MCAP file Foxglove opens.

Every message is stamped (log time, publish time and its own timestamp) with the frame's
time in the source log (RUN/ingest/frames.npz `stamps_ns`). Per frame k:

  /surgrecon/cloud          foxglove.PointCloud  the labelled cloud RUN/clouds/k.ply in the
                            world: x y z (float32 m, the PLY's values), red green blue alpha
                            (uint8, by class), point_id (int32), label (uint8), residual
                            (float32 m, NaN = no target), sigma (float32 m), deform_floor
                            (float32 m, frames >= 1), displacement_mm (float32), then
                            status / views (frames >= 1) or n_views / reprojection_px
                            (frame 0)
  /surgrecon/target         foxglove.PointCloud  the measured targets (frame 0: the template)
  /surgrecon/tf             foxglove.FrameTransforms  world -> camera_CC, world -> tool (and
                                                      tool_1, ... for `[[tools]]`)
  /surgrecon/scene          foxglove.SceneUpdate  camera frusta, each tool's shaft and jaw
  /surgrecon/frame_metrics  JSON  the frame's row of RUN/metrics/frames.csv
  /surgrecon/deformation    JSON  the frame's contact and indentation measures (a row of
                            RUN/metrics/deformation.csv; when `measure` is done, and then
                            the cloud also carries inward_mm (float32, the compensated
                            displacement into the tissue) and deformed (uint8))
  /cameras/CC/image         foxglove.CompressedImage  the image as recorded (JPEG / PNG);
                            for a video camera foxglove.CompressedVideo: its H.264 / H.265
                            packets as recorded (RUN/ingest/video/CC.npz), not re-encoded
  /cameras/CC/calibration   foxglove.CameraCalibration
  /cameras/CC/annotations   foxglove.ImageAnnotations  the cloud's points projected, by class

and once, at frame 0, /surgrecon/template_cloud (foxglove.PointCloud: the template in its
colours). CC is the camera's index in the sorted id list; the metadata record `surgrecon`
maps indices to ids. The shipped Foxglove layout is written beside the file
(OUT.layout.json).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from ... import __version__
from ...config import Config, from_dict
from ...core.classify.labels import CLASS_NAMES, INTRA, UNKNOWN
from ...errors import RunFolderError
from ..run.artefacts import (
    read_deformation,
    read_frame_cloud,
    read_labels,
    read_registration,
    read_template,
)
from ..run.atomic import atomic_open, write_text
from ..run.folder import RunFolder
from ..run.ingest_store import IngestedLog, VideoPackets, load_ingested, load_video
from ..run.layout import RunLayout
from ..run.metrics import read_csv
from .foxglove_pack import point_cloud
from .foxglove_scene import (
    WORLD_FRAME,
    camera_calibration,
    class_colours,
    compressed_image,
    compressed_video,
    frame_transforms,
    image_annotations,
    projected_labels,
    scene_update,
)
from .mcap_out import McapOut

TOPIC_CLOUD = "/surgrecon/cloud"
TOPIC_TARGET = "/surgrecon/target"
TOPIC_TEMPLATE = "/surgrecon/template_cloud"
TOPIC_TF = "/surgrecon/tf"
TOPIC_SCENE = "/surgrecon/scene"
TOPIC_METRICS = "/surgrecon/frame_metrics"
TOPIC_DEFORMATION = "/surgrecon/deformation"
LAYOUT_RESOURCE = "foxglove_layout.json"
_TARGET_RGBA = (255, 190, 0, 255)


def camera_topic(index: int, kind: str) -> str:
    """/cameras/CC/{image, calibration, annotations}."""
    return f"/cameras/{index:02d}/{kind}"


def shipped_layout() -> str:
    """The Foxglove layout shipped with the package (JSON text)."""
    return resources.files("surgrecon_cli").joinpath(LAYOUT_RESOURCE).read_text("utf-8")


@dataclass(frozen=True)
class McapExport:
    """What `export_mcap` wrote: the file, its size, the layout beside it, the messages per
    topic and how long it took."""

    path: Path
    bytes: int
    layout: Path
    frames: int
    counts: dict[str, int]
    seconds: float


def export_mcap(run_dir: Path, out_path: Path,
                on_frame: Callable[[int, int], None] | None = None) -> McapExport:
    """Write the MCAP export of a classified run (atomically) and the layout beside it;
    `on_frame(done, total)` after each frame."""
    start = time.perf_counter()
    layout = RunLayout(run_dir)
    run = RunFolder(run_dir)
    recorded = run.read()
    run.require_done("classify")
    config = from_dict(recorded.get("config") or {}, Config())
    log = load_ingested(layout.ingest_dir)
    template = read_template(layout)
    n, n_frames = len(template.points), log.n_frames
    labels = read_labels(layout, (n_frames, n))
    displacement = labels.displacement_mm
    metrics = _frame_metrics(layout, log, labels.labels)
    schema = metrics_schema(metrics)
    measured = read_deformation(layout, (n_frames, n)) if run.is_done("measure") else None
    measures = [] if measured is None else [{k: v for k, v in row.items() if v is not None}
                                            for row in measured.series.rows()]
    measures_schema = {**metrics_schema(measures), "title": "surgrecon.Deformation",
                       "description": "One frame's tool-tissue contact and indentation "
                       "(core/measure/indentation.py; mm, mm², mm³, N; force_n a model output)"}
    videos = {c: VideoPassThrough(log, c, video) for c in range(len(log.cameras))
              if (video := load_video(log.root, c)) is not None}
    out_path = Path(out_path)
    with atomic_open(out_path, "wb") as stream:
        out = McapOut(stream)
        out.metadata("surgrecon", {
            "version": __version__, "run": str(layout.root.resolve()),
            "source_log": str(recorded.get("input", {}).get("path", "")),
            **{f"camera_{c:02d}": cam for c, cam in enumerate(log.cameras)}})
        stamp0 = int(log.stamps_ns[0])
        out.protobuf(TOPIC_TEMPLATE, point_cloud(stamp0, WORLD_FRAME, [
            *_xyz(template.points), *_rgba(template.rgb),
            ("point_id", "<i4", np.arange(n)), ("n_views", "u1", template.n_views),
            ("sigma", "<f4", template.sigma),
            ("reprojection_px", "<f4", template.reprojection_px)]), stamp0)
        for k in range(n_frames):
            extra = [] if measured is None else [
                ("inward_mm", "<f4", measured.field.inward_mm[k]),
                ("deformed", "u1", measured.field.deformed[k].astype(np.uint8))]
            _write_frame(out, layout, log, config, k, n, displacement[k], (metrics[k], schema),
                         extra, videos)
            if measured is not None:
                stamp = int(log.stamps_ns[k])
                out.json(TOPIC_DEFORMATION, "surgrecon.Deformation", measures_schema,
                         measures[k], stamp)
            if on_frame:
                on_frame(k + 1, n_frames)
        out.finish()
        counts = dict(out.counts)
    layout_path = RunLayout.foxglove_layout_beside(out_path)
    write_text(layout_path, shipped_layout())
    return McapExport(out_path, out_path.stat().st_size, layout_path, n_frames, counts,
                      time.perf_counter() - start)


def _xyz(points: np.ndarray) -> list[tuple[str, str, np.ndarray]]:
    return [(axis, "<f4", points[:, i]) for i, axis in enumerate("xyz")]


def _rgba(rgb: np.ndarray) -> list[tuple[str, str, np.ndarray]]:
    """red green blue alpha (uint8) of rgb (M, 3) or rgba (M, 4)."""
    alpha = rgb[:, 3] if rgb.shape[1] == 4 else np.full(len(rgb), 255, np.uint8)
    return [("red", "u1", rgb[:, 0]), ("green", "u1", rgb[:, 1]), ("blue", "u1", rgb[:, 2]),
            ("alpha", "u1", alpha)]


class VideoPassThrough:
    """A video camera's recorded packets, passed through to /cameras/CC/image as
    foxglove.CompressedVideo (no re-encoding): every packet up to a frame's image is
    written before that frame's annotations, the image's own packet stamped with the frame
    time (as the other messages of the frame), the ones between frames with their own."""

    def __init__(self, log: IngestedLog, c: int, video: VideoPackets) -> None:
        self.log, self.c, self.format = log, c, video.format
        self.packets = video.packets()
        self.sent = 0

    def up_to(self, out: McapOut, k: int) -> None:
        image_stamp = int(self.log.image_stamps_ns[k, self.c])
        frame_stamp = int(self.log.stamps_ns[k])
        while self.sent < len(self.packets) and self.packets[self.sent][0] <= image_stamp:
            own, data = self.packets[self.sent]
            stamp = frame_stamp if own == image_stamp else own
            out.protobuf(camera_topic(self.c, "image"),
                         compressed_video(stamp, self.c, data, self.format), stamp)
            self.sent += 1


def _write_frame(out: McapOut, layout: RunLayout, log: IngestedLog, config: Config, k: int,
                 n: int, displacement_mm: np.ndarray,
                 metrics: tuple[dict[str, Any], dict[str, Any]],
                 extra: list[tuple[str, str, np.ndarray]],
                 videos: dict[int, VideoPassThrough]) -> None:
    """All messages of frame k; metrics: the frame's metrics and their JSON Schema; extra:
    more per-point fields of the cloud (name, dtype, values (N,) by point_id); videos: the
    video cameras' packet streams by camera index."""
    stamp = int(log.stamps_ns[k])
    cloud = read_frame_cloud(layout, k)
    ids = cloud["point_id"].astype(np.int64)
    columns = [("x", "<f4", cloud["x"]), ("y", "<f4", cloud["y"]), ("z", "<f4", cloud["z"]),
               *_rgba(class_colours(cloud["label"])), ("point_id", "<i4", cloud["point_id"]),
               ("label", "u1", cloud["label"]), ("residual", "<f4", cloud["residual"])]
    columns += [(name, "<f4", cloud[name]) for name in ("sigma", "deform_floor")
                if name in cloud]
    columns.append(("displacement_mm", "<f4", displacement_mm[ids]))
    columns += [(name, dtype, values[ids]) for name, dtype, values in extra]
    columns += [(name, "u1", cloud[name]) for name in ("status", "views", "n_views")
                if name in cloud]
    if "reprojection_px" in cloud:
        columns.append(("reprojection_px", "<f4", cloud["reprojection_px"]))
    out.protobuf(TOPIC_CLOUD, point_cloud(stamp, WORLD_FRAME, columns), stamp)
    out.protobuf(TOPIC_TARGET, point_cloud(stamp, WORLD_FRAME, _target_columns(layout, k, n)),
                 stamp)

    poses = log.usable_poses(k)
    tools = log.all_tool_poses(k)
    out.protobuf(TOPIC_TF, frame_transforms(stamp, poses, tools), stamp)
    posed = np.isfinite(poses).all((1, 2))
    out.protobuf(TOPIC_SCENE, scene_update(
        stamp, log.models, posed, list(np.isfinite(tools).all((1, 2))), config.tool_configs(),
        config.template.working_distance_m), stamp)

    points = np.column_stack([cloud["x"], cloud["y"], cloud["z"]]).astype(float)
    for c, model in enumerate(log.models):
        rel = log.image_paths[k][c]
        if not rel:
            continue
        if c in videos:
            videos[c].up_to(out, k)
        else:
            image = log.root / rel
            try:
                data = image.read_bytes()
            except OSError as exc:
                raise RunFolderError(f"{image}: cannot read ({exc.strerror or exc}); re-run "
                                     "ingest") from exc
            out.protobuf(camera_topic(c, "image"),
                         compressed_image(stamp, c, data, image.suffix.lstrip(".")), stamp)
        out.protobuf(camera_topic(c, "calibration"), camera_calibration(stamp, c, model), stamp)
        uv = np.zeros((0, 2))
        labels = np.zeros(0, np.uint8)
        if posed[c]:
            uv, labels = projected_labels(points, cloud["label"], poses[c], model, tools,
                                          config.tool_configs())
        out.protobuf(camera_topic(c, "annotations"), image_annotations(stamp, uv, labels),
                     stamp)
    out.json(TOPIC_METRICS, "surgrecon.FrameMetrics", metrics[1], metrics[0], stamp)


def _target_columns(layout: RunLayout, k: int, n: int) -> list[tuple[str, str, np.ndarray]]:
    """Frame k's targets (the points with one): position, colour, point_id, status, views and
    target_sigma (m); at frame 0 the template (its sigma, status intra)."""
    if k == 0:
        template = read_template(layout)
        ids = np.arange(n)
        points, status = template.points, np.full(n, INTRA, np.uint8)
        views, sigma = template.n_views, template.sigma
    else:
        reg = read_registration(layout, k, n)
        ids = np.flatnonzero(reg.has_target)
        points, status = reg.target[ids], reg.status[ids]
        views, sigma = reg.views[ids], reg.target_sigma[ids]
    rgba = np.tile(np.array(_TARGET_RGBA, np.uint8), (len(ids), 1))
    return [*_xyz(points), *_rgba(rgba), ("point_id", "<i4", ids), ("status", "u1", status),
            ("views", "u1", views), ("target_sigma", "<f4", sigma)]


def metrics_schema(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """The JSON Schema of the metrics messages: every column any row has, typed by its
    values (number, boolean or string), so that Foxglove's plot panel offers
    /surgrecon/frame_metrics.<column>."""
    kinds: dict[str, set[str]] = {}
    for row in rows:
        for key, value in row.items():
            kind = ("boolean" if isinstance(value, bool) else
                    "number" if isinstance(value, int | float) else "string")
            kinds.setdefault(key, set()).add(kind)
    return {
        "title": "surgrecon.FrameMetrics",
        "description": "One frame's row of the run's per-frame metrics table (frames.csv; "
                       "lengths in mm where the name ends in _mm); cells without a value are "
                       "left out",
        "type": "object",
        "properties": {key: {"type": sorted(k)[0] if len(k) == 1 else sorted(k)}
                       for key, k in kinds.items()},
        "required": ["frame"],
    }


def _frame_metrics(layout: RunLayout, log: IngestedLog,
                   labels: np.ndarray) -> list[dict[str, Any]]:
    """frames.csv's rows if the report has been written; else the frame numbers, times and
    class counts of the labels (T, N)."""
    if layout.frames_csv.is_file():
        rows = read_csv(layout.frames_csv)
        if len(rows) == log.n_frames:
            return rows
    t0 = int(log.stamps_ns[0])
    rows = []
    for k in range(log.n_frames):
        row: dict[str, Any] = {"frame": k, "time_s": (int(log.stamps_ns[k]) - t0) * 1e-9}
        row.update({name: int((labels[k] == code).sum()) for code, name in CLASS_NAMES.items()})
        row["unknown"] = int((labels[k] == UNKNOWN).sum())
        rows.append(row)
    return rows
