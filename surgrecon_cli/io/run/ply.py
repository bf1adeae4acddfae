"""PLY point clouds on `plyfile`: the labelled per-frame writer (spec section 4) and a strict
reader.

Writer: binary little-endian, written atomically, per-vertex `x y z` float32 (metres),
`red green blue` uchar, `point_id` int32, `label` uchar, `residual` float32 (metres, NaN =
none), `scalar_label` float32 (the label again, which CloudCompare loads as a scalar field),
then any extra properties; one header comment per property says what it holds. Readable by
Open3D, plyfile, CloudCompare and MeshLab.

Reader: ascii and binary (little/big endian) files; the `vertex` element's properties are
returned, other elements (faces, edges, ...) are read and ignored. Anything malformed raises
`InputError` with one line naming the file. Vertices with a non-finite x, y or z are dropped
and counted (a warning; `read_ply_counted` returns the count); non-finite values of other
properties are kept.
"""

from __future__ import annotations

import logging
import os
import re
from pathlib import Path

import numpy as np
from plyfile import PlyData, PlyElement, PlyElementParseError, PlyListProperty, PlyParseError

from ...core.classify.labels import CLASS_NAMES, STATUS_NAMES, UNKNOWN
from ...errors import InputError
from .atomic import atomic_open

log = logging.getLogger(__name__)

_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
_ELEMENT = re.compile(rb"^\s*element\s+(\S+)\s+(-?\d+)", re.MULTILINE)
_MAX_HEADER = 1 << 16  # bytes; a real header is a few hundred


def _codes(names: dict[int, str]) -> str:
    return ", ".join(f"{code} {name}" for code, name in names.items())


# One header comment per property (extras by the names the stages write).
_DOCS = {
    "x": "position x (m)",
    "y": "position y (m)",
    "z": "position z (m)",
    "red": "colour red (0-255)",
    "green": "colour green (0-255)",
    "blue": "colour blue (0-255)",
    "point_id": "template point index, stable across frames",
    "label": f"{_codes(CLASS_NAMES)}, {UNKNOWN} unknown",
    "residual": "distance to the point's target or correspondence (m); NaN = none",
    "scalar_label": "label as float32 (a scalar field in CloudCompare)",
    "status": f"reprojection check: {_codes(STATUS_NAMES)}",
    "views": "cameras that tracked the point",
    "n_views": "cameras that saw the point",
    "sigma": "RMS 3D position uncertainty (m); NaN = unknown",
    "deform_floor": "rigid-fit RMS a bend along the lines of sight needs to be labelled "
                    "deforming (m); NaN = not labelled",
    "reprojection_px": "RMS reprojection error (px)",
    "correspondence": "target vertex index (-1 = none)",
    "outlier": "1 = matched but the residual is above registration.outlier_mm",
}


# ----------------------------------------------------------------------------- writing
def _extra_type(arr: np.ndarray) -> str:
    """Little-endian numpy type of an extra property, by dtype."""
    if arr.dtype == np.bool_ or arr.dtype == np.uint8:
        return "u1"
    if np.issubdtype(arr.dtype, np.integer):
        return "<i4"
    return "<f4"


def _as_uint8_rgb(rgb: np.ndarray, n: int) -> np.ndarray:
    rgb = np.asarray(rgb)
    if rgb.shape != (n, 3):
        raise InputError(f"rgb: expected shape ({n}, 3), got {rgb.shape}")
    if np.issubdtype(rgb.dtype, np.integer):
        return np.clip(rgb, 0, 255).astype(np.uint8)
    vals = np.nan_to_num(np.asarray(rgb, float), nan=0.0)
    return np.clip(np.round(vals * 255.0), 0, 255).astype(np.uint8)


def write_cloud_ply(
    path: Path | str,
    xyz: np.ndarray,
    rgb: np.ndarray | None = None,
    point_id: np.ndarray | None = None,
    label: np.ndarray | None = None,
    residual: np.ndarray | None = None,
    extra: dict[str, np.ndarray] | None = None,
) -> int:
    """Write a labelled cloud atomically; returns the number of non-finite points dropped.

    xyz (N, 3) metres; a point with a non-finite coordinate is not written. rgb (N, 3) uint8
    or float 0..1 (default grey 128); point_id (N,) (default 0..N-1); label (N,) (default
    255 = unknown), also written as `scalar_label` float32; residual (N,) metres (default
    0; NaN allowed: no target). extra {name: (N,)} after those, typed by dtype: bool /
    uint8 -> uchar, other integers -> int32, the rest -> float32 (NaN kept); an extra named
    `scalar_label` (as `read_ply` returns it) is replaced by the one derived from `label`.
    """
    xyz = np.asarray(xyz, dtype=float)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise InputError(f"{path}: xyz must have shape (N, 3), got {xyz.shape}")
    n = len(xyz)
    colours = _as_uint8_rgb(rgb, n) if rgb is not None else np.full((n, 3), 128, np.uint8)
    columns: list[tuple[str, str, np.ndarray]] = [
        ("x", "<f4", xyz[:, 0]), ("y", "<f4", xyz[:, 1]), ("z", "<f4", xyz[:, 2]),
        *((c, "u1", colours[:, i]) for i, c in enumerate(("red", "green", "blue"))),
    ]
    given = {
        "point_id": ("<i4", np.arange(n) if point_id is None else point_id),
        "label": ("u1", np.full(n, UNKNOWN) if label is None else label),
        "residual": ("<f4", np.zeros(n) if residual is None else residual),
    }
    given["scalar_label"] = ("<f4", given["label"][1])
    for name, (dtype, values) in given.items():
        values = np.asarray(values)
        if values.shape != (n,):
            raise InputError(f"{path}: {name} must have shape ({n},), got {values.shape}")
        columns.append((name, dtype, values))
    taken = {c[0] for c in columns}
    for name, values in (extra or {}).items():
        if name == "scalar_label":
            continue
        values = np.asarray(values)
        if not _NAME.match(name) or name in taken:
            raise InputError(f"{path}: bad or duplicate extra property name {name!r}")
        if values.shape != (n,):
            raise InputError(f"{path}: extra {name!r} must have shape ({n},), got {values.shape}")
        taken.add(name)
        columns.append((name, _extra_type(values), values))

    keep = np.all(np.isfinite(xyz), axis=1)
    table = np.empty(int(keep.sum()), dtype=[(name, dtype) for name, dtype, _ in columns])
    for name, _, values in columns:
        table[name] = values[keep]
    comments = ["written by surgrecon"]
    comments += [f"{name}: {_DOCS.get(name, 'extra property')}" for name, _, _ in columns]
    ply = PlyData([PlyElement.describe(table, "vertex")], text=False, byte_order="<",
                  comments=comments)
    with atomic_open(path, "wb") as f:
        ply.write(f)
    return n - len(table)


# ----------------------------------------------------------------------------- reading
def _check_counts(path: Path | str, head: bytes, size: int) -> None:
    """Reject a file without the magic or `end_header` in its first 64 KiB, or with an
    element of more records than bytes after the header (before anything is allocated)."""
    if not head.startswith(b"ply"):
        raise InputError(f"{path}: not a valid PLY file (missing 'ply' magic)")
    end = head.find(b"end_header")
    if end < 0:
        raise InputError(f"{path}: not a valid PLY file (no end_header in the first "
                         f"{_MAX_HEADER} bytes)")
    for match in _ELEMENT.finditer(head[:end]):
        name, count = match[1].decode("ascii", "replace"), int(match[2])
        if count < 0:
            raise InputError(f"{path}: not a valid PLY file (element {name!r} has {count} "
                             "records)")
        if count > size - end:
            raise InputError(f"{path}: truncated PLY file: element {name!r} declares {count} "
                             f"records, at most {size - end} bytes follow the header")


def _parse_error(path: Path | str, exc: PlyElementParseError) -> InputError:
    """One line for plyfile's error on an element's data."""
    what = {"early end-of-file": "truncated PLY file",
            "early end-of-line": "wrong number of values in an ascii line",
            "expected end-of-line": "wrong number of values in an ascii line",
            "malformed input": "non-numeric value in an ascii line"}.get(exc.message,
                                                                         "not a valid PLY file")
    return InputError(f"{path}: {what} ({exc})")


def read_ply_counted(path: Path | str) -> tuple[dict[str, np.ndarray], int]:
    """Like `read_ply`, also returning how many vertices with a non-finite x, y or z were
    dropped."""
    try:
        with open(path, "rb") as f:
            _check_counts(path, f.read(_MAX_HEADER), os.fstat(f.fileno()).st_size)
            f.seek(0)
            ply = PlyData.read(f)  # binary elements without lists are memory-mapped
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror or exc})") from exc
    except PlyElementParseError as exc:
        raise _parse_error(path, exc) from exc
    except OverflowError as exc:
        raise InputError(f"{path}: value out of range for its property type ({exc})") from exc
    except UnicodeDecodeError as exc:
        raise InputError(f"{path}: not a valid PLY file (non-ASCII byte in the header or an "
                         "ascii body)") from exc
    except (PlyParseError, ValueError) as exc:
        raise InputError(f"{path}: not a valid PLY file ({exc})") from exc
    if "vertex" not in ply:
        raise InputError(f"{path}: PLY file has no vertex element")
    vertex = ply["vertex"]
    if any(isinstance(p, PlyListProperty) for p in vertex.properties):
        raise InputError(f"{path}: list properties on vertices are not supported")
    if not {"x", "y", "z"} <= {p.name for p in vertex.properties}:
        raise InputError(f"{path}: vertex element lacks x, y, z")
    if vertex.count == 0:
        raise InputError(f"{path}: empty point cloud (0 vertices)")
    table = vertex.data
    out = {p.name: table[p.name].astype(table.dtype[p.name].newbyteorder("="))
           for p in vertex.properties}
    finite = np.isfinite(out["x"]) & np.isfinite(out["y"]) & np.isfinite(out["z"])
    dropped = int((~finite).sum())
    if dropped:
        if not finite.any():
            raise InputError(f"{path}: no vertex has finite coordinates")
        out = {k: v[finite] for k, v in out.items()}
    return out, dropped


def read_ply(path: Path | str) -> dict[str, np.ndarray]:
    """Vertex properties of a PLY file as {name: (N,) array} (ascii or binary, any endian,
    native byte order).

    Vertices with a non-finite x, y or z are dropped with a warning; malformed files raise
    `InputError`.
    """
    out, dropped = read_ply_counted(path)
    if dropped:
        log.warning("%s: dropped %d vertices with non-finite coordinates", path, dropped)
    return out
