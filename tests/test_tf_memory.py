"""Issue 25, finding 6: TF is stored compactly per edge (memory per transform bounded and
flat), and a huge frame id is refused in one short line instead of being echoed whole or
allocated for every sample."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import synth_log
from synth_log import MS, T0, SynthSpec

from surgrecon_cli.cli.main import main
from surgrecon_cli.core.sync.tf_samples import MAX_FRAME_ID_BYTES, SampleCollector, concat_samples
from surgrecon_cli.core.sync.tf_tree import build_tf_tree
from surgrecon_cli.io.logs.records import PoseRecord
from surgrecon_cli.sim.tf_load import write_tf_log

BENCHMARK = Path(__file__).resolve().parents[1] / "benchmarks" / "tf_memory.py"


def test_rss_growth_reading_100k_transforms_stays_small(tmp_path: Path):
    """Measured (benchmarks/tf_memory.py, 100k samples on 20 edges): growth at the peak
    70 MB before (702 bytes/sample), 16 MB after (158). The cap is generous."""
    log = tmp_path / "tf.mcap"
    assert write_tf_log(log, 100_000) == 100_000
    out = subprocess.run([sys.executable, str(BENCHMARK), str(log), "--measure-only", "--json"],
                         check=True, capture_output=True, text=True).stdout
    r = json.loads(out)
    assert r["samples"] == 100_000 and r["edges"] == 20
    assert r["peak"] - r["base"] < 50e6


def test_samples_are_kept_per_edge_in_arrival_order():
    collector = SampleCollector()
    for k in range(5):
        for child in ("a", "b"):
            collector.add("w", child, False, T0 + (5 - k), [k, 0, 0, 0, 0, 0, 1])
    samples = concat_samples([collector.samples(), collector.samples()])
    assert [(e.parent, e.child, e.static, len(e.stamps_ns)) for e in samples.edges] == [
        ("w", "a", False, 10), ("w", "b", False, 10)]
    assert samples.edges[0].stamps_ns.dtype == np.int64
    assert samples.edges[0].values.shape == (10, 7)
    np.testing.assert_array_equal(samples.edges[0].values[:5, 0], np.arange(5))
    tree = build_tf_tree(samples)
    assert tree.edge("a").published == 10 and len(tree.edge("a").stream) == 5


def test_a_huge_frame_id_is_refused_in_one_short_line(tmp_path: Path, capsys):
    huge = "x" * 5_000_000
    for name, extra in (("tf", ("/tf", T0 + 150 * MS + 1,
                                PoseRecord(T0 + 150 * MS, "world", huge, np.zeros(3),
                                           np.array([0.0, 0, 0, 1])))),
                        ("pose", ("/navigation/endoscope_1/pose", T0 + 150 * MS + 1,
                                  PoseRecord(T0 + 150 * MS, huge, "", np.zeros(3),
                                             np.array([0.0, 0, 0, 1]))))):
        log = synth_log.write(tmp_path / f"{name}.mcap", SynthSpec(extra=[extra]))
        capsys.readouterr()
        assert main(["ingest", str(log), "-o", str(tmp_path / name), "--quiet"]) == 2
        err = capsys.readouterr().err.strip()
        assert "\n" not in err and len(err) < 400, err[:400]
        assert extra[0] in err and f"{len(huge)} bytes ('xxxx" in err
        assert f"more than the {MAX_FRAME_ID_BYTES}" in err
