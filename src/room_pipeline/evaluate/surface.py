"""Accuracy of an estimated SDF and of a lumen mesh against an analytic :class:`AirwayTree`.

All distances are returned in metres (keys ``*_m``) and in voxels of a given
size (keys ``*_vox``).  Only points where the tree's signed distance is exact
(see :meth:`AirwayTree.sdf`) enter the figures.
"""
from __future__ import annotations

import numpy as np

from ..anatomy.tree import AirwayTree
from ..io.mesh import Mesh, sample_surface
from ..io.volume import Volume


def _stats(err: np.ndarray, voxel: float, prefix: str) -> dict:
    err = np.abs(np.asarray(err, dtype=np.float64))
    if err.size == 0:
        return {f"{prefix}n": 0}
    mean, p95, mx = float(err.mean()), float(np.percentile(err, 95)), float(err.max())
    return {f"{prefix}n": int(err.size),
            f"{prefix}mean_m": mean, f"{prefix}p95_m": p95, f"{prefix}max_m": mx,
            f"{prefix}mean_vox": mean / voxel, f"{prefix}p95_vox": p95 / voxel, f"{prefix}max_vox": mx / voxel}


#: points per call of the tree's SDF in :meth:`TreeTruth.grid_band` (bounds its memory: ~0.4 GB of arrays)
GRID_BAND_SLAB_VOXELS = 4_000_000


class TreeTruth:
    """The exact quantities of one :class:`AirwayTree` that comparisons need, each computed once per argument:
    its signed distance at a grid's voxel centres within a band of the wall, and its surface samples.
    ``validate_anatomy`` measures two SDFs on one grid and two meshes at one spacing against the same tree."""

    def __init__(self, tree: AirwayTree) -> None:
        self.tree = tree
        self._grid: dict = {}
        self._samples: dict = {}

    def grid_band(self, vol: Volume, band: float) -> tuple[tuple[slice, ...], np.ndarray, np.ndarray]:
        """``(block, sel, true)``: the index block of ``vol`` that can lie within ``band`` (metres) of the
        wall, the flat indices (C order, in the block) of its voxels with an exact true SDF ``|true| <= band``,
        and that true SDF there (metres)."""
        key = (tuple(vol.shape), np.asarray(vol.affine, dtype=np.float64).tobytes(), float(band))
        if key not in self._grid:
            self._grid[key] = self._grid_band(vol, band)
        return self._grid[key]

    def _grid_band(self, vol: Volume, band: float):
        tree = self.tree
        lo, hi = tree.bounds(margin=band + 2 * float(vol.spacing.max()))
        # only voxels in the (grown) bounding box of the tree can lie within band of the wall
        w = vol.world_to_index(np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                                         for z in (lo[2], hi[2])]))
        shape = np.array(vol.shape)
        a = np.clip(np.floor(w.min(axis=0)).astype(int), 0, shape)
        b = np.clip(np.ceil(w.max(axis=0)).astype(int) + 1, 0, shape)
        aff = np.asarray(vol.affine, dtype=np.float64)
        ii, jj, kk = (np.arange(a[d], b[d], dtype=np.float64) for d in range(3))
        # slabs of the block along its first axis, each at most GRID_BAND_SLAB_VOXELS (a measured tree's grid is
        # its bounding box: the block is the whole 52 M-voxel volume); each point's value does not depend on
        # the others in its call, so the slabs give the whole block's arrays
        plane = max(1, len(jj) * len(kk))
        step = max(1, GRID_BAND_SLAB_VOXELS // plane)
        sels, trues = [], []
        for i0 in range(0, len(ii), step):
            sub = ii[i0:i0 + step]
            # voxel centres, world metres (the affine applied by broadcasting: no (N, 3) index array)
            pts = (aff[:3, 3] + sub[:, None, None, None] * aff[:3, 0] + jj[None, :, None, None] * aff[:3, 1]
                   + kk[None, None, :, None] * aff[:3, 2]).reshape(-1, 3)
            true, exact = tree.sdf(pts, band=band * 1.5 + 1e-9)
            sel = np.flatnonzero(exact & (np.abs(true) <= band))
            sels.append(sel + i0 * plane)
            trues.append(true[sel])
            del pts, true, exact
        sel = np.concatenate(sels) if sels else np.zeros(0, dtype=np.int64)
        true = np.concatenate(trues) if trues else np.zeros(0)
        return tuple(slice(int(a[d]), int(b[d])) for d in range(3)), sel, true

    def surface_samples(self, spacing: float) -> np.ndarray:
        """:meth:`AirwayTree.surface_samples` points at ``spacing`` (metres)."""
        key = float(spacing)
        if key not in self._samples:
            self._samples[key] = self.tree.surface_samples(spacing)[0]
        return self._samples[key]


def sdf_error(sdf_est: Volume, tree: AirwayTree, band: float, truth: TreeTruth | None = None) -> dict:
    """Error of ``sdf_est`` (metres) against the tree's exact SDF at voxel centres.

    Voxels with ``|true sdf| <= band`` (metres) and an exact true value are used.
    Returns n, MAE / p95 / max absolute error in metres (``mae_m`` ...) and in
    voxels (``mae_vox`` ..., voxel = geometric mean of the spacing), the mean
    signed error (``bias_m``, positive = estimate too far outside) and the
    fraction of voxels whose sign disagrees (``sign_mismatch``).  ``truth``: the
    tree's exact values shared with other comparisons (None: computed here).
    """
    truth = TreeTruth(tree) if truth is None else truth
    if truth.tree is not tree:
        raise ValueError("sdf_error: truth was computed for another tree")
    voxel = float(np.exp(np.mean(np.log(sdf_est.spacing))))
    block, sel, true = truth.grid_band(sdf_est, band)
    est = np.asarray(np.asarray(sdf_est.data)[block], dtype=np.float64).reshape(-1)[sel]
    err = est - true
    out = {"band_m": float(band), "voxel_m": voxel}
    s = _stats(err, voxel, "")
    out.update({"n": s.get("n", 0)})
    if s.get("n", 0):
        out.update(mae_m=s["mean_m"], p95_m=s["p95_m"], max_m=s["max_m"],
                   mae_vox=s["mean_vox"], p95_vox=s["p95_vox"], max_vox=s["max_vox"],
                   bias_m=float(err.mean()),
                   sign_mismatch=float(np.mean((est < 0) != (true < 0))))
    return out


def mesh_surface_distance(mesh: Mesh, tree: AirwayTree, spacing: float, truth: TreeTruth | None = None) -> dict:
    """Distances between a lumen mesh and the tree's exact surface (metres and voxels).

    ``spacing`` is the voxel size (metres) used to express distances in voxels;
    the mesh is sampled at about a quarter voxel.  mesh -> true: ``|tree sdf|`` at
    points uniformly sampled on the faces plus the vertices (exact values only).
    true -> mesh: distance from ``tree.surface_samples`` to the mesh (open3d
    ``RaycastingScene.compute_distance``).  Keys: ``m2t_*`` and ``t2m_*``
    (mean / p95 / max in ``_m`` and ``_vox``), ``hausdorff_m``/``hausdorff_vox``
    (symmetric), ``mean_m``/``mean_vox``/``p95_m``/``p95_vox`` of mesh -> true.
    ``truth``: the tree's surface samples shared with other comparisons (None: computed here).
    """
    from ..geometry.open3d_adapter import MeshScene

    pts = np.concatenate([sample_surface(mesh, spacing / 4.0), mesh.vertices])
    d, exact = tree.sdf(pts, band=8 * spacing)
    m2t = np.abs(d[exact])
    truth = TreeTruth(tree) if truth is None else truth
    if truth.tree is not tree:
        raise ValueError("mesh_surface_distance: truth was computed for another tree")
    samples = truth.surface_samples(spacing / 2.0)
    # distances in a local frame (float32 precision)
    t2m = MeshScene.of(mesh, origin=mesh.vertices.mean(axis=0)).distance(samples)
    out = {"voxel_m": float(spacing)}
    out.update(_stats(m2t, spacing, "m2t_"))
    out.update(_stats(t2m, spacing, "t2m_"))
    h = max(float(m2t.max()) if m2t.size else 0.0, float(t2m.max()) if t2m.size else 0.0)
    out.update(hausdorff_m=h, hausdorff_vox=h / spacing,
               mean_m=out.get("m2t_mean_m", float("nan")), mean_vox=out.get("m2t_mean_vox", float("nan")),
               p95_m=out.get("m2t_p95_m", float("nan")), p95_vox=out.get("m2t_p95_vox", float("nan")))
    return out
