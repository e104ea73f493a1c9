"""A signed distance field sampled off the grid: SDF and its world gradient, trilinear, all four at once.

Used by the medial axis (:mod:`room_pipeline.anatomy.medial_axis`) and its trachea-root rules
(:mod:`room_pipeline.anatomy.trachea_root`).  Units: the volume's world frame (metres); indices are
continuous voxel indices (i, j, k) of the volume's affine.
"""
from __future__ import annotations

import numpy as np


class SdfField:
    """SDF + world gradient on a grid, trilinear lookup of all four channels at once."""

    def __init__(self, sdf: np.ndarray, affine: np.ndarray):
        A = affine[:3, :3]
        self.Ainv = np.linalg.inv(A)
        self.A = A
        self.t = affine[:3, 3]
        g = np.gradient(sdf.astype(np.float32))
        gw = np.einsum("ji,jxyz->xyzi", self.Ainv.astype(np.float32), np.stack(g))  # Ainv^T g
        self.vals = np.concatenate([sdf.astype(np.float32)[..., None], gw], axis=3).reshape(-1, 4)
        self.shape = np.array(sdf.shape)
        self.strides = np.array([sdf.shape[1] * sdf.shape[2], sdf.shape[2], 1], dtype=np.int64)
        self.offsets = np.array([(a * self.strides[0] + b * self.strides[1] + c * self.strides[2])
                                 for a in (0, 1) for b in (0, 1) for c in (0, 1)], dtype=np.int64)
        self.corner = np.array([(a, b, c) for a in (0, 1) for b in (0, 1) for c in (0, 1)], dtype=np.float32)

    def sample(self, ijk: np.ndarray) -> np.ndarray:
        """(N, 3) continuous indices -> (N, 4): sdf, world gradient."""
        p = np.clip(ijk, 0, self.shape - 1.000001)
        i0 = np.minimum(np.floor(p).astype(np.int64), self.shape - 2)
        f = (p - i0).astype(np.float32)
        base = i0 @ self.strides
        w = np.prod(np.where(self.corner[None] > 0, f[:, None, :], 1 - f[:, None, :]), axis=2)  # (N, 8)
        v = self.vals[base[:, None] + self.offsets[None]]  # (N, 8, 4)
        return np.einsum("nk,nkc->nc", w, v)

    def radius(self, ijk: np.ndarray) -> np.ndarray:
        """Lumen radius at (N, 3) indices: ``min_v (-sdf(v) + |x - v|)`` over the 8 surrounding voxels.

        The SDF is 1-Lipschitz, so every term bounds the true ``-sdf(x)`` from
        above and the minimum is exact on the medial ridge, where trilinear
        interpolation of the V-shaped profile underestimates the depth.
        """
        p = np.clip(ijk, 0, self.shape - 1.000001)
        i0 = np.minimum(np.floor(p).astype(np.int64), self.shape - 2)
        f = p - i0
        base = i0 @ self.strides
        s = self.vals[base[:, None] + self.offsets[None], 0].astype(np.float64)  # (N, 8)
        off = (f[:, None, :] - self.corner[None].astype(np.float64)) @ self.A.T  # (N, 8, 3) world
        return np.min(-s + np.linalg.norm(off, axis=2), axis=1)

    def to_world(self, ijk: np.ndarray) -> np.ndarray:
        return ijk @ self.A.T + self.t

    def to_index(self, xyz: np.ndarray) -> np.ndarray:
        return (xyz - self.t) @ self.Ainv.T
