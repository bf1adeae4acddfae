"""The documents a new user reads first describe what the code writes: every TUM file of
`export --tum` in the README, every key of the shipped ground truth in sample_data/README.md
(self-contained: no reference to a document outside the repository)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from surgrecon_cli.io.run_layout import RunLayout

ROOT = Path(__file__).resolve().parents[1]


def _table_rows(text: str) -> dict[str, str]:
    """{first cell without backticks: the whole row} of every Markdown table row."""
    return {m.group(1): m.group(0) for m in re.finditer(r"^\| `([^`]+)` \|.*$", text, re.M)}


def test_readme_documents_every_tum_file():
    rows = _table_rows((ROOT / "README.md").read_text(encoding="utf-8"))
    names = [RunLayout.tum_camera(Path(), 7).name, RunLayout.tum_tracker(Path(), 7).name,
             RunLayout.tum_tool(Path()).name, RunLayout.tum_robot(Path()).name]
    for name in (n.replace("07", "CC") for n in names):
        assert name in rows, f"{name} is not described in the README"
        assert "stamps" in rows[name], rows[name]  # each says its time base


def test_sample_readme_describes_every_ground_truth_key():
    text = (ROOT / "sample_data" / "README.md").read_text(encoding="utf-8")
    assert "SPEC" not in text and "section 6" not in text
    rows = _table_rows(text)
    with np.load(ROOT / "sample_data" / "sample.gt.npz", allow_pickle=False) as gt:
        for key in gt.files:
            assert key in rows, f"{key} of sample.gt.npz is not described"
            dims = {"T": gt["vertices"].shape[0], "V": gt["vertices"].shape[1],
                    "F": gt["faces"].shape[0]}
            shape = re.search(r"\| \(([^)]*)\) (\w+) \|", rows[key])
            assert shape is not None, rows[key]
            assert tuple(dims[d] if d in dims else int(d) for d in
                         shape.group(1).replace(" ", "").split(",") if d) == gt[key].shape
            assert shape.group(2) == gt[key].dtype.name
    for letter, value in dims.items():
        assert f"{letter} = {value}" in text
