"""PLY writer/reader: round trips through plyfile and Open3D, strict rejection of bad files,
and the `register-pair` command end to end."""

from __future__ import annotations

import numpy as np
import plyfile
import pytest

from surgrecon_cli.errors import InputError
from surgrecon_cli.io.run.ply import read_ply, read_ply_counted, write_cloud_ply


def cloud(n: int = 200, seed: int = 0):
    rng = np.random.default_rng(seed)
    xyz = rng.normal(0, 0.02, (n, 3))
    rgb = rng.integers(0, 256, (n, 3)).astype(np.uint8)
    return xyz, rgb


def test_round_trip_with_plyfile_and_open3d(tmp_path):
    xyz, rgb = cloud()
    n = len(xyz)
    ids = np.arange(n, dtype=np.int64) * 3
    label = np.tile(np.array([0, 1, 2, 255], np.uint8), n // 4)
    residual = np.linspace(0, 1e-3, n)
    extra = {"correspondence": np.arange(n) - 5, "outlier": np.arange(n) % 2 == 0,
             "score": np.linspace(0, 1, n)}
    path = tmp_path / "c.ply"
    assert write_cloud_ply(path, xyz, rgb, ids, label, residual, extra) == 0
    assert [p.name for p in tmp_path.iterdir()] == ["c.ply"]  # no temporary left behind

    ours = read_ply(path)
    np.testing.assert_allclose(ours["x"], xyz[:, 0].astype(np.float32))
    assert ours["x"].dtype == np.float32 and ours["point_id"].dtype == np.int32
    assert np.array_equal(ours["red"], rgb[:, 0]) and np.array_equal(ours["point_id"], ids)
    assert np.array_equal(ours["correspondence"], extra["correspondence"])
    assert ours["outlier"].dtype == np.uint8 and ours["score"].dtype == np.float32

    data = plyfile.PlyData.read(str(path))
    assert data.text is False and data.byte_order == "<"
    v = data["vertex"].data
    names = list(v.dtype.names)
    assert names[:10] == ["x", "y", "z", "red", "green", "blue", "point_id", "label", "residual",
                          "scalar_label"]
    assert [v.dtype[k].str for k in names[:10]] == (["<f4"] * 3 + ["|u1"] * 3
                                                    + ["<i4", "|u1", "<f4", "<f4"])
    assert np.array_equal(v["label"], label) and np.array_equal(v["scalar_label"], label)
    np.testing.assert_allclose(v["residual"], residual, rtol=1e-6)
    documented = {c.split(":")[0] for c in data.comments}
    assert "written by surgrecon" in data.comments and set(names) <= documented

    o3d = pytest.importorskip("open3d")
    pc = o3d.io.read_point_cloud(str(path))
    np.testing.assert_allclose(np.asarray(pc.points), xyz, atol=1e-8)
    np.testing.assert_allclose(np.asarray(pc.colors), rgb / 255.0, atol=1e-6)


def test_defaults_and_non_finite_points_dropped(tmp_path):
    xyz, _ = cloud(10)
    xyz[3, 1] = np.nan
    xyz[7, 0] = np.inf
    path = tmp_path / "d.ply"
    assert write_cloud_ply(path, xyz) == 2
    out = read_ply(path)
    assert len(out["x"]) == 8
    assert np.array_equal(out["point_id"], [0, 1, 2, 4, 5, 6, 8, 9])  # ids survive the drop
    assert np.all(out["label"] == 255) and np.all(out["residual"] == 0)
    assert np.all(out["red"] == 128)


def test_nan_residual_and_sigma_are_kept_only_positions_drop(tmp_path):
    xyz, _ = cloud(6)
    xyz[2, 2] = np.nan
    residual = np.array([0.001, np.nan, 0.002, np.nan, 0.0, 0.003])
    sigma = np.array([np.nan, 0.001, 0.001, 0.002, np.nan, 0.001])
    path = tmp_path / "n.ply"
    assert write_cloud_ply(path, xyz, residual=residual, extra={"sigma": sigma}) == 1
    out, dropped = read_ply_counted(path)
    assert dropped == 0 and list(out["point_id"]) == [0, 1, 3, 4, 5]
    np.testing.assert_array_equal(out["residual"], residual[[0, 1, 3, 4, 5]].astype(np.float32))
    np.testing.assert_array_equal(out["sigma"], sigma[[0, 1, 3, 4, 5]].astype(np.float32))


def test_rewrite_of_a_read_cloud_rederives_scalar_label(tmp_path):
    """As classify's relabelling does: every read property but the spec's columns goes back
    as an extra, `scalar_label` included, and follows the new labels."""
    xyz, rgb = cloud(8)
    path = tmp_path / "r.ply"
    write_cloud_ply(path, xyz, rgb, extra={"views": np.full(8, 2, np.uint8)})
    cloud_in = read_ply(path)
    spec = ("x", "y", "z", "red", "green", "blue", "point_id", "label", "residual")
    extra = {k: v for k, v in cloud_in.items() if k not in spec}
    assert set(extra) == {"scalar_label", "views"}
    labels = np.arange(8, dtype=np.uint8) % 3
    write_cloud_ply(path, xyz, rgb, label=labels, extra=extra)
    out = read_ply(path)
    assert np.array_equal(out["scalar_label"], labels) and out["scalar_label"].dtype == np.float32
    assert np.array_equal(out["views"], extra["views"])


@pytest.mark.parametrize("text,byte_order", [(True, "="), (False, ">"), (False, "<")])
def test_reads_ascii_and_both_endians_skipping_faces(tmp_path, text, byte_order):
    xyz, rgb = cloud(12)
    vert = np.empty(12, dtype=[("x", "f8"), ("y", "f8"), ("z", "f8"), ("red", "u1"),
                               ("green", "u1"), ("blue", "u1"), ("quality", "i2")])
    for i, k in enumerate("xyz"):
        vert[k] = xyz[:, i]
    vert["red"], vert["green"], vert["blue"] = rgb.T
    vert["quality"] = np.arange(12) - 6
    faces = np.empty(3, dtype=[("vertex_indices", "O")])
    faces["vertex_indices"] = [np.array([0, 1, 2], "i4"), np.array([2, 3, 4, 5], "i4"),
                               np.array([6, 7, 8], "i4")]
    for first in ("face", "vertex"):  # faces before and after the vertices
        els = [plyfile.PlyElement.describe(faces, "face"),
               plyfile.PlyElement.describe(vert, "vertex")]
        if first == "vertex":
            els.reverse()
        path = tmp_path / f"{first}.ply"
        plyfile.PlyData(els, text=text, byte_order=byte_order).write(str(path))
        out = read_ply(path)
        np.testing.assert_allclose(np.c_[out["x"], out["y"], out["z"]], xyz)
        assert np.array_equal(out["quality"], vert["quality"]) and out["quality"].dtype == np.int16
        assert np.array_equal(out["blue"], rgb[:, 2])


def _write(tmp_path, header: str, body: bytes = b"") -> str:
    path = tmp_path / "bad.ply"
    path.write_bytes(header.encode() + body)
    return str(path)


GOOD_HEAD = "ply\nformat binary_little_endian 1.0\nelement vertex {n}\n" \
            "property float x\nproperty float y\nproperty float z\nend_header\n"


@pytest.mark.parametrize("header,body,message", [
    ("PLY\n", b"", "magic"),
    ("ply\nformat binary_middle_endian 1.0\nelement vertex 1\nend_header\n", b"", "format"),
    ("ply\nformat ascii 1.0\nelement vertex 1\nproperty float128 x\nend_header\n", b"", "type"),
    (GOOD_HEAD.format(n=10), np.zeros(3 * 5, "<f4").tobytes(), "truncated"),
    (GOOD_HEAD.format(n=10**12), np.zeros(3, "<f4").tobytes(), "truncated"),
    (GOOD_HEAD.format(n=0), b"", "empty"),
    ("ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
     "property float z\nend_header\n", b"1 2 3\n4 5\n", "truncated|values"),
    ("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
     "property float z\nend_header\n", b"1 2 abc\n", "non-numeric"),
    ("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n", b"1\n", "x, y, z"),
    (GOOD_HEAD.format(n=-3), np.zeros(3, "<f4").tobytes(), "-3 records"),
    ("ply\nformat ascii 1.0\ncomment \u00e9\nelement vertex 1\nproperty float x\n"
     "property float y\nproperty float z\nend_header\n", b"1 2 3\n", "non-ASCII"),
    ("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
     "property uchar z\nend_header\n", b"1 2 300\n", "out of range"),
    ("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n", b"", "end_header"),
    ("ply\nformat ascii 1.0\nelement face 1\nproperty list uchar int vertex_indices\n"
     "end_header\n", b"3 0 1 2\n", "no vertex"),
])
def test_bad_files_raise_input_error_naming_the_file(tmp_path, header, body, message):
    path = _write(tmp_path, header, body)
    with pytest.raises(InputError, match=message) as info:
        read_ply(path)
    assert "bad.ply" in str(info.value) and "\n" not in str(info.value)


def test_nan_coordinates_dropped_and_counted(tmp_path):
    pts = np.array([[0, 0, 0], [np.nan, 1, 1], [1, 2, 3]], "<f4")
    path = _write(tmp_path, GOOD_HEAD.format(n=3), pts.tobytes())
    out, dropped = read_ply_counted(path)
    assert dropped == 1 and len(out["x"]) == 2
    all_nan = _write(tmp_path, GOOD_HEAD.format(n=1), np.full(3, np.nan, "<f4").tobytes())
    with pytest.raises(InputError, match="finite"):
        read_ply(all_nan)


def test_missing_file(tmp_path):
    with pytest.raises(InputError, match="cannot read"):
        read_ply(tmp_path / "nope.ply")


# ----------------------------------------------------------------------------- CLI
def _dome_pair(n: int = 1500):
    from test_registration import make

    src, tgt, srgb, trgb, truth, order = make(n, seed=21)
    return src, tgt, (srgb * 255).astype(np.uint8), (trgb * 255).astype(np.uint8), truth, order


def test_register_pair_command(tmp_path, capsys):
    from surgrecon_cli.cli.main import main

    src, tgt, srgb, trgb, truth, order = _dome_pair()
    write_cloud_ply(tmp_path / "src.ply", src, srgb)
    write_cloud_ply(tmp_path / "dst.ply", tgt, trgb)
    inv = np.argsort(order)
    (tmp_path / "lm.csv").write_text("src_index,dst_index\n" +
                                     "".join(f"{i},{inv[i]}\n" for i in (0, 100, 200)))
    np.savetxt(tmp_path / "w.txt", np.ones(len(src)))
    other = src[:50] + 1e-4
    write_cloud_ply(tmp_path / "other.ply", other)
    rc = main(["register-pair", str(tmp_path / "src.ply"), str(tmp_path / "dst.ply"),
               "-o", str(tmp_path / "out" / "reg.ply"), "--landmarks", str(tmp_path / "lm.csv"),
               "--weights", str(tmp_path / "w.txt"), "--apply", str(tmp_path / "other.ply"),
               "-q", "--set", "registration.outer_iterations=3"])
    assert rc == 0
    line = capsys.readouterr().out.strip()
    assert line.startswith("registered 1500 points onto 1500") and "median" in line
    out = read_ply(tmp_path / "out" / "reg.ply")
    reg = np.c_[out["x"], out["y"], out["z"]]
    assert np.median(np.linalg.norm(reg - truth, axis=1)) < 0.3e-3
    assert np.array_equal(out["correspondence"][[0, 100, 200]], inv[[0, 100, 200]])
    assert set(np.unique(out["outlier"])) <= {0, 1} and np.array_equal(out["red"], srgb[:, 0])
    moved = read_ply(tmp_path / "out" / "other.registered.ply")
    assert len(moved["x"]) == 50


def test_register_pair_bad_input_is_one_line(tmp_path, capsys):
    from surgrecon_cli.cli.main import main

    (tmp_path / "bad.ply").write_bytes(b"not a ply")
    xyz, _ = cloud()
    write_cloud_ply(tmp_path / "ok.ply", xyz)
    rc = main(["register-pair", str(tmp_path / "bad.ply"), str(tmp_path / "ok.ply"),
               "-o", str(tmp_path / "o.ply"), "-q"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and err.startswith("error:") and "bad.ply" in err and "\n" not in err
    assert not (tmp_path / "o.ply").exists()
