"""A recording split over several files is one log: a rosbag2 bag folder (metadata.yaml and
its .mcap files) or a folder of split files ingests exactly as the same messages in one
file; its identity is the hash of its files in order."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from surgrecon_cli.cli.main import main
from surgrecon_cli.io.logs.log_input import resolve_log
from surgrecon_cli.io.run.folder import RunFolder, file_sha256
from surgrecon_cli.io.run.ingest_store import load_ingested
from surgrecon_cli.sim.log_writer import write_log
from surgrecon_cli.sim.scene import SimConfig
from surgrecon_cli.sim.simulate import LogBuilder

CFG = SimConfig(cameras=3, frames=4, width=160, height=120, seed=5)
METADATA = """rosbag2_bagfile_information:
  version: 5
  storage_identifier: {storage}
  relative_file_paths:
{files}
  duration:
    nanoseconds: 1
"""


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory):
    """The same messages as one file and split in three (by log time), plus one ingest of
    the single file."""
    root = tmp_path_factory.mktemp("bag")
    messages = list(LogBuilder(CFG).messages())
    single = root / "single.mcap"
    write_log(single, messages, "ros2")
    parts = np.array_split(np.arange(len(messages)), 3)
    split = []
    for k, part in enumerate(parts):
        split.append(root / "bag" / f"bag_{k}.mcap")
        split[-1].parent.mkdir(exist_ok=True)
        write_log(split[-1], [messages[i] for i in part], "ros2")
    assert main(["ingest", str(single), "-o", str(root / "run"), "-q"]) == 0
    return root, split, load_ingested(root / "run" / "ingest")


def _same(run: Path, want) -> None:
    got = load_ingested(run / "ingest")
    np.testing.assert_array_equal(got.image_stamps_ns, want.image_stamps_ns)
    np.testing.assert_array_equal(got.poses, want.poses)
    np.testing.assert_array_equal(got.tool_poses, want.tool_poses)
    for c in range(len(want.cameras)):
        np.testing.assert_array_equal(got.load_image(2, c), want.load_image(2, c))


def _metadata(folder: Path, files: list[Path], storage: str = "mcap") -> None:
    listed = "\n".join(f"    - {f.name}" for f in files)
    (folder / "metadata.yaml").write_text(METADATA.format(storage=storage, files=listed))


def test_a_bag_folder_is_one_log(recording, tmp_path: Path):
    _, split, want = recording
    folder = split[0].parent
    _metadata(folder, split)
    run = tmp_path / "run"
    assert main(["ingest", str(folder), "-o", str(run), "-q"]) == 0
    _same(run, want)
    concatenated = tmp_path / "all.bin"
    concatenated.write_bytes(b"".join(p.read_bytes() for p in split))
    assert RunFolder(run).input_hash == file_sha256(concatenated) == resolve_log(folder).sha256()


def test_split_files_without_metadata_in_natural_order(recording, tmp_path: Path):
    _, split, want = recording
    folder = tmp_path / "rec"
    folder.mkdir()
    for k, path in enumerate(split):  # rec_2 must come before rec_10
        (folder / f"rec_{[2, 10, 11][k]}.mcap").write_bytes(path.read_bytes())
    assert [p.name for p in resolve_log(folder).files] == ["rec_2.mcap", "rec_10.mcap",
                                                           "rec_11.mcap"]
    assert main(["ingest", str(folder), "-o", str(tmp_path / "run"), "-q"]) == 0
    _same(tmp_path / "run", want)


def test_bad_bag_folders_are_refused_in_one_line(recording, tmp_path: Path, capsys):
    _, split, _ = recording
    sqlite = tmp_path / "sqlite_bag"
    sqlite.mkdir()
    _metadata(sqlite, split, storage="sqlite3")
    missing = tmp_path / "missing_bag"
    missing.mkdir()
    _metadata(missing, split)
    empty = tmp_path / "empty"
    empty.mkdir()
    for folder, message in ((sqlite, "not a .db3 file"), (missing, "missing from"),
                            (empty, "without metadata.yaml")):
        assert main(["ingest", str(folder), "-o", str(tmp_path / f"run_{folder.name}"),
                     "-q"]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and message in err, err
