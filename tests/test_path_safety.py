"""Names taken from a log (topic names, frame ids, camera ids captured by `{camera}`) never
become paths: whatever they hold (`..`, absolute paths, backslashes, NUL bytes, newlines,
thousands of characters, HTML), nothing is written outside the run folder, the ids are stored
as data (files are named by camera index), and a run either works or fails with one line.

A camera id cannot contain `/` (`{camera}` captures `[^/]+`), so the path-like ids here are
`..`, `.`, `C:\\x`, `\\..\\..\\x`; whole topic names and frame ids carry `/../../x` and
absolute paths.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest
import synth_log
from synth_log import SynthSpec

from surgrecon_cli.cli.main import main
from surgrecon_cli.config import Config, TopicsConfig, load_config
from surgrecon_cli.io.logs.reader import LogReader
from surgrecon_cli.io.logs.records import ImageRecord, PoseRecord
from surgrecon_cli.io.run.folder import RunFolder
from surgrecon_cli.io.run.ingest_store import load_ingested
from surgrecon_cli.io.run.ply import read_ply
from surgrecon_cli.sim.log_writer import write_log

ID_PAIRS = [
    ("..", "."),
    ("\x00", "a\x00b"),
    ("\\..\\..\\x", "C:\\x"),
    ("x" * 4000, "~"),
    ("\n", "<b>&amp;"),
    ("é", "{camera}"),
    ("-rf", " "),
    ("0", "00"),
]
ENCODINGS = ("ros2", "foxglove-json", "ros1", "foxglove-protobuf")


def tree(root: Path) -> dict[str, tuple[bool, int, int]]:
    """Every path under `root` (relative) -> (is_dir, size, mtime_ns)."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            path = Path(dirpath) / name
            st = path.lstat()
            out[str(path.relative_to(root))] = (path.is_dir(), st.st_size, st.st_mtime_ns)
    return out


def changed_outside(before: dict, after: dict, allowed: str) -> list[str]:
    """Paths created, changed or deleted that are not `allowed` or under it."""
    paths = {p for p in set(before) | set(after) if before.get(p) != after.get(p)}
    return sorted(p for p in paths if p != allowed and not p.startswith(allowed + os.sep))


def toml_string(value: str) -> str:
    return json.dumps(value)  # JSON string escapes are valid TOML basic-string escapes


def assert_one_line_error(capsys) -> str:
    """The one error line (returned with its details, the indented lines after it, one
    item each): a name with line breaks never breaks a line."""
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    starts = [k for k, ln in enumerate(err) if ln.startswith("error:")]
    assert len(starts) == 1 and "Traceback" not in "\n".join(err), err
    details = err[starts[0] + 1:]
    assert all(ln.startswith("  ") and not ln[2:].startswith(" ") for ln in details), err
    return " | ".join(err[starts[0]:])


def _weird_log(path: Path, ids: tuple[str, str], encoding: str, outside: Path,
               transforms: bool) -> tuple[Path, str]:
    """A 2-camera log whose camera ids are `ids`; tool and joint topics and every frame id
    are path-like. Returns the log and a [topics] config for it."""
    tool_topic = "/../../tool" if not transforms else "/tf"
    joint_topic = f"{outside}/joints\x00/../x"
    spec = SynthSpec(cameras=(0, 1), frames=3, image_topic="/cam{c}/image",
                     info_topic="/cam{c}/info", pose_topic="/nav/cam{c}/pose",
                     tool_topic=tool_topic, joint_topic=joint_topic,
                     tf_topic="/tf" if transforms else None, camera_frame="opt{c}",
                     tool_frame=f"{outside}/tool_frame")

    def rename(messages):
        out = []
        for topic, t, rec in messages:
            for c, cid in enumerate(ids):
                topic = topic.replace(f"/cam{c}/", f"/cam{cid}/")
            if isinstance(rec, PoseRecord) and rec.child_frame_id.startswith("opt"):
                c = int(rec.child_frame_id[3:])
                rec = PoseRecord(rec.stamp_ns, "/../../world", f"opt{ids[c]}", rec.position,
                                 rec.orientation)
            elif isinstance(rec, ImageRecord):
                rec = ImageRecord(rec.stamp_ns, f"{outside}/frame", rec.format, rec.data,
                                  rec.width, rec.height, rec.step)
            out.append((topic, t, rec))
        return out

    spec.mutate = rename
    synth_log.write(path, spec, encoding)
    config = "\n".join([
        "[topics]",
        f"image = {toml_string('/cam{camera}/image')}",
        f"camera_info = {toml_string('/cam{camera}/info')}",
        f"camera_pose = {toml_string('/tf' if transforms else '/nav/cam{camera}/pose')}",
        f"camera_frame = {toml_string('opt{camera}')}",
        f"tool_pose = {toml_string(tool_topic)}",
        f"tool_frame = {toml_string(f'{outside}/tool_frame')}",
        f"joint_states = {toml_string(joint_topic)}",
    ]) + "\n"
    return path, config


@pytest.mark.parametrize("k", range(len(ID_PAIRS)))
def test_ingest_keeps_names_as_data(tmp_path: Path, capsys, k: int):
    ids = ID_PAIRS[k]
    inputs, outside = tmp_path / "inputs", tmp_path / "outside"
    inputs.mkdir()
    log, config = _weird_log(inputs / "log.mcap", ids, ENCODINGS[k % len(ENCODINGS)],
                             outside, transforms=k % 2 == 1)
    (inputs / "topics.toml").write_text(config, encoding="utf-8")
    run = tmp_path / "run"
    before = tree(tmp_path)
    rc = main(["ingest", str(log), "-o", str(run), "--config", str(inputs / "topics.toml"),
               "-q"])
    assert changed_outside(before, tree(tmp_path), "run") == []
    assert not outside.exists()
    if rc != 0:
        assert rc == 2
        assert_one_line_error(capsys)
        return
    meta = RunFolder(run).read()
    assert meta["ingest"]["cameras"] == sorted(ids)
    ingested = load_ingested(run / "ingest")
    assert ingested.cameras == tuple(sorted(ids)) and ingested.n_frames == 3
    assert sorted(p.name for p in (run / "ingest" / "images").iterdir()) == ["00", "01"]
    assert all(p.name[:6].isdigit() for p in (run / "ingest" / "images").rglob("*.*"))
    report = json.loads((run / "ingest" / "cameras.json").read_text(encoding="utf-8"))
    assert sorted(report["report"]["cameras"]) == sorted(ids)
    # the run's config.toml reads back as the config that was used, names and all
    used = load_config(inputs / "topics.toml", ())
    assert load_config(run / "config.toml", ()) == used


def test_bad_names_in_errors_stay_on_one_line(tmp_path: Path, capsys):
    """A missing role lists the log's topics: names with newlines and NULs stay one line."""
    ids = ("a\nb", "\x00\r\n")
    log, _ = _weird_log(tmp_path / "log.mcap", ids, "ros2", tmp_path / "outside", False)
    rc = main(["ingest", str(log), "-o", str(tmp_path / "run"), "-q"])  # default topics
    assert rc == 2
    line = assert_one_line_error(capsys)
    assert "/cama\\nb/image" in line


def _renamed_pipeline_log(source: Path, path: Path, ids: list[str]) -> Path:
    """`source` (the simulator's 6-camera log) with camera c renamed to ids[c]."""
    reader = LogReader(source, TopicsConfig())
    messages = []
    for item in reader:
        topic = item.topic
        if item.camera:
            new = ids[int(item.camera)]
            topic = topic.replace(f"endoscope_{item.camera}/", f"endoscope_{new}/")
        messages.append((topic, item.log_time_ns, item.record))
    write_log(path, messages, "ros2")
    return path


def test_whole_run_with_hostile_camera_ids(pipeline_log: Path, tmp_path: Path, capsys):
    ids = ["..", "\x00", "<img src=x onerror=alert(1)>", "x" * 300, "C:\\x", "~"]
    inputs = tmp_path / "inputs"
    inputs.mkdir()
    log = _renamed_pipeline_log(pipeline_log, inputs / "log.mcap", ids)
    run = tmp_path / "run"
    before = tree(tmp_path)
    rc = main(["run", str(log), "-o", str(run), "-q"])
    assert changed_outside(before, tree(tmp_path), "run") == []
    assert rc == 0, capsys.readouterr().err
    meta = RunFolder(run).read()
    assert meta["ingest"]["cameras"] == sorted(ids)
    assert all(meta["stages"][s]["status"] == "done"
               for s in ("ingest", "build-template", "register", "classify", "report"))
    assert sorted(p.name for p in (run / "ingest" / "images").iterdir()) == [
        f"{c:02d}" for c in range(6)]
    assert len(read_ply(run / "clouds" / "000005.ply")["x"]) > 100
    html = (run / "report.html").read_text(encoding="utf-8")
    assert "<img src=x onerror=alert(1)>" not in html
    assert load_config(run / "config.toml", ()) == Config()
