"""Binary little-endian PLY writer/reader for point sets with per-vertex properties and edges.

Used for the medial axis (points with radius and branch id, polyline edges)
and, later, point clouds.  Positions in metres; the header carries comments
stating units and frame.  Output bytes depend only on the inputs.
"""
from __future__ import annotations

import io
import os
from pathlib import Path
from typing import Mapping

import numpy as np

from ..errors import InputError
from .atomic import write_bytes

_PLY_TYPES = {np.dtype("float32"): "float", np.dtype("float64"): "double", np.dtype("int32"): "int",
              np.dtype("uint8"): "uchar", np.dtype("int64"): "int", np.dtype("uint32"): "uint"}
_NP_TYPES = {"float": "<f4", "double": "<f8", "int": "<i4", "uchar": "u1", "uint": "<u4"}


def encode_ply(vertex: Mapping[str, np.ndarray], edges: np.ndarray | None = None,
               comments: tuple[str, ...] = ()) -> bytes:
    """PLY bytes: ``vertex`` maps property name -> (N,) array (``x``, ``y``, ``z`` first);
    ``edges`` is an (E, 2) array of vertex indices."""
    names = list(vertex)
    n = len(vertex[names[0]])
    cols = []
    header = ["ply", "format binary_little_endian 1.0", *[f"comment {c}" for c in comments],
              f"element vertex {n}"]
    for name in names:
        a = np.asarray(vertex[name])
        if len(a) != n:
            raise ValueError(f"vertex property {name} has {len(a)} values, expected {n}")
        t = _PLY_TYPES.get(a.dtype)
        if t is None:
            raise ValueError(f"unsupported dtype {a.dtype} for {name}")
        header.append(f"property {t} {name}")
        cols.append((name, _NP_TYPES[t], a))
    rec = np.empty(n, dtype=[(nm, dt) for nm, dt, _ in cols])
    for nm, _, a in cols:
        rec[nm] = a
    body = rec.tobytes()
    if edges is not None:
        e = np.asarray(edges, dtype="<i4").reshape(-1, 2)
        header += [f"element edge {len(e)}", "property int vertex1", "property int vertex2"]
        body += e.tobytes()
    header.append("end_header")
    return ("\n".join(header) + "\n").encode("ascii") + body


def write_ply(path: str | os.PathLike, vertex: Mapping[str, np.ndarray], edges: np.ndarray | None = None,
              comments: tuple[str, ...] = ()) -> None:
    write_bytes(path, encode_ply(vertex, edges, comments))


def read_ply(path: str | os.PathLike) -> tuple[dict[str, np.ndarray], np.ndarray | None]:
    """Read what :func:`write_ply` writes: (vertex properties, edges or None)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"PLY not found: {path}")
    data = path.read_bytes()
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply") or end < 0:
        raise InputError(f"{path}: not a PLY file")
    lines = data[:end].decode("ascii").splitlines()
    if "format binary_little_endian 1.0" not in lines:
        raise InputError(f"{path}: only binary little-endian PLY is supported")
    elements: list[tuple[str, int, list[tuple[str, str]]]] = []
    for ln in lines:
        parts = ln.split()
        if parts[:1] == ["element"]:
            elements.append((parts[1], int(parts[2]), []))
        elif parts[:1] == ["property"]:
            if parts[1] == "list":
                raise InputError(f"{path}: list properties are not supported")
            elements[-1][2].append((parts[2], _NP_TYPES[parts[1]]))
    buf = io.BytesIO(data[end + len(b"end_header\n"):])
    out: dict[str, np.ndarray] = {}
    edges = None
    for name, count, props in elements:
        dt = np.dtype(props)
        arr = np.frombuffer(buf.read(dt.itemsize * count), dtype=dt, count=count)
        if name == "vertex":
            out = {p: arr[p].copy() for p, _ in props}
        elif name == "edge":
            edges = np.stack([arr["vertex1"], arr["vertex2"]], axis=1).astype(np.int64)
    return out, edges
