"""The anatomy chain on real data from ../shared/data (skipped when absent).

Real airway masks (Med-MPD patients 1-3, AirQuant demo): mask -> sdf -> mesh must give a watertight,
outward-oriented surface whose SDF agrees with the mask.  Real CT segmentation is measured in
``tests/test_real_ct_segmentation.py``; every real mask through every stage in ``tests/test_real_pipeline.py``.
"""
from __future__ import annotations

import numpy as np
import pytest

from room_pipeline.io.volume import read_volume

from .conftest import shared_path

pytestmark = pytest.mark.shared

MASKS = [("airway_masks", "medmpd", "patient1", "bronchialTree.nii.gz"),
         ("airway_masks", "medmpd", "patient2", "bronchialTree.nii.gz"),
         ("airway_masks", "medmpd", "patient3", "bronchialTree.nii.gz"),
         ("airway_masks", "airquant_demo", "github_demo_seg.nii.gz")]


@pytest.mark.parametrize("parts", [p if p[-2] == "airquant_demo" else pytest.param(p, marks=pytest.mark.exhaustive)
                                   for p in MASKS], ids=lambda p: p[-2])    # Med-MPD 1: test_real_pipeline
def test_real_mask_chain(parts):
    from room_pipeline.anatomy.mesh import MeshParams, extract_surface, mesh_topology
    from room_pipeline.anatomy.sdf import SdfParams, compute_sdf
    from room_pipeline.anatomy.segment import validate_mask

    mask = validate_mask(read_volume(shared_path(*parts)))
    inside = np.asarray(mask.data) > 0
    sdf = compute_sdf(mask.with_data(inside), SdfParams())
    s = np.asarray(sdf.data)
    assert np.mean(s[inside] < 0) > 0.99          # sign agrees with the mask
    assert np.mean(s[~inside] > 0) > 0.999
    res = extract_surface(sdf, MeshParams())
    topo = mesh_topology(res.mesh)
    assert topo["watertight"] and topo["orientation_consistent"]
    assert res.mesh.signed_volume() > 0
    # enclosed volume close to the mask's voxel volume
    vox_vol = inside.sum() * float(np.prod(mask.spacing))
    assert res.mesh.signed_volume() == pytest.approx(vox_vol, rel=0.15)
