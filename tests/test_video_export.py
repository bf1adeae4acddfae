"""H.264 inputs are exported as they were recorded: ingest keeps each video camera's packets
(RUN/ingest/video/CC.npz) and the MCAP export passes them through as
foxglove.CompressedVideo, instead of re-encoding the decoded frames as PNG (5x the size)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest
import synth_log
from mcap.reader import make_reader
from synth_log import SynthSpec
from test_video import _images_as

from surgrecon_cli.cli.main import main
from surgrecon_cli.io.export.to_mcap import VideoPassThrough, camera_topic
from surgrecon_cli.io.run.ingest_store import load_ingested, load_video

pytestmark = pytest.mark.skipif(importlib.util.find_spec("av") is None,
                                reason='PyAV not installed (pip install "surgrecon[video]")')


class _Recorder:
    """Stands in for McapOut: keeps (topic, message, stamp)."""

    def __init__(self) -> None:
        self.messages: list[tuple[str, object, int]] = []

    def protobuf(self, topic: str, message: object, stamp_ns: int) -> None:
        self.messages.append((topic, message, stamp_ns))


def _recorded_packets(log: Path, topic: str) -> list[tuple[int, bytes]]:
    from mcap_protobuf.decoder import DecoderFactory

    with open(log, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        return [(m.timestamp.seconds * 10**9 + m.timestamp.nanos, bytes(m.data))
                for _, _, _, m in reader.iter_decoded_messages(topics=[topic])]


def test_video_packets_are_kept_and_exported_as_recorded(tmp_path: Path):
    spec = SynthSpec(cameras=(0, 1), frames=6, mutate=_images_as("h264"))
    log = synth_log.write(tmp_path / "video.mcap", spec, "foxglove-protobuf")
    assert main(["ingest", str(log), "-o", str(tmp_path / "run"), "-q"]) == 0
    ingested = load_ingested(tmp_path / "run" / "ingest")
    for c, cam in enumerate(spec.cameras):
        recorded = _recorded_packets(log, f"/endoscope_{cam}/color/compressed")
        video = load_video(ingested.root, c)
        assert video is not None and video.format == "h264"
        assert video.packets() == recorded  # every packet, byte for byte, with its stamp

        out = _Recorder()
        passing = VideoPassThrough(ingested, c, video)
        for k in range(ingested.n_frames):
            passing.up_to(out, k)
        sent = [m for topic, m, _ in out.messages if topic == camera_topic(c, "image")]
        assert [type(m).__name__ for m in sent] == ["CompressedVideo"] * len(recorded)
        assert [bytes(m.data) for m in sent] == [data for _, data in recorded]
        assert {m.format for m in sent} == {"h264"}
        # each frame's own packet carries the frame's time, as every message of the frame
        assert [s for _, _, s in out.messages] == [int(t) for t in ingested.stamps_ns]
        png = sum((ingested.root / ingested.image_paths[k][c]).stat().st_size
                  for k in range(ingested.n_frames))
        assert sum(len(m.data) for m in sent) < png
