"""Signed-distance evaluators the planner checks clearance with: world points (m) -> SDF (m, negative
inside the lumen)."""
from __future__ import annotations

from typing import Callable

import numpy as np
from scipy.ndimage import map_coordinates

from ..errors import ConfigError


SdfFn = Callable[[np.ndarray], np.ndarray]


def volume_sdf_fn(volume, outside: float = 1.0) -> SdfFn:
    """Trilinear interpolation of an SDF :class:`~room_pipeline.io.volume.Volume` (metres).

    The grid's voxels are cells centred on the samples: a point within half a voxel beyond the outermost
    samples (still inside the outermost cells, e.g. a route start on a mask cut in its top slice) reads the
    nearest face sample; points farther outside read ``outside`` metres (outside the lumen).
    """
    data = np.asarray(volume.data, dtype=np.float64)
    inv = np.linalg.inv(volume.affine)
    hi = np.asarray(data.shape[:3], dtype=np.float64) - 1.0

    def fn(points: np.ndarray) -> np.ndarray:
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        ijk = p @ inv[:3, :3].T + inv[:3, 3]
        in_cell = np.all((ijk >= -0.5) & (ijk <= hi + 0.5), axis=1)
        ijk = np.where(in_cell[:, None], np.clip(ijk, 0.0, hi), ijk)
        return map_coordinates(data, ijk.T, order=1, mode="constant", cval=float(outside), prefilter=False)

    return fn


def as_sdf_fn(sdf) -> SdfFn:
    """An SDF evaluator ``(N, 3) metres -> (N,) metres`` from a Volume, an AirwayTree or a callable.

    A callable may return ``(sdf, exact)`` like :meth:`AirwayTree.sdf`; the first item is used.
    """
    from ..anatomy.tree import AirwayTree
    from ..io.volume import Volume

    if isinstance(sdf, Volume):
        return volume_sdf_fn(sdf)
    if isinstance(sdf, AirwayTree):
        return lambda p: sdf.sdf(p)[0]
    if not callable(sdf):
        raise ConfigError(f"sdf_fn must be a callable, a Volume or an AirwayTree, got {type(sdf).__name__}")

    def fn(points: np.ndarray) -> np.ndarray:
        out = sdf(np.asarray(points, dtype=np.float64).reshape(-1, 3))
        if isinstance(out, tuple):
            out = out[0]
        return np.asarray(out, dtype=np.float64).reshape(-1)

    return fn
