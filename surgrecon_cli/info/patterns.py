"""Camera-id patterns from names (pure): which `{camera}` template explains a set of topic or
frame names, and how strongly a name says what it is (`word_score`).

Camera ids are the part of the names that differs between cameras
(`/endoscope_{camera}/color/compressed`); a template puts `{camera}` in place of one name
token (a run of letters and digits) or of one occurrence of an id already known from another
role.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Sequence
from typing import Any

from ..io.logs.topics import pattern_regex

_TOKEN = re.compile(r"[A-Za-z0-9]+")


def captures(pattern: str, names: Iterable[str]) -> dict[str, str]:
    """{name: camera id} of the names that `pattern` (with `{camera}`) matches in full."""
    regex = pattern_regex(pattern)
    out = {}
    for name in names:
        m = regex.match(name)
        if m is not None:
            out[name] = m.groupdict().get("camera") or ""
    return out


def _candidates(names: Sequence[str], ids: Iterable[str]) -> set[str]:
    """Templates made by putting `{camera}` in place of one name token or of one occurrence
    of a known id."""
    out = set()
    for name in names:
        for m in _TOKEN.finditer(name):
            out.add(name[: m.start()] + "{camera}" + name[m.end():])
        for cam in ids:
            if cam:
                for m in re.finditer(re.escape(cam), name):
                    out.add(name[: m.start()] + "{camera}" + name[m.end():])
    return {t for t in out if t.count("{camera}") == 1}


def camera_pattern(
    names: Sequence[str],
    ids: Sequence[str] = (),
    prefer: Sequence[str] = (),
    leaves: frozenset[str] | None = None,
) -> tuple[str, dict[str, str]]:
    """The `{camera}` pattern that best explains `names`, and its {name: id} captures.

    Without `ids`: the pattern capturing the most distinct ids (the varying part of the
    names). With `ids` (the cameras found from another role): the one capturing most of them
    and fewest others; ("", {}) if none captures any. Ties: more `prefer` words in the
    pattern, more captured names in `leaves`, ids with digits, shorter ids, then the
    alphabetically first pattern.
    """
    known = set(ids)
    best: tuple[Any, ...] | None = None
    chosen: tuple[str, dict[str, str]] = ("", {})
    for template in sorted(_candidates(names, known)):
        caps = captures(template, names)
        got = set(caps.values())
        if known:
            primary: tuple[int, ...] = (len(got & known), -len(got - known))
            if not got & known:
                continue
        else:
            primary = (len(got),)
        lower = template.lower()
        key = (
            *primary,
            sum(w in lower for w in prefer),
            sum(n in leaves for n in caps) if leaves is not None else 0,
            all(any(ch.isdigit() for ch in g) for g in got),
            -sum(len(g) for g in got),
        )
        if best is None or key > best:
            best, chosen = key, (template, caps)
    return chosen


def sort_ids(ids: Iterable[str]) -> tuple[str, ...]:
    """Camera ids sorted naturally (numbers by value)."""
    return tuple(sorted(set(ids), key=lambda s: (not s.isdigit(), int(s) if s.isdigit() else 0,
                                                 s)))


def word_score(name: str, words: Sequence[str]) -> int:
    """How many of `words` the name holds: as a token, as the start of a token (3+ letters),
    or, for words with `_`, anywhere."""
    lower = name.lower()
    tokens = [t for t in re.split(r"[^a-z0-9]+", lower) if t]
    return sum(1 for w in words if w in tokens or ("_" in w and w in lower) or (
        len(w) >= 3 and any(t.startswith(w) for t in tokens)))
