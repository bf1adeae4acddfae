"""A self-contained HTML report: inline CSS, PNG figures embedded as base64, no scripts.

Build a list of `Section`s (each a title and a list of blocks made by `paragraph`,
`table`, `figure`, `tiles`) and render it with `render`, with the run's caveats (what
damaged or altered it) in a box above everything.
"""

from __future__ import annotations

import base64
import html
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

_CSS = """
:root { --ink:#1f2933; --muted:#66788a; --line:#e4e7eb; --accent:#4C78A8; --bg:#f7f9fb; }
* { box-sizing: border-box; }
body { margin:0; font:14px/1.5 -apple-system,BlinkMacSystemFont,"Segoe UI",Roboto,Helvetica,
       Arial,sans-serif; color:var(--ink); background:var(--bg); }
header { background:linear-gradient(120deg,#1f3b5a,#4C78A8); color:white; padding:28px 40px; }
header h1 { margin:0 0 4px; font-size:24px; font-weight:600; }
header p { margin:0; opacity:.85; }
nav { background:white; border-bottom:1px solid var(--line); padding:8px 40px; position:sticky;
      top:0; z-index:2; }
nav a { color:var(--accent); text-decoration:none; margin-right:18px; font-size:13px; }
main { max-width:1180px; margin:0 auto; padding:8px 40px 60px; }
section { background:white; border:1px solid var(--line); border-radius:8px; padding:18px 24px;
          margin:22px 0; }
section h2 { margin:0 0 10px; font-size:18px; }
p.note { color:var(--muted); margin:6px 0 12px; }
.tiles { display:flex; flex-wrap:wrap; gap:12px; margin:8px 0 14px; }
.tile { flex:1 1 150px; border:1px solid var(--line); border-radius:6px; padding:10px 14px; }
.tile .v { font-size:22px; font-weight:600; }
.tile .k { color:var(--muted); font-size:12px; text-transform:uppercase; letter-spacing:.04em; }
.tile.good .v { color:#2e7d32; } .tile.bad .v { color:#c62828; }
table { border-collapse:collapse; margin:8px 0 14px; font-size:13px; }
th, td { padding:4px 10px; border-bottom:1px solid var(--line); text-align:right; }
th { background:#f0f3f6; font-weight:600; }
th:first-child, td:first-child { text-align:left; }
figure { margin:10px 0 18px; }
figure img { max-width:100%; height:auto; display:block; }
figcaption { color:var(--muted); font-size:12.5px; margin-top:4px; }
.grid2 { display:grid; grid-template-columns:repeat(auto-fit,minmax(420px,1fr)); gap:12px; }
.caveats { background:#fff4e5; border:2px solid #e08a00; border-radius:8px;
            padding:12px 24px; margin:22px 0; }
.caveats h2 { margin:0 0 6px; font-size:17px; color:#8a4b00; }
.caveats li { margin:3px 0; }
code { background:#f0f3f6; padding:1px 4px; border-radius:3px; font-size:12.5px; }
footer { color:var(--muted); font-size:12px; text-align:center; padding:20px; }
"""


@dataclass
class Section:
    """One report section: an anchor id, a title and its HTML blocks."""

    anchor: str
    title: str
    blocks: list[str] = field(default_factory=list)

    def add(self, *blocks: str) -> Section:
        self.blocks.extend(blocks)
        return self


def paragraph(text: str, note: bool = False) -> str:
    """A paragraph of escaped text (`note`: muted explanatory text)."""
    return f'<p{" class=note" if note else ""}>{html.escape(text)}</p>'


def raw(markup: str) -> str:
    """Trusted markup, inserted as is (only for markup built in this package)."""
    return markup


@dataclass(frozen=True)
class Link:
    """A table cell that links `text` to `href` (a relative path or URL)."""

    href: str
    text: str


def table(columns: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """An HTML table; floats shown with 3 significant decimals, None as a dash, `Link`s as
    links."""
    head = "".join(f"<th>{html.escape(str(c))}</th>" for c in columns)
    body = "".join("<tr>" + "".join(f"<td>{_cell(v)}</td>" for v in row) + "</tr>"
                   for row in rows)
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


def figure(png: bytes, caption: str = "", alt: str = "") -> str:
    """A PNG figure embedded as a base64 data URI, with a caption."""
    data = base64.b64encode(png).decode("ascii")
    cap = f"<figcaption>{html.escape(caption)}</figcaption>" if caption else ""
    return (f'<figure><img src="data:image/png;base64,{data}" alt="{html.escape(alt or caption)}">'
            f"{cap}</figure>")


def grid(*blocks: str) -> str:
    """Blocks side by side (wrapping on narrow screens)."""
    return '<div class="grid2">' + "".join(f"<div>{b}</div>" for b in blocks) + "</div>"


def tiles(items: Sequence[tuple[str, str, str]]) -> str:
    """Headline numbers: (label, value, mood) with mood "", "good" or "bad"."""
    cells = "".join(f'<div class="tile {mood}"><div class="v">{html.escape(value)}</div>'
                    f'<div class="k">{html.escape(label)}</div></div>'
                    for label, value, mood in items)
    return f'<div class="tiles">{cells}</div>'


def render(title: str, subtitle: str, sections: Sequence[Section], footer: str = "",
           caveats: Sequence[str] = ()) -> str:
    """The whole document; `caveats` (plain sentences) in a box above the first section."""
    nav = "".join(f'<a href="#{s.anchor}">{html.escape(s.title)}</a>' for s in sections)
    box = ('<div class="caveats" id="caveats"><h2>Caveats: read before trusting this run</h2>'
           "<ul>" + "".join(f"<li>{html.escape(c)}</li>" for c in caveats) + "</ul></div>"
           if caveats else "")
    body = box + "".join(f'<section id="{s.anchor}"><h2>{html.escape(s.title)}</h2>'
                   + "".join(s.blocks) + "</section>" for s in sections)
    return (
        "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
        "<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">"
        f"<title>{html.escape(title)}</title><style>{_CSS}</style></head><body>"
        f"<header><h1>{html.escape(title)}</h1><p>{html.escape(subtitle)}</p></header>"
        f"<nav>{nav}</nav><main>{body}</main>"
        f"<footer>{html.escape(footer)}</footer></body></html>\n"
    )


def number(value: Any, unit: str = "") -> str:
    """A measured value to 3 significant digits with its unit; "–" when it is missing (None
    or not finite)."""
    if value is None or not np.isfinite(value):
        return "–"
    return f"{value:.3g} {unit}".rstrip()


def _cell(value: Any) -> str:
    if isinstance(value, Link):
        return f'<a href="{html.escape(value.href)}">{html.escape(value.text)}</a>'
    return html.escape(_fmt(value))


def _fmt(value: Any) -> str:
    if value is None:
        return "–"
    if isinstance(value, float):
        if value != value:  # NaN
            return "–"
        return f"{value:.3g}" if abs(value) < 1000 else f"{value:,.0f}"
    return str(value)
