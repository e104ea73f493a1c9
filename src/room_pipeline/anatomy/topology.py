"""Topology figures of triangle meshes (numpy only): components, boundary / non-manifold edges and vertices."""
from __future__ import annotations

import numpy as np
from scipy import sparse
from scipy.sparse.csgraph import connected_components

from ..io.mesh import Mesh


def _components(n_vertices: int, faces: np.ndarray) -> tuple[int, np.ndarray]:
    """Connected components of faces (sharing a vertex): (count, label per face)."""
    if len(faces) == 0:
        return 0, np.zeros(0, dtype=np.int64)
    rows = np.repeat(faces[:, 0], 2)
    cols = faces[:, 1:].reshape(-1)
    g = sparse.coo_matrix((np.ones(len(rows), dtype=np.int8), (rows, cols)), shape=(n_vertices, n_vertices))
    _, lab = connected_components(g, directed=False)
    flab = lab[faces[:, 0]]
    uniq, flab = np.unique(flab, return_inverse=True)
    return len(uniq), flab


def mesh_topology(mesh: Mesh) -> dict:
    """Topology figures of a triangle mesh, computed in numpy.

    Returns boundary_edges, non_manifold_edges (shared by > 2 faces),
    non_manifold_vertices (faces around the vertex form more than one fan),
    watertight (no boundary or non-manifold edge), manifold (no non-manifold
    edge or vertex), orientation_consistent (every edge used once in each
    direction where it has two faces), components, euler_characteristic (V - E + F
    over referenced vertices), n_vertices, n_faces.
    """
    f = mesh.faces
    nv = mesh.n_vertices
    if len(f) == 0:
        return {"n_vertices": nv, "n_faces": 0, "boundary_edges": 0, "non_manifold_edges": 0,
                "non_manifold_vertices": 0, "watertight": False, "manifold": True,
                "orientation_consistent": True, "components": 0, "euler_characteristic": 0}
    he = np.stack([f, np.roll(f, -1, axis=1)], axis=2).reshape(-1, 2)  # directed half-edges
    und = np.sort(he, axis=1)
    key = und[:, 0] * np.int64(nv) + und[:, 1]
    ukey, inv, cnt = np.unique(key, return_inverse=True, return_counts=True)
    boundary = int(np.sum(cnt == 1))
    nonman_e = int(np.sum(cnt > 2))
    dkey = he[:, 0] * np.int64(nv) + he[:, 1]
    _, dcnt = np.unique(dkey, return_counts=True)
    # consistent: no directed half-edge repeated (two faces traversing an edge the same way)
    consistent = bool(np.all(dcnt == 1))
    # non-manifold vertices: link of the vertex has more than one connected piece
    corners = np.concatenate([f[:, [0, 1, 2]], f[:, [1, 2, 0]], f[:, [2, 0, 1]]])  # (centre, a, b)
    c, a, b = corners[:, 0], corners[:, 1], corners[:, 2]
    ka = c * np.int64(nv) + a
    kb = c * np.int64(nv) + b
    nodes, node_inv = np.unique(np.concatenate([ka, kb]), return_inverse=True)
    m = len(corners)
    g = sparse.coo_matrix((np.ones(m, dtype=np.int8), (node_inv[:m], node_inv[m:])), shape=(len(nodes), len(nodes)))
    _, lab = connected_components(g, directed=False)
    centre = nodes // nv
    pairs = np.unique(np.stack([centre, lab], axis=1), axis=0)
    pieces = np.bincount(pairs[:, 0], minlength=nv)
    nonman_v = int(np.sum(pieces > 1))
    used = np.unique(f)
    ncomp, _ = _components(nv, f)
    return {"n_vertices": int(nv), "n_faces": int(len(f)), "boundary_edges": boundary,
            "non_manifold_edges": nonman_e, "non_manifold_vertices": nonman_v,
            "watertight": bool(boundary == 0 and nonman_e == 0),
            "manifold": bool(nonman_e == 0 and nonman_v == 0),
            "orientation_consistent": consistent, "components": int(ncomp),
            "euler_characteristic": int(len(used) - len(ukey) + len(f))}
