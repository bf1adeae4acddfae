"""Issue 25, finding 5: inputs that would silently remove a camera are handled or named at
once: EXIF orientation ignored (pixels as stored), conflicting pose samples at one stamp
warned about and dropped, implausible intrinsics refused."""

from __future__ import annotations

import dataclasses
import struct
from pathlib import Path

import numpy as np
import pytest
import synth_log
from synth_log import MS, T0, SynthSpec
from test_ingest import check_log

from surgrecon_cli.cli.main import main
from surgrecon_cli.core.geometry.cameras import CameraModel
from surgrecon_cli.core.geometry.intrinsics import folds_before_corners, implausible_intrinsics
from surgrecon_cli.io.logs.records import CameraInfoRecord, ImageRecord, PoseRecord
from surgrecon_cli.io.run.ingest_store import load_ingested


def with_orientation(jpeg: bytes, orientation: int) -> bytes:
    """The JPEG with an EXIF APP1 segment whose Orientation tag (0x0112) is `orientation`."""
    ifd = struct.pack("<H", 1) + struct.pack("<HHII", 0x0112, 3, 1, orientation) + b"\0" * 4
    tiff = b"II*\x00" + struct.pack("<I", 8) + ifd
    body = b"Exif\x00\x00" + tiff
    return jpeg[:2] + b"\xff\xe1" + struct.pack(">H", len(body) + 2) + body + jpeg[2:]


@pytest.mark.parametrize("orientation", [3, 6])
def test_exif_orientation_is_ignored(tmp_path: Path, orientation: int, capsys):
    """Orientation 3 (rotated 180°) used to rotate camera 1's images; 6 (90°) made them
    48x64 px and failed ingest with a size error."""

    def mutate(messages):
        return [(t, lt, dataclasses.replace(r, data=with_orientation(r.data, orientation)))
                if isinstance(r, ImageRecord) and t.startswith("/endoscope_1/") else (t, lt, r)
                for t, lt, r in messages]

    spec = SynthSpec(image_format="jpeg", mutate=mutate)
    log = synth_log.write(tmp_path / "log.mcap", spec)
    run = tmp_path / "run"
    assert main(["ingest", str(log), "-o", str(run), "--quiet"]) == 0, capsys.readouterr().err
    check_log(run, spec, jpeg=True)  # camera 1's images as stored, not rotated


def _conflict(tf: bool):
    """A mutation adding, just before camera 1's tracker sample at 200 ms (which places its
    first image, at 203 ms), a second sample at the same stamp 5 cm away."""
    t = T0 + 200 * MS

    def mutate(messages):
        good = next(r for topic, _, r in messages if isinstance(r, PoseRecord) and r.stamp_ns == t
                    and (r.child_frame_id == "endoscope_1_optical" if tf
                         else topic == "/navigation/endoscope_1/pose"))
        topic = "/tf" if tf else "/navigation/endoscope_1/pose"
        bad = dataclasses.replace(good, position=good.position + np.array([0.05, 0, 0]))
        return [*messages, (topic, t + MS - 1, bad)]

    return mutate


@pytest.mark.parametrize("tf", [False, True], ids=["topic", "tf"])
def test_conflicting_pose_samples_at_one_stamp_are_dropped_with_a_warning(
        tmp_path: Path, tf: bool, capsys):
    spec = SynthSpec(tf_topic="/tf" if tf else None, camera_frame="endoscope_{c}_optical",
                     mutate=_conflict(tf))
    log = synth_log.write(tmp_path / "log.mcap", spec)
    run = tmp_path / "run"
    tf_topics = ["--set", "topics.camera_pose=/tf", "--set", "topics.tool_pose=/tf", "--set",
                 "topics.camera_frame=endoscope_{camera}_optical", "--set",
                 f"topics.tool_frame={spec.tool_frame}"] if tf else []
    assert main(["ingest", str(log), "-o", str(run), "--quiet", *tf_topics]) == 0
    err = capsys.readouterr().err
    # neither sample is trusted; the neighbours (160, 240 ms) interpolate the true motion
    check_log(run, spec)
    name = "TF 'world' -> 'endoscope_1_optical'" if tf else "/navigation/endoscope_1/pose"
    [line] = [w for w in err.splitlines() if "disagree" in w]
    assert line.startswith(f"{name}: 1 stamp with pose samples that disagree")
    assert "1700000000.200000000 s" in line and "up to 50 mm" in line
    report = load_ingested(run / "ingest").report["cameras"]
    assert [report[c]["pose_conflicts"] for c in ("0", "1", "2")] == [0, 1, 0]


def test_agreeing_repeated_samples_are_kept_silently(tmp_path: Path, capsys):
    t = T0 + 200 * MS

    def mutate(messages):
        again = next((topic, lt, r) for topic, lt, r in messages
                     if topic == "/navigation/endoscope_1/pose" and r.stamp_ns == t)
        return [*messages, again]

    spec = SynthSpec(mutate=mutate)
    log = synth_log.write(tmp_path / "log.mcap", spec)
    assert main(["ingest", str(log), "-o", str(tmp_path / "run"), "--quiet"]) == 0
    assert "disagree" not in capsys.readouterr().err
    check_log(tmp_path / "run", spec)


def _info(k: np.ndarray | None = None, d: list[float] | None = None):
    def mutate(messages):
        return [(t, lt, dataclasses.replace(
                    r, K=r.K if k is None else k, D=r.D if d is None else np.array(d)))
                if isinstance(r, CameraInfoRecord) and t == "/endoscope_1/calibration"
                else (t, lt, r) for t, lt, r in messages]

    return mutate


K1 = synth_log.intrinsics(1)
CX_FAR = np.array([[0, 0, 1e6], [0, 0, 0], [0, 0, 0]])
NO_K22 = np.diag([0.0, 0.0, 1.0])


@pytest.mark.parametrize(("mutate", "fragment"), [
    (_info(k=K1 + CX_FAR), "principal point (1.00003e+06, 23.5) px"),
    (_info(k=K1 - NO_K22), "K's last row is [0.0, 0.0, 0.0]"),
    (_info(d=[-1.5, 40.0, 0.0, 0.0, -300.0]), "distortion [-1.5, 40.0, 0.0, 0.0, -300.0] is not "
                                              "monotonic"),
], ids=["principal-point", "K22", "distortion"])
def test_implausible_intrinsics_are_refused_naming_topic_and_value(
        tmp_path: Path, mutate, fragment: str, capsys):
    log = synth_log.write(tmp_path / "log.mcap", SynthSpec(mutate=mutate))
    assert main(["ingest", str(log), "-o", str(tmp_path / "run"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and err.startswith("error: /endoscope_1/calibration: intrinsics at")
    assert fragment in err and "cannot be a real camera's" in err


@pytest.mark.parametrize(("model", "dist"), [
    ("plumb_bob", [-0.35, 0.12, 0.001, -0.002, 0.0]),  # a wide endoscope
    ("rational_polynomial", [0.4, -0.1, 0.0, 0.0, 0.0, 0.7, -0.05, 0.0]),
    ("equidistant", [-0.02, 0.01, -0.004, 0.0005]),  # a fisheye
])
def test_real_lenses_are_plausible(model: str, dist: list[float]):
    K = np.array([[500.0, 0, 319.5], [0, 500, 239.5], [0, 0, 1]])
    assert implausible_intrinsics(K, 640, 480, CameraModel(K, np.array(dist), 640, 480,
                                                           model)) is None
    camera = CameraModel(K, np.array(dist), 640, 480, model)
    assert folds_before_corners(K, 640, 480, camera) is None
    # r_d = r - k r^3 peaks at r_d = 2 / (3 sqrt(3 k)): 0.385 for k = 1, before the edges'
    # midpoints (0.64 and 0.47 from the principal point); 0.72 for k = 0.286, past the
    # edges but before the corners (0.8): refused, and only warned about.
    edges = CameraModel(K, np.array([-1.0, 0.0, 0.0, 0.0, 0.0]), 640, 480)
    assert "not monotonic out to pixel (319.5, 0)" in str(
        implausible_intrinsics(K, 640, 480, edges))
    corners = CameraModel(K, np.array([-0.286, 0.0, 0.0, 0.0, 0.0]), 640, 480)
    assert implausible_intrinsics(K, 640, 480, corners) is None
    assert "not monotonic out to pixel (0, 0)" in str(folds_before_corners(K, 640, 480, corners))
