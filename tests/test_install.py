"""Reproducible installs: `make install` installs the exact versions of constraints.txt (and
reinstalls when it changes), the file pins every dependency of the project and of its dev
extra at a version the project accepts, and `make test` leaves out the slow tests that
`make test-slow` (and CI, .ci/run) runs."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import tomllib
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name
from packaging.version import Version

ROOT = Path(__file__).resolve().parents[1]
LOCK = ROOT / "constraints.txt"


def _pins() -> dict[str, Version]:
    pins = {}
    for line in LOCK.read_text(encoding="utf-8").splitlines():
        line = line.split("#")[0].strip()
        if line:
            name, sep, version = line.partition("==")
            assert sep, f"constraints.txt: {line!r} is not an exact pin (NAME==VERSION)"
            pins[canonicalize_name(name)] = Version(version)
    return pins


def test_constraints_pin_every_dependency_at_an_accepted_version():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]
    pins = _pins()
    assert "surgrecon" not in pins  # the project itself is installed from the checkout
    for text in [*project["dependencies"], *project["optional-dependencies"]["dev"]]:
        req = Requirement(text)
        name = canonicalize_name(req.name)
        assert name in pins, f"{req.name} is not pinned in constraints.txt"
        assert req.specifier.contains(pins[name], prereleases=True), (
            f"constraints.txt pins {req.name}=={pins[name]}, outside {req.specifier}")


def _make(*args: str) -> str:
    """What `make -n ARGS` prints (-n: nothing is run), also when the suite runs under make
    (`make test`: no inherited flags, no "Entering directory" lines)."""
    if shutil.which("make") is None:
        pytest.skip("make is not installed")
    env = {k: v for k, v in os.environ.items() if k not in ("MAKEFLAGS", "MFLAGS", "MAKELEVEL")}
    return subprocess.run(["make", "-n", "--no-print-directory", *args], cwd=ROOT, env=env,
                          capture_output=True, text=True, check=False).stdout


def test_make_installs_the_constraints_and_tests_without_the_slow_ones():
    install = _make("-B", ".venv/.installed")
    assert re.search(r"pip install -q -c constraints\.txt -e \"?\.\[dev\]", install), install
    database = _make("-p", "install")  # the rules, with their prerequisites
    stamp = next(line for line in database.splitlines() if line.startswith(".venv/.installed:"))
    assert "constraints.txt" in stamp.split(":", 1)[1].split()
    # -o: the installed stamp taken as up to date, so only the test recipes are printed
    assert "-m \"not slow\"" in _make("-o", ".venv/.installed", "test").splitlines()[-1]
    assert "-m slow" in _make("-o", ".venv/.installed", "test-slow").splitlines()[-1]
    ci = (ROOT / ".ci" / "run").read_text(encoding="utf-8").split()
    assert "make" in ci and {"test", "test-slow"} <= set(ci)
    assert "lock:" in (ROOT / "Makefile").read_text(encoding="utf-8")
