"""The documents a new user reads first describe what the code writes: every TUM file of
`export --tum` in docs/outputs.md, every key of the shipped ground truth in
sample_data/README.md (self-contained: no reference to a document outside the repository).
The README stays a front door (at most 10 KB), its library call runs as written, and every
relative link of the README and docs/ resolves (file and heading)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from surgrecon_cli.io.run.layout import RunLayout

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = sorted((ROOT / "docs").glob("*.md"))
MAX_README_BYTES = 10 * 1024


def _table_rows(text: str) -> dict[str, str]:
    """{first cell without backticks: the whole row} of every Markdown table row."""
    return {m.group(1): m.group(0) for m in re.finditer(r"^\| `([^`]+)` \|.*$", text, re.M)}


def test_outputs_page_documents_every_tum_file():
    rows = _table_rows((ROOT / "docs" / "outputs.md").read_text(encoding="utf-8"))
    names = [RunLayout.tum_camera(Path(), 7).name, RunLayout.tum_tracker(Path(), 7).name,
             RunLayout.tum_tool(Path()).name, RunLayout.tum_robot(Path()).name]
    for name in (n.replace("07", "CC") for n in names):
        assert name in rows, f"{name} is not described in docs/outputs.md"
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


def test_readme_is_a_front_door():
    text = README.read_text(encoding="utf-8")
    assert len(README.read_bytes()) <= MAX_README_BYTES
    assert len(DOCS) >= 8  # everything else lives in docs/, each page linked from the README
    assert [p.name for p in DOCS if f"](docs/{p.name})" not in text] == []


def _slug(heading: str) -> str:
    """GitHub's anchor of a Markdown heading."""
    text = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return text.replace(" ", "-")


def _anchors(path: Path) -> set[str]:
    text = path.read_text(encoding="utf-8")
    return {_slug(m.group(1)) for m in re.finditer(r"^#+ (.+)$", text, re.M)}


@pytest.mark.parametrize("doc", [README, *DOCS], ids=lambda p: p.name)
def test_every_relative_link_resolves(doc: Path):
    text = doc.read_text(encoding="utf-8")
    links = re.findall(r"\]\(([^)\s]+)\)", text)
    for link in links:
        if re.match(r"[a-z]+:", link):
            continue  # an absolute URL
        target, _, anchor = link.partition("#")
        path = (doc.parent / target).resolve() if target else doc
        assert path.exists(), f"{doc.name}: {link} does not exist"
        if anchor:
            assert anchor in _anchors(path), f"{doc.name}: no heading #{anchor} in {target}"


def test_the_readme_library_call_runs_as_written():
    """The README's Python block, on a patch of surface moved by a known translation."""
    block = re.search(r"```python\n(.*?)```", README.read_text(encoding="utf-8"), re.S)
    assert block is not None
    rng = np.random.default_rng(3)
    xy = rng.uniform(-0.015, 0.015, (400, 2))
    surface = np.column_stack([xy, 0.002 * np.sin(xy[:, 0] * 200)])
    shift = np.array([0.0008, -0.0005, 0.0003])  # m
    rgb = rng.uniform(0, 1, (400, 3))
    names = {"source_xyz": surface, "target_xyz": surface + shift, "source_rgb": rgb,
             "target_rgb": rgb, "other_xyz": surface[:5]}
    exec(compile(block.group(1), "README.md", "exec"), names)  # the repository's own text
    result = names["result"]
    error = np.linalg.norm(result.registered - (surface + shift), axis=1)
    assert np.median(error) < 1e-4  # within 0.1 mm of the known motion
    np.testing.assert_allclose(names["moved"], surface[:5] + shift, atol=3e-4)
