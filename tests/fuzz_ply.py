"""Seeded PLY inputs for `register-pair` in tests/test_fuzz.py: valid pairs, NaN / Inf
vertices, all-NaN and empty clouds, bad headers, vertex counts larger than the file, flipped
bytes, truncation, degenerate clouds (1-4 points, coincident, collinear), huge and tiny
coordinates, float64 and big-endian files, a face element with bad list lengths before the
vertices, and bad --landmarks / --weights / --use-ids inputs."""

from __future__ import annotations

import random
import struct

import numpy as np
from fuzz_mcap import flip_bytes


def dome(n: int, rng: np.random.Generator) -> np.ndarray:
    r = 0.02 * np.sqrt(rng.uniform(0, 1, n))
    th = rng.uniform(0, 2 * np.pi, n)
    return np.c_[r * np.cos(th), r * np.sin(th), 0.008 * (1 - (r / 0.02) ** 2)]


def ply_bytes(xyz: np.ndarray, rgb: np.ndarray | None = None, fmt: str = "binary_little_endian",
              count: int | None = None, header_extra: str = "", dtype: str = "float",
              ids: np.ndarray | None = None) -> bytes:
    n = len(xyz)
    props = [f"property {dtype} {c}" for c in "xyz"]
    cols = [("x", xyz[:, 0]), ("y", xyz[:, 1]), ("z", xyz[:, 2])]
    if rgb is not None:
        props += [f"property uchar {c}" for c in ("red", "green", "blue")]
        cols += [(c, rgb[:, i]) for i, c in enumerate(("red", "green", "blue"))]
    if ids is not None:
        props.append("property int point_id")
        cols.append(("point_id", ids))
    head = (f"ply\nformat {fmt} 1.0\n{header_extra}element vertex {n if count is None else count}"
            "\n" + "\n".join(props) + "\nend_header\n")
    if fmt == "ascii":
        body = "".join(" ".join(repr(float(v)) if k < 3 else str(int(v))
                                for k, (_, col) in enumerate(cols) for v in [col[i]]) + "\n"
                       for i in range(n)).encode()
    else:
        order = "<" if fmt == "binary_little_endian" else ">"
        ftype = order + ("f4" if dtype == "float" else "f8")
        table = np.empty(n, [(c, ftype if k < 3 else order + "i4" if c == "point_id" else "u1")
                             for k, (c, _) in enumerate(cols)])
        for c, col in cols:
            table[c] = col
        body = table.tobytes()
    return head.encode() + body


def ply_element_first(xyz: np.ndarray, count: int, ctype: str, lists: list[int]) -> bytes:
    """A binary PLY with a `face` element (list property) before the vertices: `count`
    faces declared, `lists` the list lengths written (as `ctype`), each with int32 items."""
    head = (f"ply\nformat binary_little_endian 1.0\nelement face {count}\n"
            f"property list {ctype} int vertex_indices\nelement vertex {len(xyz)}\n"
            "property float x\nproperty float y\nproperty float z\nend_header\n").encode()
    code = {"char": "<b", "uchar": "<B", "int": "<i", "uint": "<I"}[ctype]
    faces = b"".join(struct.pack(code, k) + bytes(4 * max(min(k, 3), 0)) for k in lists)
    return head + faces + xyz.astype("<f4").tobytes()


def ply_cases(rng: random.Random, nprng: np.random.Generator, n_cases: int):
    """(family, source bytes, target bytes, expected exit, extra argv, extra files) tuples;
    "{dir}" in the argv is the case folder."""
    out = []
    families = ("valid", "nan", "all_nan", "empty", "header", "count", "flip", "truncate",
                "degenerate", "huge_values", "formats", "elements", "options")
    for k in range(n_cases):
        family = families[k % len(families)]
        n = int(nprng.integers(60, 160))
        src = dome(n, nprng)
        dst = src + nprng.normal(0, 2e-4, src.shape) + [0.001, 0, 0.0005]
        rgb = nprng.integers(0, 256, (n, 3)).astype(np.uint8)
        fmt = rng.choice(("binary_little_endian", "binary_big_endian", "ascii"))
        good = ply_bytes(dst, rgb, fmt)
        expect, extra, files = "any", [], {}
        if family == "valid":
            bad, expect = ply_bytes(src, rgb, fmt), "0"
        elif family == "nan":
            s = src.copy()
            s[nprng.choice(n, 5, replace=False), nprng.integers(0, 3)] = rng.choice(
                (np.nan, np.inf, -np.inf))
            bad, expect = ply_bytes(s, rgb, fmt), "0"
        elif family == "all_nan":
            bad, expect = ply_bytes(np.full_like(src, np.nan), rgb, fmt), "2"
        elif family == "empty":
            bad, expect = rng.choice((b"", b"ply\n", ply_bytes(src[:0], rgb[:0], fmt),
                                      b"ply\nformat ascii 1.0\nend_header\n")), "2"
        elif family == "header":
            expect = "2"
            bad = rng.choice((
                ply_bytes(src, rgb, fmt).replace(b"ply\n", b"plx\n", 1),
                ply_bytes(src, rgb, fmt).replace(b"end_header", b"end_headr"),
                ply_bytes(src, rgb, fmt).replace(b" 1.0\n", b" 2.0\n"),
                ply_bytes(src, rgb, fmt).replace(b"format", b"formt"),
                ply_bytes(src, rgb, fmt).replace(b"property float x", b"property quad x"),
                ply_bytes(src, rgb, fmt).replace(b"property float z", b"property float y"),
                ply_bytes(src, rgb, fmt).replace(b"property float z\n", b""),
                ply_bytes(src, rgb, fmt, header_extra="comment \xe9\n".encode("latin-1")
                          .decode("latin-1")),
                ply_bytes(src, rgb, fmt, header_extra="property float w\n"),
                b"ply\nformat ascii 1.0\n" + b"comment x\n" * 20000 + b"end_header\n",
                ply_bytes(src, rgb, fmt).replace(b"element vertex", b"element vertex -",
                                                 1),
                ply_bytes(src, rgb, fmt, header_extra="element face 3\nproperty list uchar "
                          "int vertex_indices\n"),
                ply_bytes(src, rgb, fmt).replace(b"property float x",
                                                 b"property list uchar float x"),
            ))
            if b"element face 3" in bad:
                expect = "any"
        elif family == "count":
            expect = "2"
            bad = ply_bytes(src, rgb, fmt, count=rng.choice((n + 1, n * 10, 10**12, 2**63)))
        elif family == "flip":
            b = bytearray(ply_bytes(src, rgb, fmt))
            flip_bytes(b, 0, len(b), rng, rng.randint(1, 8))
            bad = bytes(b)
        elif family == "truncate":
            b = ply_bytes(src, rgb, fmt)
            bad = b[: rng.randrange(0, len(b))]
        elif family == "degenerate":
            m = rng.choice((1, 2, 3, 4, n))
            how = rng.choice(("same", "line", "few"))
            pts = src[:m].copy()
            if how == "same":
                pts[:] = pts[0]
            elif how == "line":
                pts = np.c_[np.linspace(0, 0.01, m), np.zeros(m), np.zeros(m)]
            bad = ply_bytes(pts, rgb[:m], fmt)
            if rng.random() < 0.5:
                good = ply_bytes(pts + 1e-4, rgb[:m], fmt)
        elif family == "huge_values":
            scale = rng.choice((1e30, 3e38, 1e-30, 1e6))
            bad = ply_bytes(src * scale, rgb, fmt, dtype=rng.choice(("float", "double")))
        elif family == "formats":
            bad, expect = ply_bytes(src, None, fmt, dtype="double"), "0"
            extra = rng.choice(([], ["--use-ids"]))
            if extra:
                expect = "any"
        elif family == "elements":
            count, ctype, lists = rng.choice((
                (3, "uchar", [3, 3, 3]), (2, "char", [-1, -1]), (10**12, "char", [-1, 0, 3]),
                (10**12, "uchar", [0, 0]), (5, "int", [-(2**31), 3]), (3, "uint", [2**32 - 1]),
                (4, "int", [2**31 - 1, 1])))
            bad = ply_element_first(src.astype(np.float32), count, ctype, lists)
        elif family == "options":
            bad = ply_bytes(src, rgb, fmt)
            option = rng.choice(("--landmarks", "--weights", "--use-ids"))
            if option == "--landmarks":
                files["lm.csv"] = rng.choice((
                    b"0,999999\n", b"-1,0\n", b"5,5\n" * 1000, b"a,b\n0,1\n", b"0,1,2\n",
                    b"99999999999999999999,0\n", b"", b"src,dst\n", b"\xff\xfe0,1\n"))
                extra = ["--landmarks", "{dir}/lm.csv"]
            elif option == "--weights":
                w = np.ones(rng.choice((n, n - 1, 0)))
                if len(w):
                    w[: rng.randint(1, len(w))] = rng.choice((np.nan, -1.0, np.inf, 0.0, 1e300))
                files["w.txt"] = "\n".join(repr(float(v)) for v in w).encode()
                extra = ["--weights", "{dir}/w.txt"]
            else:
                ids = nprng.integers(-5, n + 5, n)
                ids[: rng.randint(0, 3)] = rng.choice((-(2**31), 2**31 - 1))
                good = ply_bytes(dst, rgb, fmt, ids=ids)
                extra = ["--use-ids"]
        out.append((family, bad, good, expect, extra, files))
    return out
