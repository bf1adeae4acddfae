"""Convert speed benchmark (issue 23): frames/s of `surgrecon convert` on stereo image folders
(JPEG and PNG bytes copied, not re-encoded) and on a side-by-side stereo video (decoded and
encoded once as JPEG q95), from the real SurgT clip in tests/data/surgt.

    .venv/bin/python benchmarks/convert_speed.py [--frames 300] [--workdir DIR]

The folders hold --frames stereo pairs at the clip's 1280x1024 px per eye (its 10 frames
repeated: JPEG quality 90, ~260 KB an image; PNG ~1.9 MB), written once; the video is the
clip itself (10 frames). Each conversion runs in a fresh process, as `surgrecon convert`
does (imports excluded), and prints wall and CPU seconds (user + system: on a VM the
kernel's page faults and page-cache pages are most of a PNG folder's cost), frames/s of
both, and MB/s written. The goal (issue 23): >= 100 frames/s for JPEG/PNG folders. On a
loaded machine the wall figure is noisy; the CPU figure shows what the conversion costs.
Results: docs/recordings.md ("Convert speed").
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
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
    """(frames, wall s, CPU s, bytes written) of one conversion in this process."""
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


def timed_fresh(src: Path, out: Path, image_format: str) -> tuple[int, float, float, int]:
    """`timed` in a fresh Python process (what a `surgrecon convert` command costs)."""
    code = ("import json, sys; sys.path.insert(0, sys.argv[1]); import convert_speed as b; "
            "from pathlib import Path; import surgrecon_cli.convert.run; "
            "print(json.dumps(b.timed(Path(sys.argv[2]), Path(sys.argv[3]), "
            "image_format=sys.argv[4])))")
    done = subprocess.run([sys.executable, "-c", code, str(HERE.parent), str(src), str(out),
                           image_format], check=True, capture_output=True, text=True)
    frames, wall, cpu, size = json.loads(done.stdout.splitlines()[-1])
    return frames, wall, cpu, size


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=300, help="stereo pairs per folder")
    parser.add_argument("--workdir", type=Path, help="where the folders go (default: a temp dir)")
    args = parser.parse_args()
    if args.workdir is not None:
        args.workdir.mkdir(parents=True, exist_ok=True)
    root = Path(tempfile.mkdtemp(prefix="convert_speed_", dir=args.workdir))
    try:
        folders = make_folders(root, args.frames)
        print(f"{'input':<34} {'frames':>6} {'wall s':>7} {'CPU s':>7} {'fps wall':>9} "
              f"{'fps CPU':>8} {'MB/s':>6}")
        rows = [("JPEG folder (bytes copied)", folders["jpeg"], "jpeg"),
                ("PNG folder (bytes copied)", folders["png"], "jpeg"),
                ("side-by-side video -> JPEG q95", SURGT / "video.mp4", "jpeg"),
                ("side-by-side video -> PNG", SURGT / "video.mp4", "png")]
        for label, src, image_format in rows:
            frames, wall, cpu, size = timed_fresh(src, root / "out.mcap", image_format)
            print(f"{label:<34} {frames:>6} {wall:>7.2f} {cpu:>7.2f} {frames / wall:>9.1f} "
                  f"{frames / cpu:>8.1f} {size / wall / 1e6:>6.0f}")
    finally:
        shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":
    main()
