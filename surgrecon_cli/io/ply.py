"""PLY point clouds: the labelled per-frame writer (spec section 4) and a strict reader.

Writer: binary little-endian, written atomically, per-vertex `x y z` float32 (metres),
`red green blue` uchar, `point_id` int32, `label` uchar, `residual` float32 (metres), then any
extra properties. Readable by Open3D, plyfile, CloudCompare and MeshLab.

Reader: ascii and binary (little/big endian) `vertex` elements via numpy structured dtypes;
other elements (faces, edges, ...) are skipped. Anything malformed raises `InputError` with one
line naming the file. Vertices with non-finite coordinates are dropped and counted (a warning;
`read_ply_counted` returns the count).
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np

from ..errors import InputError
from .atomic import atomic_open

log = logging.getLogger(__name__)

# PLY type names (both spellings) -> numpy base type
_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_FORMATS = {"ascii": None, "binary_little_endian": "<", "binary_big_endian": ">"}
_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
_MAX_HEADER = 1 << 16  # bytes; a real header is a few hundred


# ----------------------------------------------------------------------------- writing
def _ply_type(arr: np.ndarray) -> tuple[str, str]:
    """(PLY type, little-endian numpy type) for an extra property, by dtype."""
    if arr.dtype == np.bool_ or arr.dtype == np.uint8:
        return "uchar", "u1"
    if np.issubdtype(arr.dtype, np.integer):
        return "int", "<i4"
    return "float", "<f4"


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

    xyz (N, 3) metres; rgb (N, 3) uint8 or float 0..1 (default grey 128); point_id (N,)
    (default 0..N-1); label (N,) (default 255 = unknown); residual (N,) metres (default 0;
    NaN allowed: no correspondence); extra {name: (N,)} after those, typed by dtype: bool /
    uint8 -> uchar, other integers -> int32, the rest -> float32.
    """
    xyz = np.asarray(xyz, dtype=float)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise InputError(f"{path}: xyz must have shape (N, 3), got {xyz.shape}")
    n = len(xyz)
    columns: list[tuple[str, str, str, np.ndarray]] = [
        ("x", "float", "<f4", xyz[:, 0]), ("y", "float", "<f4", xyz[:, 1]),
        ("z", "float", "<f4", xyz[:, 2]),
    ]
    colours = _as_uint8_rgb(rgb, n) if rgb is not None else np.full((n, 3), 128, np.uint8)
    columns += [(c, "uchar", "u1", colours[:, i]) for i, c in enumerate(("red", "green", "blue"))]
    defaults = {
        "point_id": ("int", "<i4", point_id, np.arange(n)),
        "label": ("uchar", "u1", label, np.full(n, 255)),
        "residual": ("float", "<f4", residual, np.zeros(n)),
    }
    for name, (ptype, dtype, given, default) in defaults.items():
        values = default if given is None else np.asarray(given)
        if values.shape != (n,):
            raise InputError(f"{path}: {name} must have shape ({n},), got {values.shape}")
        columns.append((name, ptype, dtype, values))
    taken = {c[0] for c in columns}
    for name, values in (extra or {}).items():
        values = np.asarray(values)
        if not _NAME.match(name) or name in taken:
            raise InputError(f"{path}: bad or duplicate extra property name {name!r}")
        if values.shape != (n,):
            raise InputError(f"{path}: extra {name!r} must have shape ({n},), got {values.shape}")
        taken.add(name)
        columns.append((name, *_ply_type(values), values))

    keep = np.all(np.isfinite(xyz), axis=1)
    dropped = int(n - keep.sum())
    table = np.empty(int(keep.sum()), dtype=[(c[0], c[2]) for c in columns])
    for name, _, _, values in columns:
        table[name] = values[keep]
    header = ["ply", "format binary_little_endian 1.0", "comment written by surgrecon",
              f"element vertex {len(table)}"]
    header += [f"property {ptype} {name}" for name, ptype, _, _ in columns]
    header.append("end_header")
    with atomic_open(path, "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(table.tobytes())
    return dropped


# ----------------------------------------------------------------------------- reading
class _Element:
    def __init__(self, name: str, count: int) -> None:
        self.name = name
        self.count = count
        self.props: list[tuple[str, str]] = []  # (name, numpy base type)
        self.lists: list[tuple[str, str, str]] = []  # (name, count type, item type)


def _parse_header(path: Path, data: bytes) -> tuple[str, list[_Element], int]:
    def bad(msg: str) -> InputError:
        return InputError(f"{path}: not a valid PLY file ({msg})")

    if not data.startswith(b"ply"):
        raise bad("missing 'ply' magic")
    end = data.find(b"end_header", 0, _MAX_HEADER)
    if end < 0:
        raise bad("no end_header")
    nl = data.find(b"\n", end)
    body = nl + 1 if nl >= 0 else len(data)
    try:
        lines = data[:end].decode("ascii").splitlines()
    except UnicodeDecodeError as exc:
        raise bad("header is not ASCII") from exc
    fmt = None
    elements: list[_Element] = []
    for raw in lines[1:]:
        words = raw.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        key = words[0]
        if key == "format":
            if len(words) != 3 or words[1] not in _FORMATS or words[2] != "1.0":
                raise bad(f"unsupported format line {raw.strip()!r}")
            fmt = words[1]
        elif key == "element":
            if len(words) != 3 or not words[2].isdigit():
                raise bad(f"bad element line {raw.strip()!r}")
            elements.append(_Element(words[1], int(words[2])))
        elif key == "property":
            if not elements:
                raise bad("property before any element")
            el = elements[-1]
            if len(words) == 5 and words[1] == "list":
                if words[2] not in _TYPES or words[3] not in _TYPES:
                    raise bad(f"unknown list type in {raw.strip()!r}")
                el.lists.append((words[4], _TYPES[words[2]], _TYPES[words[3]]))
            elif len(words) == 3:
                if words[1] not in _TYPES:
                    raise bad(f"unknown property type {words[1]!r}")
                if el.lists:
                    raise bad("scalar property after a list property is not supported")
                el.props.append((words[2], _TYPES[words[1]]))
            else:
                raise bad(f"bad property line {raw.strip()!r}")
        else:
            raise bad(f"unknown header keyword {key!r}")
    if fmt is None:
        raise bad("no format line")
    return fmt, elements, body


def _skip_binary(path: Path, data: bytes, pos: int, el: _Element, order: str) -> int:
    """Byte offset after element `el` starting at `pos` (list records walked one by one)."""
    fixed = int(np.dtype([(n, order + t) for n, t in el.props]).itemsize) if el.props else 0
    if not el.lists:
        return pos + fixed * el.count
    for _ in range(el.count):  # records of a non-vertex element with list properties
        pos += fixed
        for _, ctype, itype in el.lists:
            cdt = np.dtype(order + ctype)
            if pos + cdt.itemsize > len(data):
                raise InputError(f"{path}: truncated PLY file (element {el.name!r})")
            count = int(np.frombuffer(data, cdt, 1, pos)[0])
            if count < 0:
                raise InputError(f"{path}: negative list length {count} in element {el.name!r}")
            pos += cdt.itemsize + count * np.dtype(itype).itemsize
    return pos


def read_ply_counted(path: Path | str) -> tuple[dict[str, np.ndarray], int]:
    """Like `read_ply`, also returning how many non-finite vertices were dropped."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror or exc})") from exc
    fmt, elements, pos = _parse_header(path, data)
    names = [e.name for e in elements]
    if "vertex" not in names:
        raise InputError(f"{path}: PLY file has no vertex element")
    vertex = elements[names.index("vertex")]
    if vertex.lists:
        raise InputError(f"{path}: list properties on vertices are not supported")
    props = [p for p, _ in vertex.props]
    if len(set(props)) != len(props):
        raise InputError(f"{path}: duplicate vertex property names")
    if not {"x", "y", "z"} <= set(props):
        raise InputError(f"{path}: vertex element lacks x, y, z")
    if vertex.count == 0:
        raise InputError(f"{path}: empty point cloud (0 vertices)")
    if fmt == "ascii":
        table = _read_ascii(path, data[pos:], elements, vertex)
    else:
        order = _FORMATS[fmt] or "<"
        for el in elements[: names.index("vertex")]:
            pos = _skip_binary(path, data, pos, el, order)
        dtype = np.dtype([(n, order + t) for n, t in vertex.props])
        need = dtype.itemsize * vertex.count
        if pos + need > len(data):
            raise InputError(f"{path}: truncated PLY file: {vertex.count} vertices need "
                             f"{need} bytes, {max(len(data) - pos, 0)} present")
        table = np.frombuffer(data, dtype, vertex.count, pos)
    out = {n: np.ascontiguousarray(table[n]).astype(np.dtype(t)) for n, t in vertex.props}
    finite = np.isfinite(out["x"]) & np.isfinite(out["y"]) & np.isfinite(out["z"])
    dropped = int((~finite).sum())
    if dropped:
        out = {k: v[finite] for k, v in out.items()}
        if not finite.any():
            raise InputError(f"{path}: no vertex has finite coordinates")
    return out, dropped


def _read_ascii(path: Path, body: bytes, elements: list[_Element], vertex: _Element):
    lines = body.split(b"\n")
    start = 0
    for el in elements:
        if el is vertex:
            break
        start += el.count  # one record per line
    rows = [ln for ln in lines[start:start + vertex.count]]
    if len(rows) < vertex.count or (rows and not rows[-1].strip()):
        raise InputError(f"{path}: truncated PLY file: fewer than {vertex.count} vertex lines")
    width = len(vertex.props)
    try:
        tokens = np.array(b" ".join(rows).split(), dtype=float)
    except ValueError as exc:
        raise InputError(f"{path}: non-numeric value in an ascii vertex line") from exc
    if tokens.size != width * vertex.count:
        raise InputError(f"{path}: ascii vertex lines do not have {width} values each")
    cols = tokens.reshape(vertex.count, width)
    table = np.empty(vertex.count, dtype=[(n, t) for n, t in vertex.props])
    for i, (n, _) in enumerate(vertex.props):
        table[n] = cols[:, i]
    return table


def read_ply(path: Path | str) -> dict[str, np.ndarray]:
    """Vertex properties of a PLY file as {name: (N,) array} (ascii or binary, any endian).

    Non-finite vertices are dropped with a warning; malformed files raise `InputError`.
    """
    out, dropped = read_ply_counted(path)
    if dropped:
        log.warning("%s: dropped %d vertices with non-finite coordinates", path, dropped)
    return out
