"""Small helpers for the metrics files in RUN/metrics/ (JSON without NaN, CSV tables)."""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .atomic import write_json, write_text


def finite_json(obj: Any) -> Any:
    """A copy of `obj` with NaN/Inf floats as None (strict JSON), numpy scalars as Python."""
    if isinstance(obj, dict):
        return {str(k): finite_json(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [finite_json(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return finite_json(obj.tolist())
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def write_metrics_json(path: Path, obj: Any) -> None:
    """Write strict JSON (NaN -> null) atomically."""
    write_json(path, finite_json(obj))


def write_csv(path: Path, columns: Sequence[str], rows: Sequence[dict[str, Any]]) -> None:
    """Write a CSV table atomically; floats with 6 significant digits, NaN/None as empty."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(columns)
    for row in rows:
        writer.writerow([_cell(row.get(c)) for c in columns])
    write_text(path, buf.getvalue())


def _cell(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, float | np.floating):
        return "" if not math.isfinite(float(value)) else f"{float(value):.6g}"
    return str(value)


def read_csv(path: Path) -> list[dict[str, Any]]:
    """Rows of a table written by `write_csv`, typed back: integers, floats, True/False as
    bool, empty cells left out (they were NaN or None)."""
    with open(path, encoding="utf-8", newline="") as f:
        return [{k: _typed(v) for k, v in row.items() if v not in ("", None)}
                for row in csv.DictReader(f)]


def _typed(text: str) -> Any:
    if text in ("True", "False"):
        return text == "True"
    for cast in (int, float):
        try:
            return cast(text)
        except ValueError:
            continue
    return text
