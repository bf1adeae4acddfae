"""Real 6-camera recording (tests/data/dlfd: d-lfd, MIT): one image folder per camera and a
`cameras` calibration with hand-eye poses convert, and ingest places every camera where the
calibration file says, with its intrinsics scaled to the resized images."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from surgrecon_cli.cli.main import main

DLFD = Path(__file__).parent / "data" / "dlfd"
CAMERAS = ("p1_left", "p1_right", "p2_left", "p2_right", "p3_left", "p3_right")


def test_six_cameras_convert_and_ingest_where_the_calibration_puts_them(tmp_path: Path):
    out = tmp_path / "dlfd.mcap"
    cams = [x for c in CAMERAS for x in ("--camera", f"{c}={DLFD / c}")]
    assert main(["convert", "-o", str(out), "--calibration", str(DLFD / "calibration.json"),
                 "--scale-calibration", *cams, "-q"]) == 0
    run = tmp_path / "run"
    assert main(["ingest", str(out), "-o", str(run), "--config", str(out.with_suffix(".toml")),
                 "-q"]) == 0
    from surgrecon_cli.io.run.ingest_store import load_ingested

    log = load_ingested(run / "ingest")
    assert log.cameras == CAMERAS and log.n_frames == 3 and log.usable.all()
    calib = json.loads((DLFD / "calibration.json").read_text(encoding="utf-8"))["cameras"]
    for k, name in enumerate(CAMERAS):
        pose = np.array(calib[name]["pose"])
        np.testing.assert_allclose(log.poses[0, k, :3, 3], pose[:3, 3] / 1000, atol=1e-9)
        # the file's rotations are orthonormal to ~1e-4 only: convert takes the nearest
        np.testing.assert_allclose(log.poses[0, k, :3, :3], pose[:3, :3], atol=5e-4)
        K = np.array(calib[name]["K"])
        sx, sy = 310 / 640, 244 / 480  # the videos' size over the calibration images'
        model = log.models[k]
        assert (model.width, model.height) == (310, 244)
        np.testing.assert_allclose([model.K[0, 0], model.K[1, 1]], [K[0, 0] * sx, K[1, 1] * sy])
        np.testing.assert_allclose([model.K[0, 2], model.K[1, 2]],
                                   [(K[0, 2] + 0.5) * sx - 0.5, (K[1, 2] + 0.5) * sy - 0.5])
