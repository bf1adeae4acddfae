"""Convert speed benchmark (issue 23): frames/s of `surgrecon convert` on stereo image folders
(JPEG and PNG bytes copied, not re-encoded) and on a side-by-side stereo video (decoded and
encoded once as JPEG q95), from the real SurgT clip in tests/data/surgt.

    .venv/bin/python benchmarks/convert_speed.py [--frames 300] [--workdir DIR]

The folders hold --frames stereo pairs at the clip's 1280x1024 px per eye (its 10 frames
repeated: JPEG quality 90, ~260 KB an image; PNG ~1.9 MB), written once; the video is the
clip itself (10 frames). Each conversion runs in this process
after a warm-up (imports excluded) and prints wall and CPU seconds and frames/s (wall). The
goal (issue 23): >= 100 frames/s for JPEG/PNG folders. On a loaded machine the wall figure is
noisy; the CPU figure shows what the conversion itself costs, MB/s the bytes written (a
PNG folder at this size is bound by the disk: 3.8 MB a frame).
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve()
SURGT = HERE.parents[1] / "tests" / "data" / "surgt"


def make_folders(root: Path, frames: int) -> dict[str, Path]:
    """root/jpeg/{left,right}/*.jpg and root/png/{left,right}/*.png of the clip's frames."""
    import av
    import cv2

    with av.open(str(SURGT / "video.mp4")) as container:
        views = [frame.to_ndarray(format="bgr24") for frame in container.decode(video=0)]
    out = {}
    for kind, ext, params in (("jpeg", ".jpg", [cv2.IMWRITE_JPEG_QUALITY, 90]),
                              ("png", ".png", [])):
        folder = root / kind
        for side, cols in (("left", slice(0, 1280)), ("right", slice(1280, 2560))):
            (folder / side).mkdir(parents=True, exist_ok=True)
            encoded = [cv2.imencode(ext, v[:, cols], params)[1].tobytes() for v in views]
            for i in range(frames):
                (folder / side / f"{i:06d}{ext}").write_bytes(encoded[i % len(encoded)])
        out[kind] = folder
    return out


def timed(src: Path, out: Path, **options: object) -> tuple[int, float, float, int]:
    """(frames, wall s, CPU s, bytes written) of one conversion."""
    from surgrecon_cli.convert.run import ConvertRequest, convert

    request = ConvertRequest(out=out, calibration=(SURGT / "calibration.yaml",), src=src,
                             **options)  # type: ignore[arg-type]
    wall, cpu = time.perf_counter(), time.process_time()
    result = convert(request)
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    size = out.stat().st_size
    out.unlink()
    out.with_suffix(".toml").unlink()
    return result.frames, wall, cpu, size


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=300, help="stereo pairs per folder")
    parser.add_argument("--workdir", type=Path, help="where the folders go (default: a temp dir)")
    args = parser.parse_args()
    root = Path(tempfile.mkdtemp(prefix="convert_speed_", dir=args.workdir))
    try:
        folders = make_folders(root, args.frames)
        timed(folders["jpeg"], root / "warm.mcap", frames=slice(0, 5))
        print(f"{'input':<34} {'frames':>6} {'wall s':>7} {'CPU s':>7} {'frames/s':>9} "
              f"{'MB/s':>6}")
        rows = [("JPEG folder (bytes copied)", folders["jpeg"], {}),
                ("PNG folder (bytes copied)", folders["png"], {}),
                ("side-by-side video -> JPEG q95", SURGT / "video.mp4", {}),
                ("side-by-side video -> PNG", SURGT / "video.mp4", {"image_format": "png"})]
        for label, src, options in rows:
            frames, wall, cpu, size = timed(src, root / "out.mcap", **options)
            print(f"{label:<34} {frames:>6} {wall:>7.2f} {cpu:>7.2f} {frames / wall:>9.1f} "
                  f"{size / wall / 1e6:>6.0f}")
    finally:
        shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":
    main()
