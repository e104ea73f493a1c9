"""Which part of the airway wall goes to the physics engine: faces near the scope or near the route, cut
into bodies the engine accepts (pure NumPy / SciPy; see :mod:`~room_pipeline.robot.pybullet_adapter`, Airway)."""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..io.mesh import Mesh


def crop_faces(mesh: Mesh, points: np.ndarray, radius: float, tree: cKDTree | None = None) -> np.ndarray:
    """Sorted indices of the faces whose centroid is within ``radius`` of any of ``points``."""
    if tree is None:
        tree = cKDTree(mesh.vertices[mesh.faces].mean(axis=1))
    hits = tree.query_ball_point(np.asarray(points, float).reshape(-1, 3), radius)
    if len(hits) == 0:
        return np.zeros(0, dtype=np.int64)
    idx = np.unique(np.concatenate([np.asarray(h, dtype=np.int64) for h in hits]))
    return idx


def split_faces(vertices: np.ndarray, faces: np.ndarray, max_faces: int,
                order: np.ndarray | None = None) -> list[np.ndarray]:
    """Face indices cut into consecutive runs of ``order`` of at most ``max_faces`` each, each run sorted.

    ``order`` (a permutation of the faces) defaults to the faces sorted by centroid along the
    mesh's longest bounding-box axis (stable), so every run is a compact slab of the surface.
    Equal sizes (ceil(n / ceil(n / max_faces))).  Deterministic.
    """
    n = len(faces)
    if n == 0:
        return []
    if n <= max_faces:
        return [np.arange(n)]
    if order is None:
        cen = vertices[faces].mean(axis=1)
        axis = int(np.argmax(cen.max(axis=0) - cen.min(axis=0)))
        order = np.argsort(cen[:, axis], kind="stable")
    order = np.asarray(order, np.int64)
    k = -(-n // max_faces)
    size = -(-n // k)
    return [np.sort(order[i:i + size]) for i in range(0, n, size)]


def route_corridor(mesh: Mesh, samples: np.ndarray, radius: float) -> np.ndarray:
    """The wall near a route: every face whose bounding sphere (about its centroid) reaches within
    ``radius`` of a route sample point, so no part of a kept face's neighbourhood is lost to a
    large triangle whose centroid lies farther away.

    ``samples``: (N, 3) points along the route, in order (m).  Returns the face indices ordered
    by the index of their nearest sample (i.e. along the route; stable, deterministic).
    """
    V = mesh.vertices[mesh.faces]
    cen = V.mean(axis=1)
    reach = np.linalg.norm(V - cen[:, None], axis=2).max(axis=1)
    d, j = cKDTree(np.asarray(samples, float).reshape(-1, 3)).query(
        cen, distance_upper_bound=radius + float(reach.max(initial=0.0)))
    keep = np.flatnonzero(np.isfinite(d) & (d - reach <= radius))
    return keep[np.argsort(j[keep], kind="stable")]
