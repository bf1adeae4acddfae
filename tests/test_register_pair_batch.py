"""`surgrecon register-pair` on many pairs in one process: two folders of same-named PLYs,
or a list file; every output scored against the pairs' true moved positions, a failing pair
recorded while the others are written."""

from __future__ import annotations

import numpy as np
from test_registration import err_mm, make

from surgrecon_cli.cli.main import main
from surgrecon_cli.io.run.metrics import read_csv
from surgrecon_cli.io.run.ply import read_ply, write_cloud_ply

QUICK = ["-q", "--set", "registration.outer_iterations=3"]


def _write_pairs(folder_src, folder_dst, seeds):
    """Write coloured dome pairs (true moved positions returned per name)."""
    folder_src.mkdir(parents=True, exist_ok=True)
    folder_dst.mkdir(parents=True, exist_ok=True)
    truths = {}
    for seed in seeds:
        src, tgt, srgb, trgb, truth, _ = make(800, seed=seed)
        name = f"pair{seed}.ply"
        write_cloud_ply(folder_src / name, src, (srgb * 255).astype(np.uint8))
        write_cloud_ply(folder_dst / name, tgt, (trgb * 255).astype(np.uint8))
        truths[name] = truth
    return truths


def _registered(path):
    cloud = read_ply(path)
    return np.c_[cloud["x"], cloud["y"], cloud["z"]]


def test_folders_of_pairs_register_in_one_process(tmp_path, capsys):
    truths = _write_pairs(tmp_path / "a", tmp_path / "b", (3, 4))
    rc = main(["register-pair", str(tmp_path / "a"), str(tmp_path / "b"),
               "-o", str(tmp_path / "out"), *QUICK])
    assert rc == 0
    assert "registered 2 of 2 pairs" in capsys.readouterr().out
    for name, truth in truths.items():
        assert np.median(err_mm(_registered(tmp_path / "out" / name), truth)) < 0.5
    rows = read_csv(tmp_path / "out" / "pairs.csv")
    assert [r["source_points"] for r in rows] == [800, 800]
    assert all("error" not in r and r["residual_median_mm"] > 0 for r in rows)


def test_list_file_with_a_broken_pair_keeps_the_others(tmp_path, capsys):
    truths = _write_pairs(tmp_path / "src", tmp_path / "dst", (5, 6))
    (tmp_path / "dst" / "broken.ply").write_bytes(b"ply\nformat nonsense\n")
    (tmp_path / "pairs.txt").write_text(
        "# source target [output]\n"
        "src/pair5.ply dst/pair5.ply first.ply\n"
        "src/pair6.ply dst/broken.ply\n"
        "src/pair6.ply dst/pair6.ply\n")
    rc = main(["register-pair", "--pairs", str(tmp_path / "pairs.txt"),
               "-o", str(tmp_path / "out"), *QUICK])
    captured = capsys.readouterr()
    assert rc == 2
    assert "1 of 3 pairs failed" in captured.err and "broken.ply" in captured.err
    assert np.median(err_mm(_registered(tmp_path / "out" / "first.ply"),
                            truths["pair5.ply"])) < 0.5
    assert np.median(err_mm(_registered(tmp_path / "out" / "pair6_on_pair6.ply"),
                            truths["pair6.ply"])) < 0.5
    assert not (tmp_path / "out" / "pair6_on_broken.ply").exists()
    rows = read_csv(tmp_path / "out" / "pairs.csv")
    assert len(rows) == 3 and "broken.ply" in rows[1]["error"]


def test_batch_refuses_single_pair_options_and_mismatched_folders(tmp_path, capsys):
    _write_pairs(tmp_path / "a", tmp_path / "b", (7,))
    (tmp_path / "a" / "extra.ply").write_bytes((tmp_path / "a" / "pair7.ply").read_bytes())
    rc = main(["register-pair", str(tmp_path / "a"), str(tmp_path / "b"),
               "-o", str(tmp_path / "out"), "-q"])
    assert rc == 2 and "extra.ply" in capsys.readouterr().err
    rc = main(["register-pair", str(tmp_path / "a" / "pair7.ply"), str(tmp_path / "b"),
               "-o", str(tmp_path / "out"), "-q"])
    assert rc == 2 and "both be files or both be folders" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_register_pair_imports_no_heavy_libraries(tmp_path):
    """The command loads the registration's own needs only (no OpenCV, Open3D, plotting)."""
    import subprocess
    import sys

    _write_pairs(tmp_path / "a", tmp_path / "b", (8,))
    code = ("import sys; from surgrecon_cli.cli.main import main; "
            f"rc = main(['register-pair', {str(tmp_path / 'a' / 'pair8.ply')!r}, "
            f"{str(tmp_path / 'b' / 'pair8.ply')!r}, '-o', {str(tmp_path / 'o.ply')!r}, '-q', "
            "'--set', 'registration.outer_iterations=2']); "
            "print(sorted(m for m in ('cv2', 'open3d', 'matplotlib', 'mcap', 'dask') "
            "if m in sys.modules)); sys.exit(rc)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout
    assert out.strip().splitlines()[-1] == "[]"
