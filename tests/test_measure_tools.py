"""Contact and indentation per tool: the session's simulated run measured again with its
tool as a `[[tools]]` arm (a dVRK-style frame: z out of the jaws, shaft along -z) and the
`[tool]` hovering 20 mm up its shaft, against the simulator's truth."""

from __future__ import annotations

import csv
import json

import numpy as np

from surgrecon_cli.cli.cmd_measure import format_summary
from surgrecon_cli.cli.main import main
from surgrecon_cli.config import Config
from surgrecon_cli.config.schema import ExtraToolConfig
from surgrecon_cli.io.logs.ground_truth import gt_path_beside, load_ground_truth
from surgrecon_cli.io.run.atomic import write_npz
from surgrecon_cli.io.run.layout import RunLayout
from surgrecon_cli.stages.measure import DEFORMATION_COLUMNS, TOOL_COLUMNS, run_measure


def test_each_tool_has_its_contact_and_indentation(copy_run, pipeline_log):
    layout = RunLayout(copy_run)
    frames = RunLayout.ingest_frames(layout.ingest_dir)
    with np.load(frames) as z:
        arrays = {k: z[k] for k in z.files}
    real = arrays["tool_poses"]
    flipped = real @ np.diag([1.0, -1.0, -1.0, 1.0])  # z out of the tip: shaft along -z
    hovering = real.copy()
    hovering[:, :3, 3] += 0.02 * real[:, :3, 2]  # 20 mm up the shaft, never touching
    arrays.update(tool_poses=hovering, extra_tool_poses=flipped[:, None])
    write_npz(frames, **arrays)
    config = Config(tools=(ExtraToolConfig(pose="/PSM2/measured_cp", shaft_axis="-z"),))
    summary = run_measure(copy_run, config)

    truth = load_ground_truth(gt_path_beside(pipeline_log)).indentation_m
    assert truth is not None
    with layout.deformation_tools_csv.open(newline="", encoding="utf-8") as f:
        reader = csv.DictReader(f)
        assert reader.fieldnames == list(TOOL_COLUMNS)
        rows = list(reader)
    n = len(real)
    assert [(int(r["frame"]), r["tool"]) for r in rows] == [
        (k, name) for k in range(n) for name in ("tool", "tool_1")]
    arm = [r for r in rows if r["tool"] == "tool_1"]
    hover = [r for r in rows if r["tool"] == "tool"]
    assert {r["pose"] for r in arm} == {"/PSM2/measured_cp"}
    in_contact = truth > 0
    assert [r["contact"] == "1" for r in arm] == list(in_contact)
    error = np.abs([float(r["indentation_mm"]) - 1e3 * t for r, t in zip(arm, truth,
                                                                           strict=True)])
    assert np.median(error[in_contact]) <= 0.3  # the single-tool goal (test_measure.py)
    assert all(r["contact"] == "0" and float(r["clearance_mm"]) > 10 for r in hover)
    # deformation.csv keeps its columns and describes the [tool] alone: never in contact
    with layout.deformation_csv.open(newline="", encoding="utf-8") as f:
        reader = csv.DictReader(f)
        assert reader.fieldnames == list(DEFORMATION_COLUMNS)
        assert {r["contact"] for r in reader} == {"0"}
    (extra,) = summary["extra_tools"]
    assert extra["name"] == "tool_1" and extra["onset_frame"] == int(np.argmax(in_contact))
    assert abs(extra["max_indentation_mm"] - 1e3 * truth.max()) <= 0.3
    assert summary["onset_frame"] is None
    lines = format_summary(summary).splitlines()
    assert lines[0] == "no tool-tissue contact"
    assert lines[1].startswith(f"tool_1 (/PSM2/measured_cp): contact from frame "
                               f"{int(np.argmax(in_contact))} ")
    assert json.loads(layout.deformation_summary.read_text())["extra_tools"][0]["name"] == \
        "tool_1"
    assert main(["report", str(copy_run), "-q"]) == 0
    html = layout.report_html.read_text(encoding="utf-8")
    section = html[html.index('id="contact"'):]
    section = section[:section.index("</section>")]
    assert "/PSM2/measured_cp" in section and "tool_1" in section
    assert f"{int(in_contact.sum())} (frames {int(np.argmax(in_contact))}–{n - 1})" in section
