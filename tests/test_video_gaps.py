"""Issue 25, finding 4: a lost or duplicated CompressedVideo message is found (H.264
frame_num, stamps, payloads), warned about naming the camera and frames, and the frames
decoded against the missing reference are dropped for that camera until the next keyframe."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import synth_log
from synth_log import SynthSpec
from test_video import KEYFRAME_INTERVAL, _images_as, decoded, encode_stream, frame_rgb, needs_av

from surgrecon_cli.cli.main import main
from surgrecon_cli.io.logs.records import ImageRecord
from surgrecon_cli.io.logs.video import VideoDecoder
from surgrecon_cli.io.run.ingest_store import load_ingested

N = 12  # frames 0, 5, 10 are keyframes


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(((a.astype(float) - b.astype(float)) ** 2).mean())
    return 10 * np.log10(255.0 ** 2 / max(mse, 1e-9))


def decode_all(codec: str, order: list[int]) -> tuple[list[tuple[int, float]], VideoDecoder]:
    """Decode the messages of frames `order` (indices into one N-frame stream, stamped
    100 ms apart): (frame, PSNR against its source) per output image, and the decoder."""
    frames = [frame_rgb(0, k) for k in range(N)]
    packets = encode_stream(frames, codec)
    decoder = VideoDecoder("/cam", codec)
    out = []
    for k in order:
        out += decoder.decode(ImageRecord(synth_log.T0 + k * 100 * synth_log.MS, "c", codec,
                                          packets[k]))
    out += decoder.flush()
    got = [((s - synth_log.T0) // (100 * synth_log.MS), st) for s, st in out]
    return [(k, psnr(decoded(st), frames[k])) for k, st in got], decoder


@needs_av
@pytest.mark.parametrize("codec", ["h264", "h265"])
def test_a_lost_message_drops_the_frames_until_the_next_keyframe(codec: str):
    assert KEYFRAME_INTERVAL == 5
    lost = 7  # (the stamp-based check needs a few steps to know the period)
    out, decoder = decode_all(codec, [k for k in range(N) if k != lost])
    # Frames 8 and 9 depend on the lost 7 (measured, H.264: 18 dB against ~44 dB for a
    # correct decode); frame 10 is a keyframe.
    assert [k for k, _ in out] == [0, 1, 2, 3, 4, 5, 6, 10, 11]
    assert min(p for _, p in out) > 35
    [problem] = decoder.problems
    assert problem.kind == "gap" and problem.stamp_ns == synth_log.T0 + 800 * synth_log.MS
    assert ("frame_num 3, expected 2" if codec == "h264" else "stamp step 200 ms") in problem.detail
    assert len(problem.damaged) == 2


@needs_av
@pytest.mark.parametrize("order", [[0, 1, 2, 2, 3], [0, 1, 2, 3, 2, 4]], ids=["next", "later"])
def test_a_duplicated_message_is_not_decoded_again(order: list[int]):
    order = order + list(range(max(order) + 1, N))
    out, decoder = decode_all("h264", order)
    assert [k for k, _ in out] == list(range(N))
    assert min(p for _, p in out) > 35
    [problem] = decoder.problems
    assert problem.kind == "duplicate" and "same payload and stamp" in problem.detail


@needs_av
def test_ingest_warns_naming_camera_and_frames_and_reports_them(
        tmp_path: Path, capsys: pytest.CaptureFixture):
    to_h264 = _images_as("h264")
    topic = "/endoscope_1/color/compressed"
    spec = SynthSpec(cameras=(0, 1, 2), frames=8)

    def mutate(messages):
        out = to_h264(messages)
        images = [m for m in out if m[0] == topic]
        lost, repeated = images[2], images[6]
        out.remove(lost)  # frames 3, 4 of camera 1 decode against it
        out.append((topic, repeated[1] + synth_log.MS, repeated[2]))
        return out

    spec.mutate = mutate
    log = synth_log.write(tmp_path / "log.mcap", spec, "foxglove-protobuf")
    assert main(["ingest", str(log), "-o", str(tmp_path / "run"), "--quiet"]) == 0
    ingested = load_ingested(tmp_path / "run" / "ingest")
    assert ingested.n_frames == 8
    expected = np.ones((8, 3), bool)
    expected[2:5, 1] = False
    np.testing.assert_array_equal(ingested.usable, expected)
    report = ingested.report["cameras"]["1"]
    assert (report["video_lost"], report["video_duplicates"], report["video_damaged"]) == (1, 1, 2)
    assert all(ingested.report["cameras"][c]["video_lost"] == 0 for c in ("0", "2"))
    warnings = capsys.readouterr().err.splitlines()
    lost = [w for w in warnings if "is lost" in w]
    assert len(lost) == 1 and lost[0].startswith(f"camera 1: video on {topic}")
    assert "frames 3-4" in lost[0] and "frame_num" in lost[0]
    assert sum("duplicate" in w and w.startswith("camera 1:") for w in warnings) == 1
