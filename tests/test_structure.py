"""The house rules of the code base, checked on the source: one module knows the run
folder's file names, stages do not import each other, modules stay small, and the stage
registry agrees with the layout."""

from __future__ import annotations

import ast
import re
from pathlib import Path

from surgrecon_cli.io.run.layout import DESCRIBED_FILES, RunLayout
from surgrecon_cli.stages import registry

PACKAGE = Path(__file__).resolve().parents[1] / "surgrecon_cli"
LAYOUT = PACKAGE / "io" / "run" / "layout.py"
MAX_MODULE_LINES = 350
# The simulator writes logs and ground truth, not run folders.
SOURCES = [p for p in PACKAGE.rglob("*.py") if p != LAYOUT and "sim" not in p.parts]
# Every file and folder name of the run folder, as the layout spells them.
RUN_FOLDER_NAMES = ("run.json", "config.toml", "cameras.json", "frames.npz",
                    "template.ply", "observations.npz", "summary.json", "labels.npz",
                    "evaluation.json", "evaluation_errors.npz", "frames.csv", "report.html",
                    "ingest", "template", "registration", "classify", "clouds", "metrics",
                    "images", "staged", "measure", "deformation.npz", "deformation.csv")


def _path_spellings(path: Path) -> list[str]:
    """Where `path`'s code spells a run-folder name: a file name ("run.json"), a path
    string with one of the names as a component ("clouds/x.ply"), or a path join with one
    (`run_dir / "clouds"`). Docstrings may describe the layout; code may not spell it."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    names = "|".join(re.escape(n) for n in RUN_FOLDER_NAMES)
    in_path = re.compile(rf"(?:^|/)(?:{names})/|/(?:{names})$")
    files = {n for n in RUN_FOLDER_NAMES if "." in n}
    docstrings = {id(node.body[0].value) for node in ast.walk(tree)
                  if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef))
                  and node.body and isinstance(node.body[0], ast.Expr)}
    found = []
    for node in ast.walk(tree):
        if id(node) in docstrings:
            continue
        if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Div) \
                and isinstance(node.right, ast.Constant) and node.right.value in RUN_FOLDER_NAMES:
            found.append(f"{node.lineno}: / {node.right.value!r}")
        elif isinstance(node, ast.Constant) and isinstance(node.value, str) \
                and (node.value in files or in_path.search(node.value)):
            found.append(f"{node.lineno}: {node.value!r}")
    return found


def test_no_run_folder_path_outside_the_layout_module():
    offenders = [f"{p.relative_to(PACKAGE)}:{where}" for p in SOURCES
                 for where in _path_spellings(p)]
    assert offenders == []


def test_no_stage_imports_another_stage():
    stage_modules = {p.stem for p in (PACKAGE / "stages").glob("*.py")}
    shared = {"common", "registry", "staleness", "__init__"}
    offenders = []
    for path in (PACKAGE / "stages").glob("*.py"):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.level == 1 and node.module:
                imported = node.module.split(".")[0]
                if imported in stage_modules - shared and imported != path.stem \
                        and not (path.stem.startswith("ingest") and imported.startswith("ingest_")):
                    offenders.append(f"{path.name} imports .{node.module}")
    assert offenders == []


def test_modules_under_350_lines():
    lengths = {p.relative_to(PACKAGE).as_posix(): len(p.read_text(encoding="utf-8").splitlines())
               for p in sorted(PACKAGE.rglob("*.py"))}
    assert len(lengths) > 100  # the whole package was walked
    offenders = [f"{name}: {n} lines" for name, n in lengths.items() if n > MAX_MODULE_LINES]
    assert offenders == []


def test_registry_outputs_are_layout_paths(tmp_path: Path):
    layout = RunLayout(tmp_path)
    for spec in registry.STAGES:
        for name in (*spec.outputs, spec.key_output):
            path = getattr(layout, name)
            assert isinstance(path, Path) and tmp_path in path.parents
        assert all(n in registry.NAMES[:registry.NAMES.index(spec.name)] for n in spec.needs)
        assert callable(registry.step(spec.name))
    for name, _what in DESCRIBED_FILES:
        assert isinstance(getattr(layout, name), Path)


def test_config_keys_accumulate_along_the_pipeline():
    assert registry.config_keys("ingest") == ("topics", "ingest", "tool.base_to_world", "tools")
    assert set(registry.config_keys("build-template")) >= {"topics", "tool", "template"}
    assert registry.upstream_config_keys("register") == registry.config_keys("build-template")
    assert "classify" not in registry.config_keys("register")
