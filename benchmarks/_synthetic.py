"""Synthetic capsule trees and ground-truth rasterisation shared by the sdf / mesh benchmarks, and the shared real
airway masks the anatomy benchmarks read (paths under ``../shared/data/airway_masks``)."""
from __future__ import annotations

import numpy as np

from room_pipeline.anatomy.tree import AirwayTree, Branch
from room_pipeline.io.volume import Volume


#: shared real airway masks: name -> path under ../shared/data/airway_masks (../shared/README.md)
REAL_MASKS = {"medmpd_1": "medmpd/patient1/bronchialTree.nii.gz", "medmpd_2": "medmpd/patient2/bronchialTree.nii.gz",
              "medmpd_3": "medmpd/patient3/bronchialTree.nii.gz", "airquant_demo": "airquant_demo/github_demo_seg.nii.gz",
              "atm_001": "public_trees/axes_fixed/ATM_001_0000_fixed.nii.gz",
              "case073": "public_trees/axes_fixed/CASE073_fixed.nii.gz",
              "case091": "public_trees/axes_fixed/CASE091_fixed.nii.gz"}


def capsule_tree(generations: int = 4, r0: float = 4e-3, length0: float = 30e-3, ratio: float = 0.75,
                 seed: int = 0) -> AirwayTree:
    """Symmetric dichotomous tree of capsules (metres), random branching planes."""
    rng = np.random.default_rng(seed)
    br = [Branch(0, -1, 0, [0, 0, 0.0], [0, 0, -length0], r0)]
    frontier, nid = [0], 1
    for g in range(1, generations + 1):
        nxt = []
        for pid in frontier:
            p = br[pid]
            d = p.direction
            e1 = np.cross(d, [1.0, 0, 0])
            if np.linalg.norm(e1) < 1e-6:
                e1 = np.cross(d, [0, 1.0, 0])
            e1 /= np.linalg.norm(e1)
            e2 = np.cross(d, e1)
            phi = rng.uniform(0, 2 * np.pi)
            perp = np.cos(phi) * e1 + np.sin(phi) * e2
            for s in (-1, 1):
                a = np.deg2rad(35) * s
                nd = np.cos(a) * d + np.sin(a) * perp
                br.append(Branch(nid, pid, g, p.end, p.end + 0.8 * p.length * nd, p.radius * ratio))
                nxt.append(nid)
                nid += 1
        frontier = nxt
    return AirwayTree(br)


def rasterise(tree: AirwayTree, spacing, margin: float = 5e-3) -> tuple[Volume, Volume]:
    """(true mask uint8, true SDF float32 metres) at voxel centres of a grid around the tree."""
    return tree.rasterise(spacing, margin)


def flat_trachea_mask(half_x: float = 12.0, half_y: float = 5.0, tilt_deg: float = 0.0, h: float = 0.7,
                      y_extent: float = 10.0) -> Volume:
    """A fibrotic-lung tree (as CASE073), all lengths in mm: the trachea has a ``2 half_x`` x ``2 half_y``
    elliptic cross-section, leans ``tilt_deg`` toward +x and runs out of the top of the volume (its medial surface
    is a sheet when flat, on which the skeleton runs parallel lines); main bronchi of 4.5 mm radius from the carina
    at z = -45.  Grid: x in [-45, 45], y in [-y_extent, y_extent], z in [-75, 0], spacing ``h``; affine in metres.
    Used by tests/test_medial_axis.py and benchmarks/anatomy_trachea_aspect.py."""
    mm = 1e-3
    x = np.arange(-45, 45.01, h)
    y = np.arange(-y_extent, y_extent + 0.01, h)
    z = np.arange(-75, 0.01, h)
    X, Y, Z = np.meshgrid(x, y, z, indexing="ij")
    xa = np.tan(np.deg2rad(tilt_deg)) * (Z + 45)
    m = (Z >= -45) & (((X - xa) / half_x) ** 2 + (Y / half_y) ** 2 <= 1.0)
    for sx in (-1.0, 1.0):
        d = np.array([sx * np.sin(0.6), 0.0, -np.cos(0.6)])
        t = np.clip((X * d[0] + (Z + 45) * d[2]), 0, 35)
        m |= (X - t * d[0]) ** 2 + Y ** 2 + (Z + 45 - t * d[2]) ** 2 <= 4.5 ** 2
    aff = np.diag([h * mm] * 3 + [1.0])
    aff[:3, 3] = [x[0] * mm, y[0] * mm, z[0] * mm]
    return Volume(m.astype(np.uint8), aff)
