"""The house rules of the code base, checked on the source (docs/architecture.md draws
them): one module knows the run folder's file names; stages do not import each other; no
import climbs back up the layers; core is grouped in subpackages along the data flow and io
in three by job; figures and pages only in report/; one loop streams a log's records;
modules stay under ~500 lines; the stage registry agrees with the layout."""

from __future__ import annotations

import ast
import re
from pathlib import Path

from surgrecon_cli.io.run.layout import DESCRIBED_FILES, RunLayout
from surgrecon_cli.stages import registry

PACKAGE = Path(__file__).resolve().parents[1] / "surgrecon_cli"
LAYOUT = PACKAGE / "io" / "run" / "layout.py"
MAX_MODULE_LINES = 500  # a concept per module, not a size: split by meaning when it grows
# The simulator writes logs and ground truth, not run folders.
SOURCES = [p for p in PACKAGE.rglob("*.py") if p != LAYOUT and "sim" not in p.parts]
# Every file and folder name of the run folder, as the layout spells them.
RUN_FOLDER_NAMES = ("run.json", "config.toml", "cameras.json", "frames.npz",
                    "template.ply", "observations.npz", "summary.json", "labels.npz",
                    "evaluation.json", "evaluation_errors.npz", "frames.csv", "report.html",
                    "ingest", "template", "registration", "classify", "clouds", "metrics",
                    "images", "staged", "measure", "deformation.npz", "deformation.csv")


# A mention of a source file ("core/measure/dent.py") is not a run-folder path.
_SOURCE_FILE = re.compile(r"[\w/]+\.py\b")


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
                and (node.value in files or in_path.search(_SOURCE_FILE.sub("", node.value))):
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


def test_modules_under_500_lines():
    lengths = {p.relative_to(PACKAGE).as_posix(): len(p.read_text(encoding="utf-8").splitlines())
               for p in sorted(PACKAGE.rglob("*.py"))}
    assert len(lengths) > 100  # the whole package was walked
    offenders = [f"{name}: {n} lines" for name, n in lengths.items() if n > MAX_MODULE_LINES]
    assert offenders == []


# The packages in layers: a package imports only packages of a lower rank (the package's
# own __init__, `surgrecon_cli`, holds the version and a few limits every layer may read).
RANKS = {"errors": 0, "config": 1, "core": 2, "executors": 3, "io": 3, "registration": 3,
         "report": 4, "info": 4, "sim": 4, "convert": 5, "stages": 6, "planning": 7,
         "pipeline": 8, "cli": 9, "__main__": 10}
# core's subpackages in the order of the data flow; each imports only earlier ones.
# classify comes before target because its labels module holds the point and status codes
# the target cloud and the registration already use.
CORE_ORDER = ("geometry", "sync", "noise", "classify", "target", "template", "registration",
              "measure", "evaluate")
IO_PACKAGES = ("logs", "run", "export")


def _imports(path: Path) -> list[tuple[int, tuple[str, ...]]]:
    """(line, dotted name split) of every `surgrecon_cli` module or name `path` imports,
    relative imports resolved."""
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    package = list(parts if path.name == "__init__.py" else parts[:-1])
    if path.name == "__init__.py":
        package = package[:-1]
    found = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[:len(package) - (node.level - 1)]
                name = [*base, *(node.module.split(".") if node.module else [])]
            else:
                name = (node.module or "").split(".")
            if name[0] == PACKAGE.name:
                found += [(node.lineno, (*name, a.name)) for a in node.names]
        elif isinstance(node, ast.Import):
            found += [(node.lineno, tuple(a.name.split("."))) for a in node.names
                      if a.name.split(".")[0] == PACKAGE.name]
    return found


def _top(name: tuple[str, ...]) -> str:
    return name[1] if len(name) > 1 else ""


def test_no_import_climbs_back_up():
    offenders = []
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE)
        here = rel.parts[0] if len(rel.parts) > 1 else rel.stem
        if here not in RANKS:
            continue
        for line, name in _imports(path):
            there = _top(name)
            if there != here and there in RANKS and RANKS[there] >= RANKS[here]:
                offenders.append(f"{rel}:{line} imports {'.'.join(name[1:3])}")
    assert set(RANKS) >= {p.stem if p.is_file() else p.name for p in PACKAGE.iterdir()
                          if (p.suffix == ".py" or (p / "__init__.py").exists())
                          and p.name != "__init__.py"}
    assert offenders == []


def test_core_is_grouped_along_the_data_flow():
    core = PACKAGE / "core"
    assert sorted(p.name for p in core.glob("*.py")) == ["__init__.py"]  # no flat module
    assert {p.name for p in core.iterdir() if (p / "__init__.py").exists()} == set(CORE_ORDER)
    offenders = []
    for path in sorted(core.rglob("*.py")):
        sub = path.relative_to(core).parts[0]
        for line, name in _imports(path):
            if name[1:2] == ("core",) and len(name) > 3 and name[2] != sub \
                    and CORE_ORDER.index(name[2]) > CORE_ORDER.index(sub):
                offenders.append(f"core/{path.relative_to(core)}:{line} imports core.{name[2]}")
    assert offenders == []


def test_io_is_split_by_job():
    io = PACKAGE / "io"
    assert sorted(p.name for p in io.glob("*.py")) == ["__init__.py"]  # no flat module
    assert {p.name for p in io.iterdir() if (p / "__init__.py").exists()} == set(IO_PACKAGES)
    # Exports read the run folder; nothing that reads logs or keeps the run folder exports.
    offenders = [f"io/{path.relative_to(io)}:{line}"
                 for path in sorted(io.rglob("*.py")) if path.relative_to(io).parts[0] != "export"
                 for line, name in _imports(path) if name[1:3] == ("io", "export")]
    assert offenders == []


def test_figures_and_pages_only_in_report():
    offenders = []
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE)
        if rel.parts[0] == "report":
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            modules = ([a.name for a in node.names] if isinstance(node, ast.Import) else
                       [node.module or ""] if isinstance(node, ast.ImportFrom) and not node.level
                       else [])
            offenders += [f"{rel}:{node.lineno} imports {m}" for m in modules
                          if m.split(".")[0] in ("matplotlib", "html")]
            if isinstance(node, ast.Constant) and isinstance(node.value, str) \
                    and re.search(r"<(!doctype|html|body|table)\b", node.value, re.I):
                offenders.append(f"{rel}:{node.lineno} writes HTML")
    assert offenders == []


def test_one_loop_streams_a_logs_records():
    """Only io/logs/stream.py walks a file's records to the end of the data section (the
    reader and the scan both iterate its `RecordStream`), and one helper of io/logs words a
    stream error on one line."""
    stream = PACKAGE / "io" / "logs" / "stream.py"
    offenders = []
    for path in sorted(PACKAGE.rglob("*.py")):
        in_logs = path.is_relative_to(stream.parent)
        if path == stream:
            continue
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.module == "mcap.records" \
                    and any(a.name == "DataEnd" for a in node.names):
                offenders.append(f"{path.relative_to(PACKAGE)}:{node.lineno} imports DataEnd")
            if in_logs and isinstance(node, ast.FunctionDef) \
                    and node.name.lstrip("_") == "one_line":
                offenders.append(f"{path.relative_to(PACKAGE)}:{node.lineno} defines {node.name}")
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


# Core functions take at most this many parameters (self/cls not counted, keyword-only
# counted): the run's state travels in small objects (core/target/frame_inputs.py, the
# config dataclasses, FrameRegistrar), not as loose arguments.
MAX_CORE_PARAMETERS = 6
# The documented library calls: their extra parameters are keyword-only options a user passes.
LIBRARY_CALLS = {"registration/register.py:register",
                 "registration/pair.py:register_pair"}
# Constructors of value types, built field by field (e.g. a camera model from a ROS CameraInfo).
VALUE_CONSTRUCTORS = {"__init__", "from_camera_info"}


def _parameter_count(fn: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    a = fn.args
    names = [p.arg for p in (*a.posonlyargs, *a.args, *a.kwonlyargs)]
    return len([n for n in names if n not in ("self", "cls")]) + bool(a.vararg)


def test_core_functions_take_few_parameters():
    core = PACKAGE / "core"
    offenders = []
    for path in sorted(core.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if not isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                continue
            where = f"{path.relative_to(core).as_posix()}:{node.name}"
            if where in LIBRARY_CALLS or node.name in VALUE_CONSTRUCTORS:
                continue  # the library's options; a value type's fields
            if _parameter_count(node) > MAX_CORE_PARAMETERS:
                offenders.append(f"core/{where} takes {_parameter_count(node)}")
    assert offenders == []
