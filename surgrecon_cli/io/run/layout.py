"""Every path of a run folder, in one place: nothing else in the package spells a file name.

  RUN/run.json                   status of every stage (io/run/folder.py)
  RUN/config.toml                the effective config
  RUN/.surgrecon.lock            held (OS file lock) by the command working on the folder
  RUN/ingest/cameras.json        camera ids, intrinsics, ingest report (io/run/ingest_store.py)
  RUN/ingest/frames.npz          per-frame stamps, poses, tool poses, joints
  RUN/ingest/images/CC/FFFFFF.*  image of camera index CC at frame FFFFFF, as recorded
                                 (PNG, decoded, for a video camera)
  RUN/ingest/video/CC.npz        a video camera's H.264/H.265 packets as recorded (export)
  RUN/template.ply               the template cloud P (frame 0)
  RUN/template/observations.npz  where each template point was seen, its covariance
  RUN/template/summary.json      template counts and pair plan
  RUN/registration/FFFFFF.npz    one registered frame k >= 1 (io/artefacts.FrameRegistration)
  RUN/registration/progress.jsonl  the registered frames, one line each (io/run/folder.py)
  RUN/classify/labels.npz        labels (T, N) and the measures behind them
  RUN/classify/frames/FFFFFF.npz one classified frame before hysteresis (deleted when done)
  RUN/clouds/FFFFFF.ply          every frame's labelled cloud (written once, by classify)
  RUN/measure/deformation.npz    tool-tissue contact and indentation per frame, the field
  RUN/measure/summary.json       contact onset / release, deepest indentation, ...
  RUN/metrics/deformation.csv    one row per frame: contact, indentation, area, volume, force
  RUN/metrics/evaluation.json    scores against ground truth
  RUN/metrics/evaluation_errors.npz  per-point errors behind them
  RUN/metrics/frames.csv         one row per frame
  RUN/metrics/summary.json       the run at a glance
  RUN/report.html                the report
  RUN/export.mcap                the Foxglove export (`run --export mcap`; layout beside it)

Exports, outside the run folder (`surgrecon export`):
  OUT.mcap, OUT.layout.json      the Foxglove export and its layout beside it
  DIR/camera_CC.tum, DIR/tool.tum  trajectories in TUM format, at image / frame stamps
  DIR/camera_CC_tracker.tum, DIR/tool_robot.tum  the pose streams as recorded

Camera ids never become paths: image folders and trajectory files use the camera's index in
the sorted id list.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

# Ingest's staging folder (`.ingest-` + 12 hex digits) and the ingest it replaces.
INGEST_STAGING_PREFIX = ".ingest-"
_STAGING_NAME = re.compile(r"\.ingest-(?:[0-9a-f]{12}|old-[0-9]+)")
LOCK_NAME = ".surgrecon.lock"


@dataclass(frozen=True)
class RunLayout:
    """The paths of one run folder `root`."""

    root: Path

    def __init__(self, root: Path | str) -> None:
        object.__setattr__(self, "root", Path(root))

    # run bookkeeping
    @property
    def run_json(self) -> Path:
        return self.root / "run.json"

    @property
    def config_toml(self) -> Path:
        return self.root / "config.toml"

    @property
    def lock_file(self) -> Path:
        """Locked by the one command working on the folder; holds its pid, start, command."""
        return self.root / LOCK_NAME

    # ingest
    @property
    def ingest_dir(self) -> Path:
        return self.root / "ingest"

    @staticmethod
    def ingest_cameras(ingest_dir: Path) -> Path:
        """cameras.json of an ingest folder (the final one or ingest's staging folder)."""
        return Path(ingest_dir) / "cameras.json"

    @staticmethod
    def ingest_frames(ingest_dir: Path) -> Path:
        return Path(ingest_dir) / "frames.npz"

    @staticmethod
    def image_relpath(camera_index: int, frame: int, ext: str) -> str:
        """Path of a stored image relative to the ingest folder."""
        return f"images/{camera_index:02d}/{frame:06d}.{ext}"

    @staticmethod
    def staged_dir(ingest_dir: Path) -> Path:
        """Where ingest writes images as they stream in, before naming them by frame."""
        return Path(ingest_dir) / "staged"

    @staticmethod
    def staged_relpath(camera_index: int, count: int, ext: str) -> str:
        """Path, relative to the ingest folder, of a camera's `count`-th streamed image."""
        return f"staged/{camera_index:02d}/{count:08d}.{ext}"

    @staticmethod
    def staged_video(ingest_dir: Path, camera_index: int) -> Path:
        """A video camera's packets as recorded, appended as they stream in (by discovery
        index)."""
        return Path(ingest_dir) / "staged" / f"{camera_index:02d}.video"

    @staticmethod
    def ingest_video(ingest_dir: Path, camera_index: int) -> Path:
        """A video camera's packets as recorded, with their stamps (io/run/ingest_store.py)."""
        return Path(ingest_dir) / "video" / f"{camera_index:02d}.npz"

    def ingest_staging(self, token: str) -> Path:
        """Ingest's staging folder; `token` is 12 hex digits (or `old-PID`)."""
        return self.root / f"{INGEST_STAGING_PREFIX}{token}"

    @staticmethod
    def is_ingest_staging(path: Path) -> bool:
        """Whether `path` is named like a staging folder of ingest (not, e.g., a user's
        `.ingest-notes`)."""
        return _STAGING_NAME.fullmatch(Path(path).name) is not None

    # template
    @property
    def template_ply(self) -> Path:
        return self.root / "template.ply"

    @property
    def template_dir(self) -> Path:
        return self.root / "template"

    @property
    def observations(self) -> Path:
        return self.template_dir / "observations.npz"

    @property
    def template_summary(self) -> Path:
        return self.template_dir / "summary.json"

    # registration
    @property
    def registration_dir(self) -> Path:
        return self.root / "registration"

    def registration(self, frame: int) -> Path:
        return Path(self.registration_file(frame))

    def registration_file(self, frame: int) -> str:
        """`registration(frame)` as a string, for the per-frame reads and writes of a
        register worker: Python 3.11's pathlib interns every name it parses, so a Path per
        frame adds its file name to the interpreter's table of interned strings and its
        death removes it again; that churn (~2 names a frame here, ~4 for the frame's
        images) rebuilds the 3.8 MB table every ~20,000 frames, and the C heap grows by
        the new table when no hole of its size is free (docs/frame-step-cost.md, "Long
        runs")."""
        return os.path.join(self.registration_dir, f"{frame:06d}.npz")

    @property
    def register_progress(self) -> Path:
        """The register stage's append-only record of finished frames."""
        return self.registration_dir / "progress.jsonl"

    # classification and clouds
    @property
    def classify_dir(self) -> Path:
        return self.root / "classify"

    @property
    def labels(self) -> Path:
        return self.classify_dir / "labels.npz"

    @property
    def classified_dir(self) -> Path:
        return self.classify_dir / "frames"

    def classified(self, frame: int) -> str:
        """One frame's classification before hysteresis (classify's scratch file), a string
        path as `registration_file` says why."""
        return os.path.join(self.classified_dir, f"{frame:06d}.npz")

    @property
    def clouds_dir(self) -> Path:
        return self.root / "clouds"

    def cloud(self, frame: int) -> Path:
        return Path(self.cloud_file(frame))

    def cloud_file(self, frame: int) -> str:
        """`cloud(frame)` as a string, for classify's per-frame writes and the reads of later
        stages (as `registration_file`)."""
        return os.path.join(self.clouds_dir, f"{frame:06d}.ply")

    # contact and indentation
    @property
    def measure_dir(self) -> Path:
        return self.root / "measure"

    @property
    def deformation(self) -> Path:
        return self.measure_dir / "deformation.npz"

    @property
    def deformation_summary(self) -> Path:
        return self.measure_dir / "summary.json"

    @property
    def deformation_csv(self) -> Path:
        return self.metrics_dir / "deformation.csv"

    @property
    def deformation_tools_csv(self) -> Path:
        return self.metrics_dir / "deformation_tools.csv"

    # evaluation and report
    @property
    def metrics_dir(self) -> Path:
        return self.root / "metrics"

    @property
    def evaluation_json(self) -> Path:
        return self.metrics_dir / "evaluation.json"

    @property
    def evaluation_errors(self) -> Path:
        return self.metrics_dir / "evaluation_errors.npz"

    @property
    def frames_csv(self) -> Path:
        return self.metrics_dir / "frames.csv"

    @property
    def summary_json(self) -> Path:
        return self.metrics_dir / "summary.json"

    @property
    def report_html(self) -> Path:
        return self.root / "report.html"

    # exports (anywhere, not in the run folder)
    @staticmethod
    def foxglove_layout_beside(mcap_path: Path) -> Path:
        """The Foxglove layout written beside an exported OUT.mcap (OUT.layout.json)."""
        return Path(mcap_path).with_suffix(".layout.json")

    @staticmethod
    def tum_camera(out_dir: Path, camera_index: int) -> Path:
        return Path(out_dir) / f"camera_{camera_index:02d}.tum"

    @staticmethod
    def tum_tool(out_dir: Path) -> Path:
        return Path(out_dir) / "tool.tum"

    @staticmethod
    def tum_tracker(out_dir: Path, camera_index: int) -> Path:
        """A camera's pose stream as recorded (not synchronised to its images)."""
        return Path(out_dir) / f"camera_{camera_index:02d}_tracker.tum"

    @staticmethod
    def tum_robot(out_dir: Path) -> Path:
        return Path(out_dir) / "tool_robot.tum"

    @staticmethod
    def ingest_streams(ingest_dir: Path) -> Path:
        """The pose streams as recorded, in the world frame (ingest/streams.npz)."""
        return Path(ingest_dir) / "streams.npz"

    @property
    def export_mcap(self) -> Path:
        """Where `surgrecon run --export mcap` writes the run's MCAP export."""
        return self.root / "export.mcap"

    def relative(self, path: Path) -> str:
        """`path` relative to the run folder, with forward slashes (for the report)."""
        return Path(path).relative_to(self.root).as_posix()


# What the report's "Files" table lists, in order: (layout attribute, what it holds).
DESCRIBED_FILES = (
    ("run_json", "status, timings and config of every stage"),
    ("config_toml", "the effective config (rerun with `--config`)"),
    ("template_ply", "the template cloud P (frame 0)"),
    ("clouds_dir", "one labelled cloud per frame (PLY, point_id, label, residual, sigma)"),
    ("registration_dir", "per-frame transforms, targets and uncertainties (npz)"),
    ("labels", "labels (T, N) and the measures behind them"),
    ("frames_csv", "the per-frame table behind these plots"),
    ("deformation_csv", "per frame: tool-tissue contact, indentation, area, volume, force"),
    ("deformation_tools_csv", "the same per frame and tool, when there are `[[tools]]`"),
    ("deformation", "the rigid-motion-compensated displacement field and the per-frame measures"),
    ("summary_json", "this run at a glance"),
    ("evaluation_json", "scores against ground truth (when evaluated)"),
)
