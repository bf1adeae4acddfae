"""A register worker's per-frame files (its registration, written and read back as a base,
and the frame's stored images) are reached without pathlib (issue 27, long runs).

Python 3.11's pathlib interns every name it parses (`sys.intern`); a name used for one frame
and then dropped is inserted into the interpreter's table of interned strings and removed
again, and that churn rebuilds the table (3.8 MB) every ~20,000 frames of a long run, which
the C heap kept as steps of resident memory (docs/frame-step-cost.md, "Long runs"). Here
the frame's names must not reach `sys.intern`. On Python >= 3.12 pathlib interns nothing,
so there is nothing to check.
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from surgrecon_cli.io.run.artefacts import (
    FrameRegistration,
    read_frame_cloud,
    read_registration,
    write_frame_cloud,
    write_registration,
)
from surgrecon_cli.io.run.atomic import write_npz
from surgrecon_cli.io.run.ingest_store import IngestedLog
from surgrecon_cli.io.run.layout import RunLayout

pytestmark = pytest.mark.skipif(sys.version_info >= (3, 12),
                                reason="pathlib interns names only up to Python 3.11")

FRAME = 7


@pytest.fixture
def interned(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """Every string passed to `sys.intern` while the test runs (pathlib's parsing calls it)."""
    names: list[str] = []
    real = sys.intern

    def spy(name: str) -> str:
        names.append(name)
        return real(name)

    monkeypatch.setattr(sys, "intern", spy)
    # the spy sees pathlib's interning (else the tests below would pass for nothing)
    _ = Path("/somewhere") / f"{FRAME:06d}.probe"
    assert f"{FRAME:06d}.probe" in names
    names.clear()
    return names


def _registration(n: int) -> FrameRegistration:
    rng = np.random.default_rng(3)
    registered = rng.normal(size=(n, 3)) * 0.01
    transforms = np.tile(np.eye(3, 4), (n, 1, 1))
    transforms[:, :, 3] = registered
    return FrameRegistration(
        transforms=transforms, registered=registered, target=registered,
        status=np.zeros(n, np.uint8), views=np.full(n, 2), residual=np.zeros(n),
        sigma=np.full(n, 1e-4), target_sigma=np.full(n, 1e-4),
        target_covariance=np.zeros((n, 3, 3)), target_pose_covariance=np.zeros((n, 3, 3)),
        support_mm=np.zeros(n), pixels=np.full((n, 2, 2), 5.0), tracking_px=0.05, base=6,
        converged=True, failed=False, error="", seconds_target=0.1, seconds_register=0.2,
        new_points=0, contact_points=0)


def test_registration_written_and_read_without_interning_its_name(
        tmp_path: Path, interned: list[str]) -> None:
    layout = RunLayout(tmp_path / "run")
    assert layout.registration_file(FRAME) == str(layout.registration(FRAME))
    interned.clear()
    reg = _registration(5)
    write_registration(layout, FRAME, reg)
    back = read_registration(layout, FRAME, 5)
    np.testing.assert_allclose(back.registered, reg.registered, rtol=1e-6)  # float32 on disk
    assert back.base == 6 and back.converged
    assert not [name for name in interned if f"{FRAME:06d}" in name]
    assert layout.registration(FRAME).is_file()  # where `registration` says


def test_frame_image_loaded_without_interning_its_name(tmp_path: Path,
                                                      interned: list[str]) -> None:
    root = tmp_path / "ingest"
    rel = RunLayout.image_relpath(0, FRAME, "png")
    rgb = np.zeros((6, 8, 3), np.uint8)
    rgb[..., 0] = 200  # red
    (root / rel).parent.mkdir(parents=True)
    assert cv2.imwrite(str(root / rel), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    frames = FRAME + 1
    paths = (*(("",) for _ in range(FRAME)), (rel,))
    log = IngestedLog(root=root, cameras=("cam",), models=(), stamps_ns=np.zeros(frames),
                      image_stamps_ns=np.zeros((frames, 1)), poses=np.zeros((frames, 1, 4, 4)),
                      usable=np.ones((frames, 1), bool), tool_poses=np.zeros((frames, 4, 4)),
                      joint_names=(), joint_positions=np.zeros((frames, 0)), image_paths=paths)
    interned.clear()
    np.testing.assert_array_equal(log.load_image(FRAME, 0), rgb)
    assert not [name for name in interned if f"{FRAME:06d}" in name or name == "00"]


def test_frame_cloud_and_classified_rows_without_interning_their_names(
        tmp_path: Path, interned: list[str]) -> None:
    """classify writes a cloud and a scratch file per frame; measure and report read the
    clouds back."""
    layout = RunLayout(tmp_path / "run")
    assert layout.cloud_file(FRAME) == str(layout.cloud(FRAME))
    positions = np.random.default_rng(4).normal(size=(6, 3)) * 0.01
    interned.clear()
    write_frame_cloud(layout, FRAME, positions, np.full((6, 3), 90, np.uint8),
                      np.arange(6, dtype=np.uint8), np.zeros(6), {})
    back = read_frame_cloud(layout, FRAME)
    write_npz(layout.classified(FRAME), labels=np.arange(6, dtype=np.uint8))
    with np.load(layout.classified(FRAME)) as z:
        assert list(z["labels"]) == list(range(6))
    assert not [name for name in interned if f"{FRAME:06d}" in name]
    np.testing.assert_allclose(back["x"], positions[:, 0], rtol=1e-6)  # float32 on disk
    assert list(back["label"]) == list(range(6))
    assert layout.cloud(FRAME).is_file()
