"""16-bit images: kept with their low byte wherever they are stored (convert copies the PNG,
ingest keeps it), and turned into 8 bits for tracking from the camera's real range, not by
dropping the low byte (a 12-bit camera's 0..4095 would become 0..15)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from convert_inputs import opencv_calibration, stereo_folder

from surgrecon_cli.cli.main import main
from surgrecon_cli.io.run.ingest_store import load_ingested


def _convert_and_ingest(tmp_path: Path, src: Path) -> Path:
    opencv_calibration(tmp_path / "calib.yaml")
    out = tmp_path / "rec.mcap"
    assert main(["convert", str(src), "-o", str(out), "--calibration",
                 str(tmp_path / "calib.yaml"), "-q"]) == 0
    run = tmp_path / "run"
    assert main(["ingest", str(out), "-o", str(run), "--config", str(out.with_suffix(".toml")),
                 "-q"]) == 0
    return run


@pytest.mark.parametrize("bits,ext", [(12, ".png"), (16, ".tiff")])
def test_16_bit_images_keep_their_low_byte_and_scale_from_their_range(tmp_path: Path,
                                                                      bits: int, ext: str):
    files = stereo_folder(tmp_path / "rec", frames=2, ext=ext, depth16=True)
    originals = {}
    for paths in files.values():
        for path in paths:  # a 12-bit camera: values 0..4095 in 16-bit files
            img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED) >> (16 - bits)
            assert cv2.imwrite(str(path), img)
            originals[path] = img
    run = _convert_and_ingest(tmp_path, tmp_path / "rec")
    log = load_ingested(run / "ingest")
    top = 2**bits - 1
    for c, side in enumerate(log.cameras):
        assert log.report["cameras"][side]["pixel_max"] == max(
            int(originals[p].max()) for p in files[side])
        for k, path in enumerate(files[side]):
            stored = cv2.imread(str(run / "ingest" / log.image_paths[k][c]),
                                cv2.IMREAD_UNCHANGED)
            assert stored.dtype == np.uint16
            np.testing.assert_array_equal(stored, originals[path])  # nothing lost
            if ext == ".png":  # PNG bytes are copied as they are
                assert (run / "ingest" / log.image_paths[k][c]).read_bytes() == \
                    path.read_bytes()
            want = np.round(originals[path][:, :, ::-1] * (255.0 / top))
            got = log.load_image(k, c)
            assert got.dtype == np.uint8
            assert np.abs(got.astype(float) - want).max() <= 1.0
            assert got.max() >= 200  # the range is used: not the high byte's 0..15


def test_raw_16_bit_messages_are_stored_16_bit_with_their_peak():
    """A 12-bit camera publishing `mono16` (big-endian, as ROS allows): stored as a 16-bit
    PNG of the same values, its peak the largest value, scaled to 0..255 from 0..4095."""
    from surgrecon_cli.io.logs.images import prepare_image, to_8bit
    from surgrecon_cli.io.logs.records import ImageRecord

    rng = np.random.default_rng(5)
    values = rng.integers(0, 4096, (24, 32), dtype=np.uint16)
    values[3, 4] = 4000  # the largest value
    values[values > 4000] = 17
    stored = prepare_image(ImageRecord(1, "cam", "mono16", values.astype(">u2").tobytes(),
                                       32, 24, 64, big_endian=True))
    assert stored.peak == 4000
    png = cv2.imdecode(np.frombuffer(stored.data, np.uint8), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(png, values)
    scaled = to_8bit(png, stored.peak)
    np.testing.assert_allclose(scaled, np.round(values * (255 / 4095)), atol=1.0)
