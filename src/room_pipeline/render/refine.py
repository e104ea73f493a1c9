"""Conforming midpoint refinement of a triangle mesh: split every edge longer than a length, keep the surface.

Used by :mod:`room_pipeline.render.indirect` to run the light transport on a finer mesh than the render
mesh (``IndirectConfig.max_edge_mm``).  Each pass marks the edges longer than ``max_edge_m`` and splits
every triangle by its marked edges (1 -> 2, 2 -> 3, 3 -> 4 triangles; red-green refinement, so
neighbours agree and no hanging vertices appear), until no edge is longer or ``max_passes`` is reached.
Midpoints lie on the original flat triangles: the surface is the same, only sampled finer.  The original
vertices keep their indices ``0..V-1``; new ones are appended in a deterministic order (sorted edge keys).
The winding of every triangle is kept.  Units: metres.
"""
from __future__ import annotations

import numpy as np


def refine_long_edges(vertices: np.ndarray, faces: np.ndarray, max_edge_m: float, max_passes: int = 12):
    """Refined ``(vertices (V', 3) float64, faces (F', 3) int64, interp)``: ``interp`` is a sparse (V', V)
    CSR matrix whose rows give each refined vertex as a linear combination of the original ones (identity on
    the first V rows), so ``interp @ x`` is the piecewise-linear field of vertex values ``x`` on the new
    vertices.  ``max_edge_m`` > 0 (metres); a ValueError otherwise."""
    import scipy.sparse as sp

    if not (np.isfinite(max_edge_m) and max_edge_m > 0):
        raise ValueError(f"refine: max_edge_m must be > 0, got {max_edge_m}")
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    n0 = len(v)
    interp = sp.identity(n0, format="csr", dtype=np.float64)
    for _ in range(max_passes):
        e = np.stack([f, np.roll(f, -1, axis=1)], axis=2)               # (F, 3, 2): edges ab, bc, ca
        key = np.sort(e, axis=2).reshape(-1, 2)
        length = np.linalg.norm(v[key[:, 0]] - v[key[:, 1]], axis=1)
        long_ = length > max_edge_m
        if not long_.any():
            break
        ukey, inv = np.unique(key[long_], axis=0, return_inverse=True)
        mid = np.full(len(key), -1, dtype=np.int64)
        mid[np.flatnonzero(long_)] = len(v) + inv.reshape(-1)
        mid = mid.reshape(-1, 3)                                         # midpoint of edge k of each face
        v = np.concatenate([v, 0.5 * (v[ukey[:, 0]] + v[ukey[:, 1]])])
        half = sp.csr_matrix((np.full(2 * len(ukey), 0.5), (np.repeat(np.arange(len(ukey)), 2),
                                                             ukey.reshape(-1))), shape=(len(ukey), interp.shape[0]))
        interp = sp.vstack([interp, half @ interp], format="csr")
        marked = mid >= 0
        cnt = marked.sum(axis=1)
        out = [f[cnt == 0]]
        # one marked edge: rotate it to position 0 (a, b), then (a, m, c), (m, b, c)
        i1 = np.flatnonzero(cnt == 1)
        r = np.argmax(marked[i1], axis=1)
        t, m = _rot(f[i1], r), _rot(mid[i1], r)
        out += [np.stack([t[:, 0], m[:, 0], t[:, 2]], 1), np.stack([m[:, 0], t[:, 1], t[:, 2]], 1)]
        # two marked edges: rotate the unmarked one to position 2 (c, a); then (m_ab, b, m_bc), the quad
        # (a, m_ab, m_bc, c) cut along its shorter diagonal
        i2 = np.flatnonzero(cnt == 2)
        r = (np.argmin(marked[i2], axis=1) + 1) % 3
        t, m = _rot(f[i2], r), _rot(mid[i2], r)
        a, b, c, mab, mbc = t[:, 0], t[:, 1], t[:, 2], m[:, 0], m[:, 1]
        out.append(np.stack([mab, b, mbc], 1))
        d1 = np.linalg.norm(v[a] - v[mbc], axis=1) <= np.linalg.norm(v[mab] - v[c], axis=1)
        out.append(np.where(d1[:, None], np.stack([a, mab, mbc], 1), np.stack([a, mab, c], 1)))
        out.append(np.where(d1[:, None], np.stack([a, mbc, c], 1), np.stack([mab, mbc, c], 1)))
        # three: four triangles
        i3 = np.flatnonzero(cnt == 3)
        t, m = f[i3], mid[i3]
        out += [np.stack([t[:, 0], m[:, 0], m[:, 2]], 1), np.stack([m[:, 0], t[:, 1], m[:, 1]], 1),
                np.stack([m[:, 2], m[:, 1], t[:, 2]], 1), np.stack([m[:, 0], m[:, 1], m[:, 2]], 1)]
        f = np.concatenate(out).astype(np.int64)
    return v, f, interp


def _rot(a: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Rows of ``a`` (N, 3) rolled left by ``r`` (N,): new column k is old column (k + r) % 3."""
    idx = (np.arange(3)[None] + r[:, None]) % 3
    return np.take_along_axis(a, idx, axis=1)
