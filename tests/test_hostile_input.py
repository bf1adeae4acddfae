"""Hostile input (issue 25): bombs refused before they expand, user files never deleted,
one-line errors (exit 2) naming the file instead of crashes (exit 3).

Memory bounds are measured in a child process (peak RSS from getrusage, generous caps; the
child's address space is limited too, so that a regression fails instead of swapping)."""

from __future__ import annotations

import json
import os
import struct
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from surgrecon_cli.cli.main import main
from surgrecon_cli.errors import InputError
from surgrecon_cli.io.logs.images import MAX_IMAGE_PIXELS, prepare_image
from surgrecon_cli.io.logs.log_input import resolve_log
from surgrecon_cli.io.logs.records import ImageRecord

MEMORY_CAP_MB = 1024


def peak_rss_mb(code: str, *args: str) -> tuple[float, str]:
    """Run `code` in a child process (address space capped at 4 GiB); its peak RSS in MB
    and what it printed."""
    prologue = ("import resource, sys\n"
                "resource.setrlimit(resource.RLIMIT_AS, (4 << 30, 4 << 30))\n")
    epilogue = "\nprint(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)\n"
    proc = subprocess.run([sys.executable, "-c", prologue + code + epilogue, *args],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    *printed, peak = proc.stdout.strip().splitlines()
    return float(peak), "\n".join(printed)


# ---- finding 2: YAML bombs and odd metadata.yaml ------------------------------------------
BILLION_LAUGHS = """rosbag2_bagfile_information:
  storage_identifier: mcap
  relative_file_paths: &i [&h [&g [&f [&e [&d [&c [&b [&a ["lol","lol","lol","lol","lol",
    "lol","lol","lol","lol"],*a,*a,*a,*a,*a,*a,*a,*a],*b,*b,*b,*b,*b,*b,*b,*b],*c,*c,*c,*c,
    *c,*c,*c,*c],*d,*d,*d,*d,*d,*d,*d,*d],*e,*e,*e,*e,*e,*e,*e,*e],*f,*f,*f,*f,*f,*f,*f,*f],
    *g,*g,*g,*g,*g,*g,*g,*g],*h,*h,*h,*h,*h,*h,*h,*h]
"""


def test_yaml_bomb_in_metadata_is_refused_before_it_expands(tmp_path: Path):
    (tmp_path / "metadata.yaml").write_text(BILLION_LAUGHS)
    peak, printed = peak_rss_mb(
        "from surgrecon_cli.io.logs.log_input import resolve_log\n"
        "from surgrecon_cli.errors import InputError\n"
        "try:\n    resolve_log(sys.argv[1])\nexcept InputError as exc:\n    print(exc)\n",
        str(tmp_path))
    assert "aliases are not accepted" in printed and "metadata.yaml" in printed
    assert len(printed.splitlines()) == 1
    assert peak < MEMORY_CAP_MB


@pytest.mark.parametrize("paths", ["[[a.mcap]]", "[{a: b}]", "a.mcap", "[1]"])
def test_relative_file_paths_must_be_plain_names(tmp_path: Path, paths: str):
    (tmp_path / "metadata.yaml").write_text(
        f"rosbag2_bagfile_information:\n  relative_file_paths: {paths}\n")
    with pytest.raises(InputError, match="list of file names"):
        resolve_log(tmp_path)


def test_symlink_loop_in_metadata_paths_is_one_line(tmp_path: Path, capsys):
    (tmp_path / "loop.mcap").symlink_to(tmp_path / "loop.mcap")
    (tmp_path / "metadata.yaml").write_text(
        "\ufeffrosbag2_bagfile_information:\n  relative_file_paths: [loop.mcap]\n")
    assert main(["info", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "symbolic link loop" in err and "loop.mcap" in err


# ---- finding 3: the image pixel limit cannot be bypassed ----------------------------------
def crafted_jpeg(width: int, height: int, stray: bytes = b"\x00") -> bytes:
    """A small valid JPEG whose SOF0 claims width x height, `stray` bytes before SOF0."""
    _ok, buf = cv2.imencode(".jpg", np.full((8, 8, 3), 128, np.uint8))
    data = bytearray(buf.tobytes())
    sof = data.find(b"\xff\xc0")
    data[sof + 5: sof + 9] = struct.pack(">HH", height, width)
    return bytes(data[:sof]) + stray + bytes(data[sof:])


@pytest.mark.parametrize("stray", [b"", b"\x00", b"\x17\x42", b"\xff\xff"])
def test_jpeg_claiming_too_many_pixels_is_refused_before_decoding(stray: bytes):
    data = crafted_jpeg(30000, 30000, stray)
    with pytest.raises(ValueError, match="30000x30000"):
        prepare_image(ImageRecord(0, "cam", "jpeg", data))


def test_crafted_images_stay_under_the_memory_cap(tmp_path: Path):
    """The stray-byte JPEG and a BMP (a codec surgrecon does not parse itself) claiming
    0.9 Gpx: refused without decoding them."""
    bmp = (b"BM" + struct.pack("<IHHI", 64, 0, 0, 54)
           + struct.pack("<IiiHHIIiiII", 40, 30000, 30000, 1, 24, 0, 0, 0, 0, 0, 0)
           + bytes(10))
    for k, data in enumerate((crafted_jpeg(30000, 30000), bmp)):
        (tmp_path / f"{k}.bin").write_bytes(data)
    peak, printed = peak_rss_mb(
        "from pathlib import Path\n"
        "from surgrecon_cli.io.logs.images import prepare_image\n"
        "from surgrecon_cli.io.logs.records import ImageRecord\n"
        "for path in sorted(Path(sys.argv[1]).glob('*.bin')):\n"
        "    try:\n"
        "        prepare_image(ImageRecord(0, 'cam', '', path.read_bytes()))\n"
        "    except ValueError as exc:\n"
        "        print('refused', exc)\n", str(tmp_path))
    assert [line.split()[0] for line in printed.splitlines()] == ["refused"] * 2, printed
    assert peak < MEMORY_CAP_MB


def test_pixel_limit_matches_opencv_decode_limit():
    assert int(os.environ["OPENCV_IO_MAX_IMAGE_PIXELS"]) == MAX_IMAGE_PIXELS
    _ok, buf = cv2.imencode(".jpg", np.zeros((480, 640, 3), np.uint8))
    assert prepare_image(ImageRecord(0, "cam", "jpeg", buf.tobytes())).width == 640


# ---- finding 8: never delete what surgrecon did not write ---------------------------------
def test_ingest_keeps_user_files_in_the_output_folder(pipeline_log: Path, tmp_path: Path,
                                                      capsys):
    out = tmp_path / "out"
    (out / ".ingest-notes").mkdir(parents=True)
    (out / ".ingest-notes" / "todo.txt").write_text("mine")
    (out / ".draft.tmp").write_text("mine too")
    assert main(["ingest", str(pipeline_log), "-o", str(out), "-q"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "did not write" in err
    assert (out / ".draft.tmp").read_text() == "mine too"
    assert (out / ".ingest-notes" / "todo.txt").read_text() == "mine"
    assert sorted(p.name for p in out.iterdir()) == [".draft.tmp", ".ingest-notes"]  # no trace


def test_ingest_removes_only_its_own_leftovers(pipeline_log: Path, tmp_path: Path):
    out = tmp_path / "out"
    (out / ".ingest-0123456789ab" / "staged").mkdir(parents=True)
    (out / ".run.json.ab12cd_9.tmp").write_text("{")
    assert main(["ingest", str(pipeline_log), "-o", str(out), "-q"]) == 0
    assert json.loads((out / "run.json").read_text())["stages"]["ingest"]["status"] == "done"
    assert sorted(p.name for p in out.iterdir() if p.name.startswith(".")) == [
        ".surgrecon.lock"]


# ---- finding 7: crashes that are one-line errors (or handled) -----------------------------
def test_first_joint_state_without_joints_is_skipped(tmp_path: Path, capsys):
    import dataclasses

    import synth_log

    def empty_first(messages):
        first = min((i for i, m in enumerate(messages)
                     if isinstance(m[2], synth_log.JointStateRecord)), key=lambda i: messages[i][1])
        topic, t, rec = messages[first]
        messages[first] = (topic, t, dataclasses.replace(rec, names=(), positions=np.zeros(0)))
        return messages

    log = synth_log.write(tmp_path / "log.mcap", synth_log.SynthSpec(mutate=empty_first))
    assert main(["ingest", str(log), "-o", str(tmp_path / "run"), "-q"]) == 0
    assert "joint state without joints" in capsys.readouterr().err
    data = np.load(tmp_path / "run" / "ingest" / "frames.npz")
    assert data["joint_positions"].shape[1] == len(synth_log.JOINTS)
    assert np.isfinite(data["joint_positions"]).all()


def test_log_named_dot_and_foreign_run_json(pipeline_log: Path, tmp_path: Path, capsys,
                                            monkeypatch):
    bag = tmp_path / "bag"
    bag.mkdir()
    (bag / "rec.mcap").symlink_to(pipeline_log)
    monkeypatch.chdir(bag)
    assert main(["ingest", ".", "-o", str(tmp_path / "run"), "-q"]) == 0
    other = tmp_path / "other"
    other.mkdir()
    for text in ('{"tool": "x"}', '{"surgrecon": "0.1.0", "stages": [1]}',
                 '{"surgrecon": "0.1.0", "stages": {"ingest": "done"}}'):
        (other / "run.json").write_text(text)
        for command in (["run", "."], ["ingest", "."]):
            assert main([*command, "-o", str(other), "-q"]) == 2
            err = capsys.readouterr().err.strip()
            assert len(err.splitlines()) == 1 and "not a surgrecon run.json" in err, err
        assert (other / "run.json").read_text() == text  # never overwritten


def test_full_disk_and_unusable_output_folders_name_the_file(copy_run: Path, pipeline_log: Path,
                                                             monkeypatch, capsys):
    import errno

    import surgrecon_cli.io.run.atomic as atomic

    def full(_fd: int) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(atomic.os, "fsync", full)
    assert main(["report", str(copy_run), "-q"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "No space left on device" in err
    assert str(copy_run) in err  # the file that could not be written
    monkeypatch.undo()
    for out in (os.devnull, "/proc/surgrecon-test/run"):
        assert main(["run", str(pipeline_log), "-o", out, "-q"]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and out in err, err


# ---- finding 9: TF problems on frames nobody uses are warnings ----------------------------
TF_CONFIG = ('[topics]\ncamera_pose = "/tf"\ncamera_frame = "endoscope_{camera}_optical"\n'
             'tool_pose = "/tf"\ntool_frame = "raven_tool_tip"\n')


def test_tf_problems_on_unused_frames_warn_and_ingest_succeeds(tmp_path: Path, capsys):
    import synth_log
    from synth_log import MS, T0

    def pose(parent: str, child: str, xyz=(0.0, 0.0, 0.0)):
        return ("/tf", T0 + 5 * MS, synth_log.PoseRecord(T0, parent, child, np.array(xyz),
                                                         np.array([0.0, 0, 0, 1])))

    extra = [pose("world", "gripper", (np.nan, 0, 0)), pose("world", "base"),
             pose("map", "base"), pose("loop_a", "loop_b"), pose("loop_b", "loop_a")]
    log = synth_log.write(tmp_path / "log.mcap", synth_log.SynthSpec(tf_topic="/tf",
                                                                     extra=extra))
    config = tmp_path / "tf.toml"
    config.write_text(TF_CONFIG)
    assert main(["ingest", str(log), "-o", str(tmp_path / "run"), "--config", str(config),
                 "-q"]) == 0
    err = capsys.readouterr().err
    assert "'gripper'" in err and "non-finite" in err
    assert "'base' has 2 parents" in err and "cycle" in err and "np.str_" not in err
    # the same problem on a frame a camera needs stays an error, in one line
    config.write_text(TF_CONFIG.replace("endoscope_{camera}_optical", "gripper"))
    assert main(["ingest", str(log), "-o", str(tmp_path / "run2"), "--config", str(config),
                 "-q"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("error: camera 0") and "non-finite" in err[-1]


def test_negative_stamp_is_called_negative(tmp_path: Path, capsys):
    import dataclasses

    import synth_log

    def negative(messages):
        topic, t, rec = next(m for m in messages if isinstance(m[2], synth_log.PoseRecord))
        messages.append((topic, t + 1, dataclasses.replace(rec, stamp_ns=-5)))
        return messages

    log = synth_log.write(tmp_path / "log.mcap", synth_log.SynthSpec(mutate=negative))
    main(["ingest", str(log), "-o", str(tmp_path / "run"), "-q"])
    err = capsys.readouterr().err
    assert "negative header stamp" in err and "zero header stamp" not in err


def test_long_names_in_errors_are_cut():
    from surgrecon_cli.core.sync.tf_samples import make_samples
    from surgrecon_cli.core.sync.tf_tree import build_tf_tree
    from surgrecon_cli.errors import NAME_LIMIT

    huge = "f" * 5_000_000
    tree = build_tf_tree(make_samples(["world"], [huge], [0], [[0, 0, 0]], [[0, 0, 0, 1]]))
    with pytest.raises(InputError) as exc:
        tree.lookup("map", huge, np.array([0]), 1)
    assert len(str(exc.value)) < 4 * NAME_LIMIT + 200 and "characters)" in str(exc.value)
