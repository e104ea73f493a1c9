"""Triangle meshes: an in-memory :class:`Mesh` and deterministic OBJ / PLY I/O."""
from __future__ import annotations

import dataclasses
import io
import os
from pathlib import Path

import numpy as np

from ..errors import InputError
from .atomic import write_text


@dataclasses.dataclass
class Mesh:
    """Triangle mesh in world RAS+ metres.

    Attributes:
        vertices: (N, 3) float64 positions, metres.
        faces: (M, 3) int64 vertex indices, counter-clockwise seen from outside.
    """

    vertices: np.ndarray
    faces: np.ndarray

    def __post_init__(self) -> None:
        self.vertices = np.asarray(self.vertices, dtype=np.float64).reshape(-1, 3)
        self.faces = np.asarray(self.faces, dtype=np.int64).reshape(-1, 3)

    @property
    def n_vertices(self) -> int:
        return len(self.vertices)

    @property
    def n_faces(self) -> int:
        return len(self.faces)

    def face_normals(self) -> np.ndarray:
        v = self.vertices
        n = np.cross(v[self.faces[:, 1]] - v[self.faces[:, 0]], v[self.faces[:, 2]] - v[self.faces[:, 0]])
        ln = np.linalg.norm(n, axis=1, keepdims=True)
        return n / np.where(ln > 0, ln, 1.0)

    def area(self) -> float:
        v = self.vertices
        n = np.cross(v[self.faces[:, 1]] - v[self.faces[:, 0]], v[self.faces[:, 2]] - v[self.faces[:, 0]])
        return float(0.5 * np.linalg.norm(n, axis=1).sum())

    def signed_volume(self) -> float:
        """Enclosed volume (m^3); positive when faces are oriented outward."""
        v = self.vertices
        a, b, c = v[self.faces[:, 0]], v[self.faces[:, 1]], v[self.faces[:, 2]]
        return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def sample_surface(mesh: Mesh, spacing: float, rng: np.random.Generator | None = None,
                   max_points: int = 2_000_000) -> np.ndarray:
    """Points uniformly distributed on the mesh faces, about one per ``spacing**2`` of area (metres).

    At least 1000 and at most ``max_points`` points; ``rng`` defaults to a fixed seed (deterministic).
    """
    rng = rng or np.random.default_rng(0)
    v, f = mesh.vertices, mesh.faces
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    areas = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    total = float(areas.sum())
    if total <= 0:
        return np.empty((0, 3))
    n = int(min(max_points, max(1000, np.ceil(total / spacing ** 2))))
    face = rng.choice(len(f), size=n, p=areas / total)
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    return (1 - s)[:, None] * a[face] + (s * (1 - r2))[:, None] * b[face] + (s * r2)[:, None] * c[face]


def write_obj(path: str | os.PathLike, mesh: Mesh, header: str = "") -> None:
    """Wavefront OBJ, vertices in metres with 9 decimals (nanometre), written atomically."""
    buf = io.StringIO()
    for line in header.splitlines():
        buf.write(f"# {line}\n")
    buf.write(f"# vertices {mesh.n_vertices} faces {mesh.n_faces}; units: m; frame: RAS+\n")
    np.savetxt(buf, mesh.vertices, fmt="v %.9f %.9f %.9f")
    np.savetxt(buf, mesh.faces + 1, fmt="f %d %d %d")
    write_text(path, buf.getvalue())


def read_obj(path: str | os.PathLike) -> Mesh:
    """Read vertices and (triangulated) faces of an OBJ file; other records are ignored."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"mesh not found: {path}")
    verts, faces = [], []
    with open(path, encoding="utf-8") as fh:
        for line in fh:
            if line.startswith("v "):
                verts.append([float(x) for x in line.split()[1:4]])
            elif line.startswith("f "):
                idx = [int(tok.split("/")[0]) for tok in line.split()[1:]]
                idx = [i - 1 if i > 0 else len(verts) + i for i in idx]
                for t in range(1, len(idx) - 1):
                    faces.append([idx[0], idx[t], idx[t + 1]])
    if not verts or not faces:
        raise InputError(f"{path}: OBJ holds no triangles")
    return Mesh(np.array(verts), np.array(faces))
