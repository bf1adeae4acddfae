"""`surgrecon info --write-config` writes a config that ingest runs with as written, for logs
in every pose convention of `surgrecon simulate --poses` and every encoding, for logs
without a robot or joints, with a world frame other than "world", and for bag and
split-file folders; the printed pose chains say how ingest composes each pose.

The logs are `simulate`'s messages (rendered once) rewritten by its conventions
(sim/conventions.py) and written by its writer, as `simulate` does, without the ground truth.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from surgrecon_cli.cli.main import main
from surgrecon_cli.config import TopicsConfig, load_config
from surgrecon_cli.sim.conventions import CONVENTIONS
from surgrecon_cli.sim.log_writer import write_log
from surgrecon_cli.sim.scene import SimConfig
from surgrecon_cli.sim.simulate import LogBuilder

SMALL = SimConfig(cameras=3, frames=3, width=160, height=120, seed=3)


@pytest.fixture(scope="module")
def messages() -> list:
    return list(LogBuilder(SMALL).messages())


def _write(path: Path, messages: list, convention: str = "topics", encoding: str = "ros2",
           then: Callable[[Iterator], Iterator] | None = None) -> Path:
    rewrite = CONVENTIONS[convention].rewrite
    stream = rewrite(iter(messages)) if rewrite is not None else iter(messages)
    write_log(path, list(then(stream) if then is not None else stream), encoding)
    return path


def _info(capsys, log: Path, *args: str) -> str:
    assert main(["info", str(log), *args]) == 0
    return capsys.readouterr().out


def _write_config_and_ingest(capsys, log: Path, tmp_path: Path, *extra: str
                             ) -> tuple[str, Path, int]:
    """`info LOG --write-config` (its output), the config, and ingest's exit code with it."""
    cfg = tmp_path / "cfg.toml"
    out = _info(capsys, log, "--write-config", str(cfg))
    rc = main(["ingest", str(log), "-o", str(tmp_path / "run"), "--config", str(cfg), "-q",
               *extra])
    return out, cfg, rc


def _topics(convention: str) -> TopicsConfig:
    """The [topics] that `simulate --poses CONVENTION` says to ingest with."""
    sets = [s for s in CONVENTIONS[convention].settings if s.startswith("topics.")]
    return load_config(None, sets).topics


@pytest.mark.parametrize("encoding", ["ros2", "ros1", "foxglove-protobuf"])
@pytest.mark.parametrize("convention", ["topics", "tf", "tf-tree", "tracker-frame"])
def test_written_config_ingests_every_convention(messages, tmp_path: Path, capsys,
                                                 convention: str, encoding: str):
    log = _write(tmp_path / "log.mcap", messages, convention, encoding)
    out, cfg, rc = _write_config_and_ingest(capsys, log, tmp_path)
    assert rc == 0
    assert load_config(cfg).topics == _topics(convention)
    assert "world_frame = \"world\"" in cfg.read_text()
    assert "camera 0  " in out.split("poses in world frame 'world'")[1]
    checked = _info(capsys, log, "--config", str(cfg))
    assert "the config's [topics] find every role in this log, and every pose reaches " \
           "world_frame 'world'" in checked


def test_pose_chains_are_printed_as_ingest_composes_them(messages, tmp_path: Path, capsys):
    tree = _info(capsys, _write(tmp_path / "tree.mcap", messages, "tf-tree"))
    chains = tree.split("poses in world frame 'world'")[1].split("\n\n")[0].splitlines()[1:]
    assert chains[0].split() == [
        "camera", "0", "endoscope_0_optical", "-(static)->", "endoscope_0_marker",
        "-(dynamic", "40.0", "Hz)->", "tracker", "-(static)->", "world"]
    assert chains[3].split() == ["tool", "raven_tool_tip", "-(dynamic", "100.0", "Hz)->",
                                 "psm1_base", "-(static)->", "world"]
    tracker = _info(capsys, _write(tmp_path / "tracker.mcap", messages, "tracker-frame"))
    assert "camera 2  /navigation/endoscope_2/pose (40.0 Hz) in tracker -(static)-> world" in (
        tracker)
    assert "tool      /raven/tool_tip (100.0 Hz) in world\n" in tracker


def test_a_tool_in_an_unconnected_base_frame_needs_base_to_world(messages, tmp_path: Path,
                                                                 capsys):
    log = _write(tmp_path / "log.mcap", messages, "robot-base")
    out, cfg, rc = _write_config_and_ingest(capsys, log, tmp_path)
    assert rc == 2 and "'psm1_base'" in capsys.readouterr().err
    chains = out.split("poses in world frame")[1]
    assert "tool      /raven/tool_tip (100.0 Hz) in psm1_base" in chains
    assert "ingest needs\n            tool.base_to_world" in chains
    assert "# base_to_world = [x, y, z, qx, qy, qz, qw]" in cfg.read_text()
    # the one thing the log cannot tell is all that is missing
    base = [a for s in CONVENTIONS["robot-base"].settings for a in ("--set", s)]
    assert main(["ingest", str(log), "-o", str(tmp_path / "run"), "--config", str(cfg), "-q",
                 *base]) == 0
    assert main(["info", str(log), "--config", str(cfg), *base]) == 0
    assert "every pose reaches world_frame 'world'" in capsys.readouterr().out


@pytest.mark.parametrize(("dropped", "tool", "joints"), [
    ("/raven/", "", ""), ("/raven/joint_states", "/raven/tool_tip", ""),
    ("/raven/tool_tip", "", "/raven/joint_states")])
def test_a_log_without_robot_or_joints(messages, tmp_path: Path, capsys, dropped: str,
                                       tool: str, joints: str):
    kept = [m for m in messages if not m[0].startswith(dropped)]
    out, cfg, rc = _write_config_and_ingest(capsys, _write(tmp_path / "log.mcap", kept),
                                            tmp_path)
    assert rc == 0
    topics = load_config(cfg).topics
    assert (topics.tool_pose, topics.joint_states) == (tool, joints)
    if not tool:
        assert "tool      none (tool_pose = \"\": no robot, tool removal off)" in out


def _rename_world(stream: Iterator) -> Iterator:
    """Every pose and transform given in `world` given in `map` instead."""
    for topic, log_ns, record in stream:
        if getattr(record, "frame_id", None) == "world":
            record = replace(record, frame_id="map")
        yield topic, log_ns, record


@pytest.mark.parametrize("convention", ["topics", "tf-tree", "tracker-frame"])
def test_another_world_frame_is_written_as_a_key(messages, tmp_path: Path, capsys,
                                                 convention: str):
    log = _write(tmp_path / "log.mcap", messages, convention, then=_rename_world)
    out, cfg, rc = _write_config_and_ingest(capsys, log, tmp_path)
    assert rc == 0 and load_config(cfg).topics.world_frame == "map"
    assert "poses in world frame 'map'" in out and "  world frame   map" in out
    if convention != "tf-tree":  # the default [topics] find the topics, not the world
        assert "set topics.world_frame = 'map'" in out


def test_a_world_below_the_root_is_reached_down_the_tree(messages, tmp_path: Path, capsys):
    """The tree's root is `map` and `world` a static child of it: the chains go up to `map`
    and down (inverted) to `world`, as ingest composes them."""
    from surgrecon_cli.io.logs.records import PoseRecord

    def world_under_map(stream: Iterator) -> Iterator:
        stream = _rename_world(stream)
        first = next(stream)
        pose = PoseRecord(first[1], "map", "world", np.array([0.1, 0.0, -0.2]),
                          np.array([0.0, 0.6, 0.0, 0.8]))
        yield "/tf_static", first[1], pose
        yield first
        yield from stream

    log = _write(tmp_path / "log.mcap", messages, "tf-tree", then=world_under_map)
    out, cfg, rc = _write_config_and_ingest(capsys, log, tmp_path)
    assert rc == 0 and load_config(cfg).topics == _topics("tf-tree")
    assert "camera 1  endoscope_1_optical -(static)-> endoscope_1_marker -(dynamic 40.0 Hz)-> " \
           "tracker -(static)-> map -(static, inverted)-> world" in out


METADATA = """rosbag2_bagfile_information:
  version: 5
  storage_identifier: mcap
  relative_file_paths:
{files}
"""


NAMES = ["rec_2.mcap", "rec_10.mcap", "rec_11.mcap"]  # in natural order


def _split(folder: Path, stream: list, bag: bool) -> Path:
    """`stream` in three files NAMES in `folder`, with a rosbag2 metadata.yaml if `bag`."""
    folder.mkdir()
    for name, part in zip(NAMES, np.array_split(np.arange(len(stream)), 3), strict=True):
        write_log(folder / name, [stream[i] for i in part], "ros2")
    if bag:
        (folder / "metadata.yaml").write_text(
            METADATA.format(files="\n".join(f"    - {n}" for n in NAMES)))
    return folder


@pytest.mark.parametrize("bag", [True, False])
def test_a_bag_or_split_folder_is_described_as_one_log(messages, tmp_path: Path, capsys,
                                                       bag: bool):
    stream = list(CONVENTIONS["tf-tree"].rewrite(iter(messages)))
    single = tmp_path / "single.mcap"
    write_log(single, stream, "ros2")
    folder = _split(tmp_path / "rec", stream, bag)
    one = _info(capsys, single)
    out, cfg, rc = _write_config_and_ingest(capsys, folder, tmp_path)
    assert rc == 0 and load_config(cfg).topics == _topics("tf-tree")
    head, files, rest = out.split("\n\n", 2)
    kind = "rosbag2 bag folder, 3 files" if bag else "folder of 3 split files"
    assert head.splitlines()[0].startswith(f"{folder}: {kind}, ")
    assert head.split(", profile")[1] == one.split("\n\n")[0].split(", profile")[1]
    rows = [line.split() for line in files.splitlines()[2:]]
    assert [r[0] for r in rows] == NAMES and sum(int(r[3]) for r in rows) == len(stream)
    # the same channels, tree, roles, chains and config check
    assert rest.rsplit("\nwrote ", 1)[0] == one.split("\n\n", 1)[1].rstrip("\n")


def test_a_damaged_file_of_a_split_log_is_named(messages, tmp_path: Path, capsys):
    folder = _split(tmp_path / "rec", messages, bag=False)
    middle = folder / NAMES[1]
    middle.write_bytes(middle.read_bytes()[: middle.stat().st_size // 2])
    out = _info(capsys, folder)
    assert f"damaged log: {NAMES[1]}: valid data ends at byte" in out
    assert "ingest reads nothing after the first damage" in out
    assert "streamed 1 of 3 files (no usable index)" in out
