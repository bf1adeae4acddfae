"""Every example shown by `surgrecon --help` and `surgrecon COMMAND --help` runs and exits 0.

Examples are collected from the click help texts (lines starting with `surgrecon ` inside the
`\\b` blocks of each command's help and epilog, backslash continuations joined), so a new
example is tested without editing this file. Each runs through `main()` in a fresh folder
that holds what the example refers to, built from one tiny simulated log (6 cameras,
2 frames, 320 x 240): `sample_data/sample.mcap` (+ `.gt.npz`) and any other input log are
copies of it; `runs/sample` is a run folder brought by the CLI itself to the stage the
command needs (ingested for build-template, templated for register, ...); a glob such as
`logs/*.mcap` gets two logs; a `--config` file gets the default [topics] and [tool]
sections; `--landmarks` a CSV of true pairs; `--scheduler` the address of a Dask cluster
started here; input PLYs are the run's first and last labelled clouds. Shell syntax is
interpreted: `> FILE` captures the output into FILE (a TOML one must then load and hold
every `--set`), `&& xdg-open FILE` checks that FILE exists. `surgrecon simulate` examples
get `--frames 2 --width 160 --height 120` appended (click keeps the last value) so that
rendering takes seconds, not a minute each.
"""

from __future__ import annotations

import glob
import inspect
import shlex
import shutil
from pathlib import Path

import click
import pytest

from surgrecon_cli.cli.main import cli, main

STAGE_BEFORE = {  # the run-folder state a stage command starts from
    "build-template": "ingested",
    "fit-tools": "ingested",
    "register": "templated",
    "classify": "registered",
    "measure": "registered",
    "report": "classified",
    "evaluate": "classified",
    "export": "finished",
}
RUN_READERS = {"compare"}  # commands whose every positional argument is a finished run
VIEWERS = {"xdg-open", "open"}  # programs an example may chain after `&&`: a file to view
SMALL_SIMULATION = ["--frames", "2", "--width", "160", "--height", "120"]


# ---- collecting the examples --------------------------------------------------------------


def _examples_in(text: str) -> list[str]:
    """Example command lines in the no-rewrap (\\b) paragraphs of a click help text."""
    found = []
    for paragraph in inspect.cleandoc(text).split("\n\n"):
        lines = paragraph.splitlines()
        if not lines or lines[0].strip() != "\b":
            continue
        pending = ""
        for line in lines[1:]:
            part = line.strip()
            if pending:
                pending += " " + part
            elif part.startswith("surgrecon "):
                pending = part
            if pending and not pending.endswith("\\"):
                found.append(pending)
                pending = ""
            elif pending:
                pending = pending[:-1].rstrip()
        assert not pending, f"unterminated continuation in help: {pending!r}"
    return found


def collect_examples() -> list[str]:
    examples: list[str] = []
    for command in [cli, *cli.commands.values()]:
        for text in (command.help or "", command.epilog or ""):
            examples += [e for e in _examples_in(text) if e not in examples]
    return examples


EXAMPLES = collect_examples()


def test_every_command_shows_an_example_that_is_collected(capsys):
    """Every subcommand has an example, and each collected example is what `--help` shows."""
    by_command = {name: [e for e in EXAMPLES if e.split()[1] == name]
                  for name in cli.commands}
    assert all(by_command.values()), [n for n, e in by_command.items() if not e]
    for name in [None, *cli.commands]:
        assert main([name, "--help"] if name else ["--help"]) == 0
        shown = " ".join(capsys.readouterr().out.replace(" \\\n", " ").split())
        wanted = _examples_in(cli.help) if name is None else by_command[name]
        for example in wanted:
            assert example in shown, (name, example)


# ---- the world the examples run in --------------------------------------------------------


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The tiny log (+ ground truth) and run folders of it at each stage, made by the CLI."""
    from surgrecon_cli.sim.scene import SimConfig
    from surgrecon_cli.sim.simulate import simulate

    root = tmp_path_factory.mktemp("help_world")
    log = root / "tiny.mcap"
    simulate(log, SimConfig(cameras=6, frames=2, width=320, height=240))
    states = {"log": log, "gt": root / "tiny.gt.npz", "ingested": root / "ingested"}
    assert main(["ingest", str(log), "-o", str(states["ingested"]), "-q"]) == 0
    previous = states["ingested"]
    for state, command in [("templated", "build-template"), ("registered", "register"),
                           ("classified", "classify"), ("finished", "report")]:
        states[state] = root / state
        shutil.copytree(previous, states[state])
        assert main([command, str(states[state]), "-q"]) == 0
        previous = states[state]
    return states


@pytest.fixture(scope="module")
def dask_scheduler():
    """A one-worker Dask cluster in this process (threads), started on first use."""
    holder: dict = {}

    def address() -> str:
        if "cluster" not in holder:
            distributed = pytest.importorskip("distributed")
            holder["cluster"] = distributed.LocalCluster(
                n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None)
        return holder["cluster"].scheduler_address

    yield address
    if "cluster" in holder:
        holder["cluster"].close()


def _copy_log(world: dict[str, Path], where: Path) -> None:
    """A copy of the tiny log at `where` with its ground truth beside it."""
    where.parent.mkdir(parents=True, exist_ok=True)
    shutil.copy(world["log"], where)
    shutil.copy(world["gt"], where.with_name(where.name.removesuffix(".mcap") + ".gt.npz"))


def _value_options(command: click.Command) -> set[str]:
    return {opt for p in command.params if isinstance(p, click.Option) and not p.is_flag
            and not p.count for opt in (*p.opts, *p.secondary_opts)}


def _prepare(argv: list[str], world: dict[str, Path], scheduler) -> list[str]:
    """Create in the current folder what the example `surgrecon argv...` reads; returns the
    arguments to run (globs expanded, a scheduler address substituted)."""
    name = argv[0]
    command = cli.commands[name]
    takes_value = _value_options(command)
    out: list[str] = [name]
    positional: list[str] = []
    plys = iter([world["classified"] / "clouds" / "000000.ply",
                 sorted((world["classified"] / "clouds").glob("*.ply"))[-1]])
    k = 1
    while k < len(argv):
        token = argv[k]
        option = token if token in takes_value else None
        value = argv[k + 1] if option else token
        k += 2 if option else 1
        if option == "--scheduler":
            out += [option, scheduler()]
            continue
        if option == "--config" and not Path(value).exists():
            text = _sections(["topics", "tool"])
            Path(value).write_text(text, encoding="utf-8")
        if name == "convert" and (option == "--calibration" or option is None) \
                and not value.startswith("-") and not Path(value).exists():
            _convert_input(Path(value), option)
        if option == "--landmarks" and not Path(value).exists():
            _write_landmarks(Path(value), world)
        if option == "--pairs" and not Path(value).exists():
            for ply in ("first.ply", "last.ply"):
                shutil.copy(next(plys), Path(value).parent / ply)
            Path(value).write_text("first.ply last.ply\n", encoding="utf-8")
        if option is None and not token.startswith("-"):
            if any(c in token for c in "*?["):
                pattern_dir = Path(token).parent
                if not pattern_dir.exists():
                    for stem in ("a", "b"):
                        if name in RUN_READERS:
                            shutil.copytree(world["finished"], pattern_dir / stem)
                        else:
                            _copy_log(world, pattern_dir / f"{stem}.mcap")
                matches = sorted(glob.glob(token))
                assert matches, f"{token}: the glob matches nothing"
                positional += matches
                out += matches
                continue
            positional.append(token)
            if name in RUN_READERS and not Path(token).exists():
                shutil.copytree(world["finished"], token)
            if token.endswith(".mcap") and name != "simulate" and not Path(token).exists():
                _copy_log(world, Path(token))
            if token.endswith("/") and name in ("info", "ingest", "run") \
                    and not Path(token).exists():  # a bag folder: the log split in one file
                _copy_log(world, Path(token) / "part_0.mcap")
            if token.endswith(".ply") and name == "register-pair" and not Path(token).exists():
                shutil.copy(next(plys), token)
            if token.endswith("/") and name == "register-pair" and not Path(token).exists():
                Path(token).mkdir(parents=True)  # a folder of clouds: one, same name in both
                shutil.copy(next(plys), Path(token) / "cloud.ply")
        if option and value.endswith(".gt.npz") and not Path(value).exists():
            Path(value).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy(world["gt"], value)
        out += [option, value] if option else [token]
    if name in STAGE_BEFORE:
        run = Path(positional[0])
        if not run.exists():
            shutil.copytree(world[STAGE_BEFORE[name]], run)
    if name == "simulate":
        out += SMALL_SIMULATION
    return out


SURGT = Path(__file__).parent / "data" / "surgt"


def _convert_input(path: Path, option: str | None) -> None:
    """What a `convert` example reads: the SurgT calibration, its stereo video, or two of its
    frames as a stereo image folder (left/, right/)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    if option == "--calibration":
        shutil.copy(SURGT / "calibration.yaml", path)
    elif path.suffix:
        shutil.copy(SURGT / "video.mp4", path)
    else:
        import av
        import cv2

        with av.open(str(SURGT / "video.mp4")) as container:
            for i, frame in zip(range(2), container.decode(video=0), strict=False):
                img = frame.to_ndarray(format="bgr24")
                for side, view in (("left", img[:, :1280]), ("right", img[:, 1280:])):
                    (path / side).mkdir(parents=True, exist_ok=True)
                    cv2.imwrite(str(path / side / f"{i:06d}.jpg"), view)


def _sections(names: list[str]) -> str:
    """The default config's [section]s of `names`, as TOML (what a user's config holds)."""
    from surgrecon_cli.config import load_config, to_toml

    keep, lines = False, []
    for line in to_toml(load_config(), with_docs=False).splitlines():
        if line.startswith("["):
            keep = line.strip("[] ") in names
        if keep:
            lines.append(line)
    return "\n".join(lines) + "\n"


def _write_landmarks(path: Path, world: dict[str, Path]) -> None:
    """True pairs between the run's first and last clouds (same point_id), every 25th."""
    from surgrecon_cli.io.run.ply import read_ply

    clouds = sorted((world["classified"] / "clouds").glob("*.ply"))
    src = read_ply(clouds[0])["point_id"]
    dst = read_ply(clouds[-1])["point_id"]
    where = {int(p): i for i, p in enumerate(dst)}
    rows = [f"{i},{where[int(p)]}" for i, p in enumerate(src) if int(p) in where][::25]
    path.write_text("src_index,dst_index\n" + "\n".join(rows) + "\n", encoding="utf-8")


# ---- running them -------------------------------------------------------------------------


def _run_segment(tokens: list[str], world, scheduler, capsys) -> None:
    redirect = None
    if ">" in tokens:
        at = tokens.index(">")
        tokens, redirect = tokens[:at], tokens[at + 1]
    if tokens[0] in VIEWERS:
        assert len(tokens) == 2 and Path(tokens[1]).is_file(), f"nothing to view: {tokens}"
        return
    assert tokens[0] == "surgrecon", f"example runs an unknown program: {tokens}"
    argv = _prepare(tokens[1:], world, scheduler)
    capsys.readouterr()
    code = main(argv)
    captured = capsys.readouterr()
    assert code == 0, f"exit {code}: {' '.join(argv)}\n{captured.err[-2000:]}"
    if redirect:
        Path(redirect).write_text(captured.out, encoding="utf-8")
        if redirect.endswith(".toml"):
            _check_toml_holds_overrides(Path(redirect), argv)


def _check_toml_holds_overrides(path: Path, argv: list[str]) -> None:
    """The captured TOML is the effective config: loading it gives what the --set gave."""
    from surgrecon_cli.config import load_config

    sets = [argv[k + 1] for k, token in enumerate(argv) if token == "--set"]
    assert load_config(path) == load_config(overrides=sets)


def shell_segments(line: str) -> list[list[str]]:
    """A shell command line split into its `&&`-chained commands (quotes, `>` understood)."""
    lex = shlex.shlex(line, posix=True, punctuation_chars=True)
    lex.whitespace_split = True
    segments: list[list[str]] = [[]]
    for token in lex:
        if token == "&&":
            segments.append([])
        elif token and set(token) <= set("();<>|&") and token != ">":
            raise AssertionError(f"unsupported shell syntax {token!r} in example: {line}")
        else:
            segments[-1].append(token)
    return segments


def test_shell_segments():
    assert shell_segments("surgrecon a x.mcap -o 'r s/' > my.toml && xdg-open r/x.html") == [
        ["surgrecon", "a", "x.mcap", "-o", "r s/", ">", "my.toml"], ["xdg-open", "r/x.html"]]
    with pytest.raises(AssertionError, match="unsupported"):
        shell_segments("surgrecon config | less")


def _example(example: str) -> object:
    """An example as a test case, marked slow when it runs the whole pipeline (`run`) or
    starts worker processes or a Dask cluster (tens of seconds each on 2 cores)."""
    words = example.split()
    slow = words[1] == "run" or "--executor" in words or "--scheduler" in words
    return pytest.param(example, id=example.removeprefix("surgrecon "),
                        marks=[pytest.mark.slow] if slow else [])


@pytest.mark.parametrize("example", [_example(e) for e in EXAMPLES])
def test_help_example_runs(example, world, dask_scheduler, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    for tokens in shell_segments(example):
        _run_segment(tokens, world, dask_scheduler, capsys)
