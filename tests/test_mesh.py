"""Tests of room_pipeline.anatomy.mesh (SDF -> lumen surface) and evaluate.surface.mesh_surface_distance."""
from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from room_pipeline.anatomy.mesh import MeshParams, extract_surface, mesh_topology
from room_pipeline.anatomy.sdf import SdfParams, compute_sdf
from room_pipeline.anatomy.tree import AirwayTree, Branch
from room_pipeline.errors import ConfigError, InputError
from room_pipeline.evaluate.surface import mesh_surface_distance
from room_pipeline.io.mesh import sample_surface
from room_pipeline.io.mesh import Mesh

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_sdf import grid_for, small_tree, true_mask_and_sdf  # noqa: E402  (shared analytic fixtures)

ROOT = Path(__file__).resolve().parents[1]
H = 0.7e-3


@pytest.fixture(scope="module")
def tree_case():
    tree = small_tree()
    mask, true = true_mask_and_sdf(tree, grid_for(tree, H))
    return tree, mask, true


def _check_closed(res):
    topo = mesh_topology(res.mesh)
    assert topo["watertight"] and topo["manifold"] and topo["orientation_consistent"], topo
    assert res.mesh.signed_volume() > 0
    assert res.report["watertight"] is True
    return topo


def test_params_match_yaml_and_reject_unknown_keys():
    cfg = yaml.safe_load((ROOT / "conf" / "mesh" / "default.yaml").read_text())
    assert set(cfg) == {f.name for f in dataclasses.fields(MeshParams)}
    assert MeshParams.from_dict(cfg) == MeshParams()
    with pytest.raises(ConfigError, match="mesh.nope"):
        MeshParams.from_dict({**cfg, "nope": True})
    with pytest.raises(ConfigError):
        MeshParams.from_dict({"decimation_fraction": 0})
    with pytest.raises(ConfigError):
        MeshParams.from_dict({"tetrahedralize": "yes"})


def test_ground_truth_sdf_gives_accurate_closed_surface(tree_case):
    tree, _, true = tree_case
    res = extract_surface(true, MeshParams())
    topo = _check_closed(res)
    assert topo["components"] == 1 and topo["euler_characteristic"] == 2
    e = mesh_surface_distance(res.mesh, tree, H)
    assert e["m2t_mean_vox"] <= 0.15 and e["m2t_p95_vox"] <= 0.5, e
    assert e["t2m_mean_vox"] <= 0.15 and e["t2m_p95_vox"] <= 0.5, e
    r = res.report
    assert r["n_faces"] < r["n_faces_before_decimation"]
    assert r["decimation_error_max_m"] <= MeshParams().decimation_max_error_mm * 1e-3
    assert r["decimation_error_p95_m"] <= MeshParams().decimation_p95_error_mm * 1e-3
    import json

    json.dumps(r)
    lumen_volume = float((true.data < 0).sum()) * H ** 3
    assert r["volume_m3"] == pytest.approx(lumen_volume, rel=0.05)


def test_chained_from_true_mask(tree_case):
    tree, mask, _ = tree_case
    res = extract_surface(compute_sdf(mask, SdfParams()), MeshParams())
    _check_closed(res)
    e = mesh_surface_distance(res.mesh, tree, H)
    assert e["m2t_mean_vox"] <= 0.2 and e["m2t_p95_vox"] <= 0.5, e


def test_decimation_bound_backs_off(tree_case):
    tree, _, true = tree_case
    tight = MeshParams(decimation_fraction=0.05, decimation_max_error_mm=0.02, decimation_p95_error_mm=0.005,
                       decimation_max_retries=2)
    res = extract_surface(true, tight)
    _check_closed(res)
    r = res.report
    if r["n_faces"] < r["n_faces_before_decimation"]:
        assert r["decimation_error_max_m"] <= 0.02e-3
    else:
        assert "decimation_note" in r
    assert r["decimation_fraction"] > 0.05


def test_airway_cut_by_border_is_closed():
    tree = AirwayTree([Branch(0, -1, 0, [0, 0, -0.1], [0, 0, 0.1], 2.5e-3),
                       Branch(1, 0, 1, [0, 0, 0], [0.004, 0, 0.1], 1.5e-3)])
    lo, hi = np.array([-5e-3, -5e-3, -6e-3]), np.array([7e-3, 5e-3, 6e-3])
    _, true = true_mask_and_sdf(tree, grid_for(tree, H, lo=lo, hi=hi))
    res = extract_surface(true, MeshParams(decimation_fraction=0.5))
    _check_closed(res)
    # the caps lie within one voxel beyond the border slices (the padding is one voxel of +spacing)
    assert res.mesh.vertices[:, 2].min() >= lo[2] - H and res.mesh.vertices[:, 2].max() <= hi[2] + 2 * H


def test_components_and_largest_only():
    tree = small_tree()
    iso = Branch(9, -1, 0, [0.02, 0.0, 0.0], [0.02, 0.0, -0.005], 1.5e-3)
    t2 = AirwayTree(tree.branches + [iso])
    _, true = true_mask_and_sdf(t2, grid_for(t2, 0.9e-3))
    res = extract_surface(true, MeshParams(decimation_fraction=1.0))
    assert res.report["n_components"] == 2
    res1 = extract_surface(true, MeshParams(decimation_fraction=1.0, keep_largest_component=True))
    assert res1.report["n_components"] == 1
    _check_closed(res1)


def test_empty_lumen_raises(tree_case):
    _, _, true = tree_case
    with pytest.raises(InputError, match="zero crossing"):
        extract_surface(true.with_data(np.abs(true.data) + 1e-3), MeshParams())


def test_negative_determinant_affine_keeps_outward_orientation(tree_case):
    _, _, true = tree_case
    aff = true.affine.copy()
    aff[0, 0] = -aff[0, 0]  # e.g. a LAS grid
    res = extract_surface(true.__class__(true.data, aff), MeshParams(decimation_fraction=1.0, smoothing="none"))
    _check_closed(res)


def test_tetrahedralize_small_mesh():
    tree = AirwayTree([Branch(0, -1, 0, [0, 0, 0], [0, 0, -6e-3], 2e-3)])
    _, true = true_mask_and_sdf(tree, grid_for(tree, 0.8e-3, margin=2e-3))
    res = extract_surface(true, MeshParams(decimation_fraction=0.3, tetrahedralize=True,
                                           tet_edge_length_fraction=0.15))
    v, t = res.tets
    assert t.shape[1] == 4 and len(t) > 10 and t.max() < len(v)
    a, b, c, d = (v[t[:, i]] for i in range(4))
    vol = np.abs(np.einsum("ij,ij->i", b - a, np.cross(c - a, d - a))).sum() / 6
    assert vol == pytest.approx(res.mesh.signed_volume(), rel=0.05)


# ------------------------------------------------------------------ topology / evaluation on known meshes
def _tetra():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    return v, f


def test_mesh_topology_known_cases():
    v, f = _tetra()
    t = mesh_topology(Mesh(v, f))
    assert t["watertight"] and t["manifold"] and t["orientation_consistent"]
    assert t["euler_characteristic"] == 2 and t["components"] == 1
    assert Mesh(v, f).signed_volume() == pytest.approx(1 / 6)
    open_ = mesh_topology(Mesh(v, f[:3]))
    assert open_["boundary_edges"] == 3 and not open_["watertight"]
    flipped = f.copy()
    flipped[0] = flipped[0, ::-1]
    assert not mesh_topology(Mesh(v, flipped))["orientation_consistent"]
    # two tetrahedra sharing one vertex: a non-manifold vertex
    v2 = np.vstack([v, v[1:] * -1])
    f2 = np.vstack([f, np.where(f == 0, 0, f + 3)[:, ::-1]])
    t2 = mesh_topology(Mesh(v2, f2))
    assert t2["non_manifold_vertices"] == 1 and t2["non_manifold_edges"] == 0 and not t2["manifold"]
    assert t2["components"] == 1
    # three faces on one edge
    f3 = np.vstack([f, [[0, 1, 2]]])
    assert mesh_topology(Mesh(v, f3))["non_manifold_edges"] >= 1


def test_mesh_surface_distance_sphere_known_offset():
    # an accurate sphere mesh of radius r + d against the tree sphere of radius r: distance d
    import open3d as o3d

    r, d = 5e-3, 0.2e-3
    s = o3d.geometry.TriangleMesh.create_sphere(radius=r + d, resolution=80)
    mesh = Mesh(np.asarray(s.vertices), np.asarray(s.triangles))
    tree = AirwayTree([Branch(0, -1, 0, [0, 0, 0], [0, 0, 0], r)])
    e = mesh_surface_distance(mesh, tree, spacing=0.5e-3)
    # faces of a polyhedral sphere lie slightly inside its circumsphere
    assert e["m2t_mean_m"] == pytest.approx(d, abs=0.03e-3)
    assert e["t2m_mean_m"] == pytest.approx(d, abs=0.03e-3)
    assert e["m2t_mean_vox"] == pytest.approx(e["m2t_mean_m"] / 0.5e-3)
    assert e["hausdorff_m"] == pytest.approx(d, abs=0.03e-3)
    pts = sample_surface(mesh, 0.2e-3)
    assert len(pts) > 1000


def test_mesh_topology_of_surface_with_handle():
    # a torus-like ring of capsules: genus 1 -> Euler characteristic 0
    n, R, r = 8, 6e-3, 1.5e-3
    ang = 2 * np.pi * np.arange(n + 1) / n
    pts = np.stack([R * np.cos(ang), R * np.sin(ang), np.zeros(n + 1)], axis=1)
    tree = AirwayTree([Branch(i, i - 1, 0, pts[i], pts[i + 1], r) for i in range(n)])
    _, true = true_mask_and_sdf(tree, grid_for(tree, 0.6e-3, margin=2e-3))
    res = extract_surface(true, MeshParams())
    _check_closed(res)
    assert res.report["euler_characteristic"] == 0
