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
