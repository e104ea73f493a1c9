"""Medial axis extraction (anatomy.medial_axis) and centreline metrics (evaluate.centreline)."""
from __future__ import annotations

import logging
import sys
from pathlib import Path

import numpy as np
from scipy import ndimage
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from room_pipeline.anatomy.centreline import CentrelineGraph, GraphBranch, from_airway_tree
from room_pipeline.anatomy.medial_axis import (MedialAxisParams, crop_to_interior, extract_medial_axis)
from room_pipeline.anatomy.sdf import SdfParams, compute_sdf
from room_pipeline.anatomy.tree import AirwayTree, Branch
from room_pipeline.errors import ConfigError, InputError
from room_pipeline.evaluate.centreline import centreline_metrics
from room_pipeline.io.volume import Volume, read_volume

from .conftest import REPO, shared_path

sys.path.insert(0, str(REPO / "benchmarks"))
from _synthetic import flat_trachea_mask  # noqa: E402  (shared with benchmarks/anatomy_trachea_aspect.py)

MM = 1e-3
SP = 0.5 * MM


# --------------------------------------------------------------------------- helpers
def mask_of(tree: AirwayTree, spacing: float = SP, margin: float = 3 * MM) -> Volume:
    """Voxel centre inside the capsule union -> mask on a grid around the tree."""
    return tree.rasterise(spacing, margin, band=0.01)[0]


def sdf_of(tree: AirwayTree, spacing: float = SP) -> Volume:
    return compute_sdf(mask_of(tree, spacing), SdfParams())


def check_tree(graph: CentrelineGraph, sdf: Volume | None = None) -> None:
    """Structural invariants of an extracted graph."""
    ids = {b.id for b in graph.branches}
    assert graph.root.parent == -1
    for b in graph.branches:
        assert len(b.points) >= 2 and np.all(b.radius >= 0)
        if b.parent != -1:
            p = graph.branch(b.parent)
            assert b.parent in ids
            np.testing.assert_allclose(b.points[0], p.points[-1], atol=1e-9)
            assert b.generation == p.generation + 1
            assert len(graph.children(b.parent)) >= 2  # nodes are bifurcations only
        assert len(graph.path_to(b.id)) == b.generation + 1  # no cycle
    if sdf is not None:
        from scipy import ndimage
        P, _, _ = graph.all_points()
        v = ndimage.map_coordinates(sdf.data, sdf.world_to_index(P).T, order=1, mode="nearest")
        assert np.all(v < 0), "centreline leaves the lumen"


def y_tree(angle_deg=35.0, child_len=20 * MM, r0=3 * MM, r1=2 * MM, r2=2 * MM, phi=0.0) -> AirwayTree:
    a = np.deg2rad(angle_deg)
    e = np.array([np.cos(phi), np.sin(phi), 0.0])
    top, car = np.array([0, 0, 0.0]), np.array([0, 0, -25 * MM])
    d1 = np.cos(a) * np.array([0, 0, -1.0]) + np.sin(a) * e
    d2 = np.cos(a) * np.array([0, 0, -1.0]) - np.sin(a) * e
    return AirwayTree([Branch(0, -1, 0, top, car, r0), Branch(1, 0, 1, car, car + child_len * d1, r1),
                       Branch(2, 0, 1, car, car + child_len * d2, r2)])


def leaf_ends(graph):
    return np.array([b.points[-1] for b in graph.leaves()])


def near(points, target, tol):
    return bool(np.min(np.linalg.norm(points - np.asarray(target), axis=1)) <= tol)


# --------------------------------------------------------------------------- params
def test_params_yaml_matches_defaults():
    d = yaml.safe_load((REPO / "conf" / "medial_axis" / "default.yaml").read_text())
    assert MedialAxisParams.from_dict(d) == MedialAxisParams()
    assert set(d) == set(MedialAxisParams().__dict__)


def test_params_reject_unknown_and_bad_values():
    with pytest.raises(ConfigError, match="medial_axis.bogus"):
        MedialAxisParams.from_dict({"bogus": 1})
    with pytest.raises(ConfigError, match="step_voxels"):
        MedialAxisParams.from_dict({"step_voxels": 0})
    with pytest.raises(ConfigError, match="n_surface_samples"):
        MedialAxisParams.from_dict({"n_surface_samples": 1.5})
    with pytest.raises(ConfigError, match="min_descent"):
        MedialAxisParams.from_dict({"min_descent": "x"})


def test_no_interior_raises():
    with pytest.raises(InputError, match="no interior"):
        extract_medial_axis(Volume(np.ones((8, 8, 8), np.float32), np.eye(4) * 1e-3 + np.diag([0, 0, 0, 1 - 1e-3])))


# --------------------------------------------------------------------------- metrics on hand-built graphs
def _g(branches):
    return CentrelineGraph([GraphBranch(i, p, g, np.asarray(pts, float) * MM, np.full(len(pts), r * MM))
                            for i, p, g, pts, r in branches])


def _y_graph(shift=(0, 0, 0)):
    s = np.asarray(shift, float)
    return _g([(0, -1, 0, [[0, 0, 0] + s, [0, 0, -20] + s], 4.0),
               (1, 0, 1, [[0, 0, -20] + s, [10, 0, -30] + s], 3.0),
               (2, 0, 1, [[0, 0, -20] + s, [-10, 0, -30] + s], 3.0)])


def test_metrics_identity():
    m = centreline_metrics(_y_graph(), _y_graph(), 1 * MM)
    assert m["dist_ext_to_true_mean_m"] < 1e-9 and m["dist_true_to_ext_mean_m"] < 1e-9
    assert m["detection_rate"] == 1.0 and m["detection_rate_large"] == 1.0
    assert m["spurious_fraction"] == 0.0
    assert m["bifurcation_error_median_m"] == pytest.approx(0.0, abs=1e-12)
    assert m["detection_by_generation"]["1"] == {"n": 2, "detected": 2, "rate": 1.0}


def test_metrics_shift_and_tolerances():
    m = centreline_metrics(_y_graph((0, 0.3, 0)), _y_graph(), 1 * MM)  # perpendicular to every branch
    assert m["dist_ext_to_true_mean_m"] == pytest.approx(0.3 * MM, rel=0.15)
    assert m["bifurcation_error_median_m"] == pytest.approx(0.3 * MM, rel=1e-6)
    assert m["detection_rate"] == 1.0 and m["spurious_fraction"] == 0.0
    # shifted by more than half the radius (and > 1 voxel): nothing detected, everything spurious
    m = centreline_metrics(_y_graph((3.0, 0, 0)), _y_graph(), 0.5 * MM)
    assert m["detection_rate"] == 0.0 and m["spurious_fraction"] == 1.0


def test_metrics_missing_and_spurious_branch():
    truth = _y_graph()
    missing = _g([(0, -1, 0, [[0, 0, 0], [0, 0, -20], [10, 0, -30]], 4.0)])  # one child missed
    m = centreline_metrics(missing, truth, 1 * MM)
    assert m["detection_rate"] == pytest.approx(2 / 3)
    assert m["detection_by_generation"]["1"]["detected"] == 1
    assert m["n_extracted_bifurcations"] == 0
    twig = _g([(0, -1, 0, [[0, 0, 0], [0, 0, -10]], 4.0), (1, 0, 1, [[0, 0, -10], [0, 8, -10]], 1.0),
               (2, 0, 1, [[0, 0, -10], [0, 0, -20]], 4.0), (3, 2, 2, [[0, 0, -20], [10, 0, -30]], 3.0),
               (4, 2, 2, [[0, 0, -20], [-10, 0, -30]], 3.0)])
    m = centreline_metrics(twig, truth, 1 * MM)
    assert m["n_spurious"] == 1 and m["spurious_branch_ids"] == [1]
    assert m["detection_rate"] == 1.0


def test_bifurcation_error_of_the_found_bifurcations_leaves_out_the_missed_subtrees():
    """A tree found only in part: the error over every true bifurcation counts the misses (distance to the
    nearest found junction), the error over the found ones (branch and two children detected) does not."""
    truth = _g([(0, -1, 0, [[0, 0, 0], [0, 0, -20]], 4.0), (1, 0, 1, [[0, 0, -20], [10, 0, -30]], 3.0),
                (2, 0, 1, [[0, 0, -20], [-10, 0, -30]], 3.0),
                (3, 2, 2, [[-10, 0, -30], [-20, 0, -40]], 2.0), (4, 2, 2, [[-10, 0, -30], [-10, 10, -40]], 2.0)])
    ext = _g([(0, -1, 0, [[0, 0, 0], [0, 0.5, -20]], 4.0), (1, 0, 1, [[0, 0.5, -20], [10, 0, -30]], 3.0),
              (2, 0, 1, [[0, 0.5, -20], [-10, 0, -30]], 3.0)])        # the distal junction's children missed
    m = centreline_metrics(ext, truth, 1 * MM)
    assert m["n_true_bifurcations"] == 2 and m["n_true_bifurcations_detected"] == 1
    assert m["bifurcation_error_median_m"] > 5 * MM                     # the missed junction, 14 mm away
    assert m["bifurcation_error_detected_median_m"] == pytest.approx(0.5 * MM, rel=1e-6)


def test_metrics_large_branch_filter():
    truth = _g([(0, -1, 0, [[0, 0, 0], [0, 0, -20]], 4.0), (1, 0, 1, [[0, 0, -20], [10, 0, -30]], 3.0),
                (2, 0, 1, [[0, 0, -20], [-10, 0, -30]], 0.5)])
    ext = _g([(0, -1, 0, [[0, 0, 0], [0, 0, -20], [10, 0, -30]], 4.0)])
    m = centreline_metrics(ext, truth, 1 * MM, min_radius_voxels=2.0)
    assert m["n_true_branches_large"] == 2 and m["detection_rate_large"] == 1.0
    assert m["detection_rate"] == pytest.approx(2 / 3)


# --------------------------------------------------------------------------- synthetic anatomy
def test_y_bifurcation_accuracy():
    tree = y_tree()
    sdf = sdf_of(tree)
    res = extract_medial_axis(sdf)
    g = res.graph
    check_tree(g, sdf)
    assert len(g.branches) >= 3 and len(g.children(g.root.id)) >= 2   # (the tilted tube's flat end leaves a ledge)
    assert g.root.points[0][2] > -3 * MM  # starts at the trachea's superior end
    m = centreline_metrics(g, from_airway_tree(tree, 0.25 * MM), SP)
    assert m["dist_ext_to_true_mean_vox"] < 0.5
    assert m["detection_rate"] == 1.0 and m["spurious_fraction"] == 0.0
    assert m["bifurcation_error_median_m"] < 1 * MM
    r = g.root.radius[len(g.root.radius) // 2]
    assert r == pytest.approx(3 * MM, abs=0.6 * SP)  # mask discretisation: the wall lies anywhere within a voxel
    rep = res.report
    assert rep["n_surface_samples"] > 0 and rep["n_medial_points"] > 0 and "timings" in rep
    import json
    json.dumps(rep)
    assert res.medial_points.shape == (len(res.medial_radius), 3)


def test_trifurcation():
    car = np.array([0, 0, -25 * MM])
    br = [Branch(0, -1, 0, [0, 0, 0], car, 3 * MM)]
    for k in range(3):
        phi = 2 * np.pi * k / 3
        d = np.array([0.6 * np.cos(phi), 0.6 * np.sin(phi), -0.8])
        br.append(Branch(k + 1, 0, 1, car, car + 18 * MM * d, 1.8 * MM))
    tree = AirwayTree(br)
    sdf = sdf_of(tree)
    g = extract_medial_axis(sdf).graph
    check_tree(g, sdf)
    for b in br[1:]:
        assert near(leaf_ends(g), b.end, 2 * MM)
    assert len(g.leaves()) == 3
    # one node with three children, or two nodes less than a radius apart
    nodes = np.array([b.points[-1] for b in g.branches if g.children(b.id)])
    assert len(nodes) <= 2 and np.max(np.linalg.norm(nodes - car, axis=1)) < 3 * MM
    m = centreline_metrics(g, from_airway_tree(tree, 0.25 * MM), SP)
    assert m["detection_rate"] == 1.0 and m["spurious_fraction"] == 0.0


def test_very_short_branch_kept_and_bump_pruned():
    car = np.array([0, 0, -25 * MM])
    tree = AirwayTree([Branch(0, -1, 0, [0, 0, 0], car, 3 * MM),
                       Branch(1, 0, 1, car, car + [0, 0, -15 * MM], 2.5 * MM),
                       Branch(2, 0, 1, car, car + 9 * MM * np.array([0.8, 0, -0.6]), 1.5 * MM)])
    sdf = sdf_of(tree)
    res = extract_medial_axis(sdf)
    check_tree(res.graph, sdf)
    assert len(res.graph.leaves()) == 2
    assert near(leaf_ends(res.graph), tree.branch(2).end, 1.5 * MM)
    assert res.report["n_branches_raw"] >= res.report["n_branches_after_pruning"]


def test_child_nearly_parallel_to_parent():
    car = np.array([0, 0, -25 * MM])
    d = np.array([np.sin(np.deg2rad(15)), 0, -np.cos(np.deg2rad(15))])
    tree = AirwayTree([Branch(0, -1, 0, [0, 0, 0], car, 2.5 * MM),
                       Branch(1, 0, 1, car, car + [0, 0, -25 * MM], 2.0 * MM),
                       Branch(2, 0, 1, car, car + 25 * MM * d, 1.5 * MM)])
    sdf = sdf_of(tree)
    g = extract_medial_axis(sdf).graph
    check_tree(g, sdf)
    assert len(g.leaves()) == 2
    for b in tree.branches[1:]:
        assert near(leaf_ends(g), b.end, 1.5 * MM)
    m = centreline_metrics(g, from_airway_tree(tree, 0.25 * MM), SP)
    assert m["dist_ext_to_true_mean_vox"] < 1.0 and m["spurious_fraction"] == 0.0


def test_loop_is_broken_with_warning(caplog):
    top, car, bot = np.array([0, 0, 0.0]), np.array([0, 0, -20 * MM]), np.array([0, 0, -50 * MM])
    L, R = np.array([-10 * MM, 0, -35 * MM]), np.array([10 * MM, 0, -35 * MM])
    tree = AirwayTree([Branch(0, -1, 0, top, car, 3 * MM), Branch(1, 0, 1, car, L, 1.8 * MM),
                       Branch(2, 0, 1, car, R, 1.8 * MM), Branch(3, 1, 2, L, bot, 1.8 * MM),
                       Branch(4, 2, 2, R, bot, 1.8 * MM)])
    sdf = sdf_of(tree)
    with caplog.at_level(logging.WARNING, logger="room_pipeline.anatomy.medial_axis"):
        res = extract_medial_axis(sdf)
    check_tree(res.graph, sdf)
    assert res.report["loops_broken"] >= 1
    assert any("loop" in r.message for r in caplog.records)
    # the whole loop is still covered
    m = centreline_metrics(res.graph, from_airway_tree(tree, 0.25 * MM), SP)
    assert m["dist_true_to_ext_p95_vox"] < 4


def test_disconnected_fragment_dropped_with_warning(caplog):
    tree = y_tree()
    frag = AirwayTree(tree.branches + [Branch(9, -1, 0, [15 * MM, 0, -5 * MM], [15 * MM, 0, -15 * MM], 1.5 * MM)])
    sdf = sdf_of(frag)
    with caplog.at_level(logging.WARNING, logger="room_pipeline.anatomy.medial_axis"):
        res = extract_medial_axis(sdf)
    check_tree(res.graph, sdf)
    assert res.report["dropped_components"] == 1 and res.report["dropped_cluster_points"] > 0
    assert any("dropped 1 component" in r.message for r in caplog.records)
    P, _, _ = res.graph.all_points()
    assert np.all(P[:, 0] < 12 * MM)  # nothing from the fragment


def test_one_voxel_wide_airway():
    sp = SP
    tree = AirwayTree([Branch(0, -1, 0, [0, 0, 0], [0, 0, -15 * MM], 2.5 * MM)])
    mask = mask_of(tree, sp, margin=14 * MM)
    m = mask.data
    # a straight one-voxel line leaving the trachea's end sideways along +x for 10 mm
    end = np.round(mask.world_to_index(np.array([[0, 0, -15 * MM]]))[0]).astype(int)
    n = int(round(10 * MM / sp))
    m[end[0]:end[0] + int(round(2.5 * MM / sp)) + n, end[1], end[2]] = 1
    sdf = compute_sdf(mask.with_data(m), SdfParams())
    g = extract_medial_axis(sdf).graph
    check_tree(g)
    tip = mask.index_to_world(np.array([[end[0] + int(round(2.5 * MM / sp)) + n - 1, end[1], end[2]]]))[0]
    assert near(leaf_ends(g), tip, 2 * sp)


@settings(max_examples=4, deadline=None, suppress_health_check=list(HealthCheck))
@given(angle=st.floats(25, 60), r1=st.floats(1.2, 2.5), phi=st.floats(0, np.pi))
def test_invariants_random_y(angle, r1, phi):
    tree = y_tree(angle_deg=angle, r1=r1 * MM, r2=1.5 * MM, child_len=12 * MM, phi=phi)
    sdf = sdf_of(tree, 0.6 * MM)
    g = extract_medial_axis(sdf).graph
    check_tree(g, sdf)
    assert len(g.leaves()) == 2
    for b in tree.branches[1:]:
        assert near(leaf_ends(g), b.end, 2 * MM)


def test_phantom_coarse_accuracy():
    from room_pipeline.anatomy.phantom import PhantomParams, make_phantom

    ph = make_phantom(PhantomParams.from_dict({"spacing_mm": 1.0}), seed=0)
    res = extract_medial_axis(ph.sdf)
    check_tree(res.graph)
    m = centreline_metrics(res.graph, from_airway_tree(ph.tree, 0.5 * MM), 1 * MM)
    assert m["dist_ext_to_true_mean_vox"] <= 0.5
    assert m["detection_rate_large"] >= 0.95
    assert m["spurious_fraction"] <= 0.05
    assert m["bifurcation_error_median_m"] <= 1.5 * MM


# --------------------------------------------------------------------------- real anatomy (../shared)
REAL = [("airway_masks", "medmpd", f"patient{p}", "bronchialTree.nii.gz") for p in (1, 2, 3)] + \
       [("airway_masks", "airquant_demo", "github_demo_seg.nii.gz")]


def _real_id(p: tuple) -> str:
    return p[-2] if p[-2] != "airquant_demo" else "airquant"


@pytest.mark.shared
@pytest.mark.slow
@pytest.mark.parametrize("parts", [p if p[-2] in ("patient1", "airquant_demo") else pytest.param(
    p, marks=pytest.mark.exhaustive) for p in REAL], ids=_real_id)
def test_real_masks(parts):
    mask = read_volume(shared_path(*parts))
    crop = crop_to_interior(mask, 6)
    sdf = compute_sdf(crop, SdfParams())
    res = extract_medial_axis(sdf)
    g = res.graph
    check_tree(g)
    assert len(g.branches) >= 15
    assert max(b.generation for b in g.branches) >= 3
    # the root is the trachea: wide, and starts near the top of the mask
    zmax = crop.index_to_world(np.argwhere(crop.data > 0).astype(float))[:, 2].max()
    assert g.root.points[0][2] > zmax - 15 * MM
    assert g.root.mean_radius > np.median([b.mean_radius for b in g.branches])
    assert res.report["root_centred"] is False        # round tracheas: no medial sheet


def _arch_mask(island: bool = False, h: float = 0.8) -> Volume:
    """A 6 mm radius tube bent into an arch (its widest, most superior point is mid-tube, not an end)."""
    x = np.arange(-40, 40.01, h)
    y = np.arange(-12, 12.01, h)
    z = np.arange(-12, 16.01, h)
    X, Y, Z = np.meshgrid(x, y, z, indexing="ij")
    xc = np.clip(X, -30, 30)
    zc = 6 * np.cos(np.pi * xc / 60)
    m = (X - xc) ** 2 + Y ** 2 + (Z - zc) ** 2 <= 6 ** 2
    if island:  # a small disconnected blob, wider than nothing but above everything
        m |= (X - 35) ** 2 + Y ** 2 + (Z - 13) ** 2 <= 2.0 ** 2
    aff = np.diag([h * MM] * 3 + [1.0])
    aff[:3, 3] = [x[0] * MM, y[0] * MM, z[0] * MM]
    return Volume(m.astype(np.uint8), aff)


@pytest.mark.parametrize("island", [False, True])
def test_root_is_a_free_end_when_the_widest_top_point_is_mid_tube(island):
    """Issue #18 item 2: the old root (most superior wide point, mid-arch) gave a zero-length root branch."""
    res = extract_medial_axis(compute_sdf(_arch_mask(island), SdfParams()), MedialAxisParams())
    g = res.graph
    assert res.report["root_reselected"] is True
    assert res.report["root_centred"] is False          # a round tube's medial set is a line, not a sheet
    assert g.root.length > 50 * MM  # the whole arch, from one free end
    assert abs(abs(g.root.points[0][0]) - 30 * MM) < 4 * MM  # starts at an end of the tube
    if island:
        assert res.report["dropped_components"] >= 1



def _border_cut_tree_mask(tilt_deg: float, h: float = 0.8, top: float = 0.0) -> Volume:
    """A Y tree whose trachea runs out of the top of the volume (the scan cut through it, as CASE091),
    leaning ``tilt_deg`` from the volume axis: the trachea is 5 mm in radius at the cut and widens to 7 mm
    lower down, the main bronchi are 4.5 mm."""
    x = np.arange(-40, 40.01, h)
    y = np.arange(-12, 12.01, h)
    z = np.arange(-70, top + 0.01, h)             # the last slice (z = top) still holds lumen
    X, Y, Z = np.meshgrid(x, y, z, indexing="ij")
    r_tr = np.interp(Z, [-40, -25, 0], [7.0, 7.0, 5.0])
    xa = np.tan(np.deg2rad(tilt_deg)) * (Z + 40)   # the trachea's axis leans toward +x going up
    m = (Z >= -40) & ((X - xa) ** 2 + Y ** 2 <= r_tr ** 2)
    for sx in (-1.0, 1.0):                          # main bronchi from the carina at z = -40
        d = np.array([sx * np.sin(0.6), 0.0, -np.cos(0.6)])
        t = np.clip((X * d[0] + (Z + 40) * d[2]), 0, 35)
        m |= (X - t * d[0]) ** 2 + Y ** 2 + (Z + 40 - t * d[2]) ** 2 <= 4.5 ** 2
    aff = np.diag([h * MM] * 3 + [1.0])
    aff[:3, 3] = [x[0] * MM, y[0] * MM, z[0] * MM]
    return Volume(m.astype(np.uint8), aff)


@pytest.mark.parametrize("tilt_deg", [0.0, 25.0])
def test_root_inside_the_volume_when_the_trachea_is_cut_by_its_border(tilt_deg):
    """Issue #18 (CASE091): the SDF continues a lumen past the volume border, where the tracer's clamped
    lookup is flat, so grassfire paths leaving through the cut end became medial points outside the volume;
    the root was put there and the trachea had no free end ('no trachea-like root')."""
    vol = _border_cut_tree_mask(tilt_deg)
    res = extract_medial_axis(compute_sdf(vol, SdfParams()), MedialAxisParams())
    g = res.graph
    check_tree(g)
    top = vol.index_to_world(np.array([[0.0, 0.0, vol.shape[2] - 1.0]]))[0, 2]
    assert res.medial_points[:, 2].max() <= top + 1e-9, "medial points outside the volume"
    assert res.report["root_centred"] is False and res.report["trachea_sheet_points"] == 0   # round: no sheet
    assert g.root.length > 25 * MM                    # the trachea, from the cut down to the carina
    assert g.root.points[0][2] > top - 3 * MM         # starts at the cut
    assert abs(g.root.points[0][0] - np.tan(np.deg2rad(tilt_deg)) * 40 * MM) < 3 * MM
    assert abs(g.root.points[0][1]) < 2 * MM
    assert len(g.branches) >= 3 and len(g.children(g.root.id)) >= 2   # (the tilted tube's flat end leaves a ledge)


CUTS = [0.0, -20.0, -30.0, -32.0, -35.0, -38.0]       # 40, 20, 10, 8, 5, 2 mm above the carina (z = -40)
_SYNTH_CARINA: dict = {}                                # tilt -> the uncut tree's first bifurcation (m)


@pytest.mark.parametrize("tilt_deg", [0.0, 25.0])
@pytest.mark.parametrize("top", CUTS)
def test_root_when_the_scan_is_cut_just_above_the_carina(top, tilt_deg):
    """Issue #18 item 2: the scan cut 40 mm down to 2 mm above the carina (z = -40), the trachea upright or
    leaning 25 deg: the route starts at the cut, in the middle of the trachea, and both main bronchi hang
    below the trachea's first bifurcation.  Within ~10 mm of the carina the skeleton divides at the cut (two
    downward arms); that is read as a bifurcation at the entry: a short root branch from the middle of the cut
    cross-section to where the arms part, both main bronchi its children (``root_entry_bifurcation``)."""
    vol = _border_cut_tree_mask(tilt_deg, top=top)
    res = extract_medial_axis(compute_sdf(vol, SdfParams()), MedialAxisParams())
    g = res.graph
    check_tree(g)
    rep = {k: v for k, v in res.report.items() if k.startswith("root")}
    zt = vol.index_to_world(np.array([[0.0, 0.0, vol.shape[2] - 1.0]]))[0, 2]
    axis_x = np.tan(np.deg2rad(tilt_deg)) * (zt + 40 * MM)
    assert g.root.points[0][2] > zt - 3 * MM, rep
    assert abs(g.root.points[0][0] - axis_x) < 2 * MM and abs(g.root.points[0][1]) < 2 * MM, rep
    # the two main bronchi (ends at x = +-19.7 mm, z = -69.7 mm) part below the cut, not below the carina's
    # ridge (where the bronchi's lumens separate, z = -46.6 mm), and, where the uncut tree's bifurcation lies
    # below the cut, within the real-mask bound (test_real_mask_cut_above_the_carina) of it
    ends = {int(np.sign(b.points[-1][0])): b.id for b in g.leaves() if b.points[-1][2] < -60 * MM}
    assert sorted(ends) == [-1, 1], [(b.id, b.parent, (b.points[-1] / MM).round(1).tolist()) for b in g.branches]
    left, right = g.path_to(ends[-1]), g.path_to(ends[1])
    common = [a.id for a, b in zip(left, right) if a.id == b.id]
    node = g.branch(common[-1]).points[-1]
    assert zt > node[2] > -46.6 * MM, (node / MM, rep)
    if tilt_deg not in _SYNTH_CARINA:
        _SYNTH_CARINA[tilt_deg] = extract_medial_axis(compute_sdf(_border_cut_tree_mask(tilt_deg), SdfParams()),
                                                      MedialAxisParams()).graph.root.points[-1]
    full = _SYNTH_CARINA[tilt_deg]
    if full[2] < zt:
        assert np.linalg.norm(node - full) < 5 * MM + 0.5 * (top + 40) * MM, (node / MM, full / MM, rep)
    if rep["root_entry_bifurcation"]:
        assert len(common) == 1 and len(g.children(g.root.id)) == 2, rep      # both bronchi: the root's children
        assert rep["root_stub_mm"] == pytest.approx(g.root.length / MM, rel=0.05, abs=0.5)
    if top >= -20.0:
        assert rep["root_entry_bifurcation"] is False                        # a trachea long enough for its own
    if top <= -32.0:
        assert rep["root_entry_bifurcation"] is True                         # an 8 mm or shorter stub


def test_start_offset_on_a_trachea_cut_just_above_the_carina():
    """Issue #18: the default ``trajectory.start_offset_mm`` (10 mm) is longer than the stub trachea of a scan
    cut 2 mm above the carina.  The rule (planning/trajectory.py ``_start``): an offset of half the root or
    more is clipped to half the root branch, noted in the trajectory's ``start``; the route starts inside the
    trachea stub, on its way to either main bronchus."""
    from room_pipeline.planning.trajectory import TrajectoryParams, plan_path

    vol = _border_cut_tree_mask(0.0, top=-38.0)
    sdf = compute_sdf(vol, SdfParams())
    g = extract_medial_axis(sdf, MedialAxisParams()).graph
    assert g.root.length < 10 * MM
    leaf = max(g.leaves(), key=lambda b: b.length)
    traj = plan_path(g, leaf.id, sdf, TrajectoryParams())
    assert traj.start["offset_mm"] == pytest.approx(0.5 * g.root.length / MM, abs=1e-6)
    assert "clipped" in traj.start["note"] and "root branch (trachea)" in traj.start["note"]
    p0 = traj.positions[0]
    assert np.min(np.linalg.norm(g.root.points - p0, axis=1)) < 1 * MM        # starts in the stub trachea


@pytest.mark.parametrize("top", [-46.0, -47.0])
def test_no_trachea_when_the_scan_is_cut_at_the_carina(top):
    """Issue #18 item 2: cut through the carina's ridge (z = -46.6) the top cross-section opens into both main
    bronchi: no trachea-like root, one clear error (not a route that starts at a bronchus's end)."""
    vol = _border_cut_tree_mask(0.0, top=top)
    with pytest.raises(InputError, match="no trachea-like root.*top cut.*carina"):
        extract_medial_axis(compute_sdf(vol, SdfParams()), MedialAxisParams())


@pytest.mark.parametrize("top", [-50.0, -60.0])
def test_scan_cut_below_the_carina_is_an_error(top):
    """Issue #18: a scan cut wholly below the carina (the ridge at z = -46.6) holds two separate trees, both
    main bronchi open at its top slice; the segment stage kept the larger and the route started in a main
    bronchus.  Now one clear error; a small island on the top slice (airway-model debris) is not a tree."""
    from room_pipeline.anatomy.segment import validate_mask

    from room_pipeline.anatomy.plausibility import check_mask

    cut = _border_cut_tree_mask(0.0, top=top)
    with pytest.raises(InputError, match="top slice cuts 2 separate airway trees.*below the carina"):
        validate_mask(cut)
    with pytest.raises(InputError, match=r"cut\.nii\.gz.*top slice cuts 2 separate airway trees"):
        check_mask(cut, Path("cut.nii.gz"))                # the segment stage's check of an input mask
    vol = _border_cut_tree_mask(0.0, top=-20.0)
    d = vol.data.copy()
    d[5:9, 5:9, -4:] = 1                                  # a 3 x 3 x 2.4 mm island on the top slice
    rep: dict = {}
    out = validate_mask(Volume(d, vol.affine), report=rep)
    assert rep["dropped_components"] == 1 and out.data.sum() == (vol.data > 0).sum()
    check_mask(Volume(d, vol.affine), Path("islands.nii.gz"))


_REAL_REF: dict = {}


def _real_reference(parts):
    """A shared real mask (largest component) and its full centreline graph (the reference trachea/carina)."""
    from room_pipeline.anatomy.segment import validate_mask

    if parts not in _REAL_REF:
        mask = validate_mask(read_volume(shared_path(*parts)))
        g = extract_medial_axis(compute_sdf(crop_to_interior(mask, 6), SdfParams())).graph
        _REAL_REF[parts] = (mask, g)
    return _REAL_REF[parts]


def _crop_above(vol: Volume, z: float) -> Volume:
    """The scan cut at world height ``z``: the array's slices above it removed (the header's origin moved)."""
    ax = int(np.argmax(np.abs(vol.affine[2, :3])))
    idx = np.zeros((vol.shape[ax], 3))
    idx[:, ax] = np.arange(vol.shape[ax])
    keep = np.flatnonzero(vol.index_to_world(idx)[:, 2] <= z)
    sl = [slice(None)] * 3
    sl[ax] = slice(int(keep[0]), int(keep[-1]) + 1)
    lo = np.zeros((1, 3))
    lo[0, ax] = keep[0]
    aff = vol.affine.copy()
    aff[:3, 3] = vol.index_to_world(lo)[0]
    return Volume(np.ascontiguousarray(vol.data[tuple(sl)]), aff)


#: real-mask cuts that still miss (issue #18): none since the carinal-flare test (``_divides_below``): Med-MPD 1
#: cut 10 / 5 / 2 mm above its carina, whose top cross-section is the carinal flare (aspect 1.60-1.68, sheet
#: fraction 0.88-0.99), ended its root 13.9 / 13.8 / 15.3 mm from the carina under the flattened-trachea rule
KNOWN_CUT_LIMITS: dict = {}


#: the default tier: Med-MPD 1 cut 2 mm above its carina (its carinal flare) and AirQuant 40 mm above;
#: --exhaustive: every mask at every height
_CUT_CI = {("patient1", 2.0), ("airquant", 40.0)}


@pytest.mark.shared
@pytest.mark.slow
@pytest.mark.parametrize("parts,above_mm", [
    pytest.param(p, a, marks=() if (_real_id(p), a) in _CUT_CI else pytest.mark.exhaustive, id=f"{_real_id(p)}-{a:g}")
    for a in (40.0, 10.0, 5.0, 2.0) for p in REAL])
def test_real_mask_cut_above_the_carina(parts, above_mm, request):
    """Issue #18 item 2 on real trees: each shared real mask's array cut 40 / 10 / 5 / 2 mm above its carina
    (the reference: the full mask's first bifurcation): the route still starts at the cut on the trachea's
    centreline, and the root ends at the carina with the main bronchi below it."""
    from room_pipeline.anatomy.segment import validate_mask

    name = parts[-2] if parts[-2] != "airquant_demo" else "airquant"
    if (name, above_mm) in KNOWN_CUT_LIMITS:
        request.applymarker(pytest.mark.xfail(strict=False, reason=KNOWN_CUT_LIMITS[(name, above_mm)]))

    mask, ref = _real_reference(parts)
    carina = ref.root.points[-1]
    cut = validate_mask(_crop_above(mask, carina[2] + above_mm * MM))
    res = extract_medial_axis(compute_sdf(crop_to_interior(cut, 6), SdfParams()))
    g = res.graph
    check_tree(g)
    rep = {k: v for k, v in res.report.items() if k.startswith("root") or k in (
        "trachea_aspect_ratio", "trachea_top_sheet_fraction", "trachea_divides_below_mm",
        "trachea_divides_below_radii")}
    ztop = cut.index_to_world(np.argwhere(cut.data > 0).astype(float))[:, 2].max()
    start, end = g.root.points[0], g.root.points[-1]
    tr = ref.root.points
    print(f"\n{name} cut {above_mm:g} mm above: root end {np.linalg.norm(end - carina) / MM:.1f} mm from the carina "
          f"(bound {5 + 0.5 * above_mm:g}), start {np.min(np.linalg.norm(tr - start, axis=1)) / MM:.2f} mm from the "
          f"trachea's centreline (bound 3); {rep}")
    assert start[2] > ztop - 3 * MM, rep                                   # at the cut ...
    assert np.min(np.linalg.norm(tr - start, axis=1)) < 3 * MM, rep       # ... on the trachea's centreline
    assert np.linalg.norm(end - carina) < 5 * MM + 0.5 * above_mm * MM, (end / MM, carina / MM, rep)
    assert len(g.children(g.root.id)) >= 2 and len(g.branches) >= 15


def _capsules_mask(segs, lo, hi, h: float = 1.0) -> Volume:
    """Union of capsules ``(p0, p1, radius)`` (mm) on a grid of ``h`` mm from ``lo`` to ``hi`` (mm)."""
    ax = [np.arange(lo[i], hi[i] + 1e-9, h) for i in range(3)]
    X = np.stack(np.meshgrid(*ax, indexing="ij"), -1)
    m = np.zeros(X.shape[:3], dtype=bool)
    for p0, p1, r in segs:
        p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
        t = np.clip(((X - p0) @ (p1 - p0)) / ((p1 - p0) @ (p1 - p0)), 0.0, 1.0)
        m |= np.linalg.norm(X - (p0 + t[..., None] * (p1 - p0)), axis=-1) <= r
    aff = np.diag([h * MM] * 3 + [1.0])
    aff[:3, 3] = np.asarray(lo, float) * MM
    return Volume(m.astype(np.uint8), aff)


# a trachea (8 mm radius, carina at z = -10 mm) over two main bronchi that divide once each (mm)
_Y_TREE = [((0, 0, 60), (0, 0, -10), 8.0),
           ((0, 0, -10), (20, 0, -30), 6.0), ((20, 0, -30), (25, 0, -60), 4.0), ((20, 0, -30), (45, 0, -40), 4.0),
           ((0, 0, -10), (-20, 0, -30), 6.0), ((-20, 0, -30), (-25, 0, -60), 4.0), ((-20, 0, -30), (-45, 0, -40), 4.0)]


@pytest.mark.parametrize("offset_mm", [11.0, 12.5])
def test_a_twig_whose_lumen_stays_in_the_tracheas_is_not_the_first_bifurcation(offset_mm):
    """Issue #18 item 2 (AirQuant resampled to 1 mm: a 20 mm twig of radius 8.9 mm on the trachea's medial band
    taken as the first bifurcation, 92 mm above the carina): the trachea widened on one side by a parallel
    lumen (5.5 mm radius, its axis ``offset_mm`` beside the trachea's, z 40 .. -2 mm) grows a medial line that
    ends without dividing and never leaves the lumen around the trachea; it is dropped and the root runs on
    to the carina (within 3 mm)."""
    side = [((0, offset_mm, 40), (0, offset_mm, -2), 5.5)]
    vol = _capsules_mask(_Y_TREE + side, (-55, -16, -70), (55, 22, 66))
    res = extract_medial_axis(compute_sdf(crop_to_interior(vol, 6), SdfParams()))
    g = res.graph
    check_tree(g)
    assert res.report["root_twigs_dropped"] >= 1
    assert np.linalg.norm(g.root.points[-1] - np.array([0, 0, -10]) * MM) < 3 * MM, g.root.points[-1] / MM
    assert len(g.children(g.root.id)) == 2 and len(g.branches) == 7


@pytest.mark.parametrize("length_mm, radius_mm", [(15.0, 3.0), (25.0, 3.0), (25.0, 4.5)])
def test_a_real_side_branch_of_the_trachea_stays_a_branch(length_mm, radius_mm):
    """The twig rule keeps a real side branch off the trachea (a tracheal bronchus, 60 deg from the trachea's
    axis at z = 30 mm, ending without dividing): narrower than half the trachea, or parted from it by a wall;
    it stays the first bifurcation."""
    tip = (0, length_mm * np.sin(np.pi / 3), 30 - length_mm * np.cos(np.pi / 3))
    vol = _capsules_mask(_Y_TREE + [((0, 0, 30), tip, radius_mm)], (-55, -16, -70), (55, 12 + length_mm, 66))
    res = extract_medial_axis(compute_sdf(crop_to_interior(vol, 6), SdfParams()))
    g = res.graph
    check_tree(g)
    assert res.report["root_twigs_dropped"] == 0
    assert abs(g.root.points[-1][2] - 30 * MM) < 5 * MM, g.root.points[-1] / MM
    kids = g.children(g.root.id)
    assert sorted(len(g.children(c.id)) for c in kids) == [0, 2]


def test_a_narrow_twig_that_ends_in_the_tracheas_lumen_is_not_the_first_bifurcation():
    """Issue #18 (CASE091 as stored and at 0.5 mm, CASE073 and Med-MPD 2 at 0.5 mm: the root ended at a twig
    48-101 mm above the carina, as narrow as a tracheal bronchus, 0.09-0.42 of the junction's radius, or whose ways
    left the lumen by 0.68 voxel, so the width / exit rule kept it): a 3.5 mm channel fused along the 8 mm trachea
    (its axis 10.5 mm beside the trachea's, z 45 .. 5 mm) grows medial lines of width 0.45 whose ways stay in the
    lumen; the root ended at the first, 63 mm above the carina.  Each ends where the lumen's cross-section normal to
    it runs on into the trachea's (``_twig_end_width`` 1.54 / 1.76 junction radii, > ``TWIG_END_OPEN``; a tracheal
    bronchus's end is its own disc, 0.38-0.58: ``test_a_real_side_branch_of_the_trachea_stays_a_branch``): both
    are dropped and the root runs on to the carina."""
    side = [((0, 10.5, 45), (0, 10.5, 5), 3.5)]
    vol = _capsules_mask(_Y_TREE + side, (-55, -16, -70), (55, 22, 66))
    res = extract_medial_axis(compute_sdf(crop_to_interior(vol, 6), SdfParams()))
    g = res.graph
    check_tree(g)
    assert res.report["root_open_end_twigs_dropped"] >= 1, res.report
    assert np.linalg.norm(g.root.points[-1] - np.array([0, 0, -10]) * MM) < 3 * MM, g.root.points[-1] / MM
    assert len(g.children(g.root.id)) == 2 and len(g.branches) == 7


def test_the_twig_end_width_reads_a_tube_and_an_open_lumen():
    """``_twig_end_width`` on analytic SDFs: a twig along the axis of a 3 mm tube reads its radius over the
    junction's (3 / 8), one along the axis of a 12 mm wide slab (a lumen wider than the trachea) reads the most
    the 1.5-junction-radius window holds (> 1)."""
    from room_pipeline.anatomy.sdf_field import SdfField
    from room_pipeline.anatomy.trachea_root import TWIG_END_OPEN, _twig_end_width

    h = 0.5
    ax = np.arange(-20, 20.01, h)
    X, Y, Z = np.meshgrid(ax, ax, ax, indexing="ij")
    aff = np.diag([h * MM] * 3 + [1.0])
    aff[:3, 3] = ax[0] * MM
    twig = np.stack([np.zeros(30), np.zeros(30), np.linspace(-14, 14, 30)], axis=1) * MM
    junction = np.array([0.0, 0.0, -17.0]) * MM
    tube = SdfField(((np.hypot(X, Y) - 3.0) * MM).astype(np.float32), aff)
    slab = SdfField(((np.abs(Y) - 6.0) * MM).astype(np.float32), aff)
    w_tube = _twig_end_width(twig, np.full(30, 3.0 * MM), junction, 8.0 * MM, tube, h * MM)
    w_slab = _twig_end_width(twig, np.full(30, 6.0 * MM), junction, 8.0 * MM, slab, h * MM)
    assert abs(w_tube - 3.0 / 8.0) < 0.1 and w_slab > 1.5 * TWIG_END_OPEN, (w_tube, w_slab)


def _narrowed_top_mask(h: float = 0.8, a_top: float = 10.0, b_top: float = 4.0) -> Volume:
    """A trachea cut by the scan's top (z = 20 mm) whose upper part is flattened and narrower than its lower part
    (CASE091 resampled: round, radius 7.9 mm, low down; aspect 1.5-1.7 and inscribed radius 3.9-5.3 mm in its
    upper 20 mm): round (7.5 mm) below z = -20, flattened above z = -5 to an ellipse ``a_top`` x ``b_top`` mm
    (long axis along x), linear between; the axis leans 20 deg toward +y going up; carina at z = -45, main
    bronchi 5.5 mm, 34 deg from vertical, 35 mm long.  All lengths in mm, affine in metres."""
    x, y, z = np.arange(-45, 45.01, h), np.arange(-20, 30.01, h), np.arange(-80, 20.01, h)
    X, Y, Z = np.meshgrid(x, y, z, indexing="ij")
    f = np.clip((Z + 20.0) / 15.0, 0.0, 1.0)
    yc = np.tan(np.deg2rad(20.0)) * (Z + 45.0)
    m = (Z >= -45) & ((X / (7.5 + (a_top - 7.5) * f)) ** 2 + ((Y - yc) / (7.5 + (b_top - 7.5) * f)) ** 2 <= 1.0)
    for sx in (-1.0, 1.0):
        d = np.array([sx * np.sin(0.6), 0.0, -np.cos(0.6)])
        t = np.clip(X * d[0] + (Z + 45) * d[2], 0, 35)
        m |= (X - t * d[0]) ** 2 + Y ** 2 + (Z + 45 - t * d[2]) ** 2 <= 5.5 ** 2
    aff = np.diag([h * MM] * 3 + [1.0])
    aff[:3, 3] = [x[0] * MM, y[0] * MM, z[0] * MM]
    return Volume(m.astype(np.uint8), aff)


def test_a_flattened_upper_trachea_above_a_wider_one_gives_a_root_to_the_carina():
    """Issue #18 (CASE091 resampled to 0.8 / 0.5 mm: 'no trachea-like root: the widest part of the airway tree has
    no free end'): the trachea's wide part tops out mid-tube with an arm rising into a narrower, flattened upper
    trachea (20 x 8 mm at the cut, inscribed 4 mm: below the root-radius cut of the wide part's 7.5 mm), so the
    root is re-selected at the most superior wide free end, on the edge of the upper part's medial sheet; the
    skeleton grown from there divided at once into the trunk and the sheet's network of lines, and the root
    branch came out of zero length.  The sheet's lines are dropped like twigs (a whole subtree as wide as the
    trachea's medial line whose ways into the rest of the tree stay in the lumen,
    ``root_sheet_subtrees_dropped``): the route starts at the cut, inside the trachea, and the root runs down to
    the bifurcation of the main bronchi."""
    vol = _narrowed_top_mask()
    res = extract_medial_axis(compute_sdf(vol, SdfParams()), MedialAxisParams())
    g = res.graph
    check_tree(g)
    rep = {k: v for k, v in res.report.items() if k.startswith("root") or k.startswith("trachea")}
    assert rep["root_reselected"] is True and rep["root_centred"] is False, rep
    assert rep["root_sheet_subtrees_dropped"] >= 1, rep
    start, end = g.root.points[0] / MM, g.root.points[-1] / MM
    yc = np.tan(np.deg2rad(20.0)) * (start[2] + 45.0)
    assert start[2] > 17.0 and (start[0] / 10.0) ** 2 + ((start[1] - yc) / 4.0) ** 2 < 1.0, (start, rep)   # at the cut
    assert -45.0 < end[2] < -30.0 and np.hypot(end[0], end[1]) < 4.0, (end, rep)   # the main bronchi's junction
    ends = sorted(np.sign(b.points[-1][0]) for b in g.leaves() if b.points[-1][2] < -65 * MM)
    assert ends == [-1, 1] and len(g.children(g.root.id)) == 2, [(b.id, b.parent, b.points[-1] / MM) for b in g.branches]


def test_the_twig_rule_measures_to_the_masks_resolution():
    """Issue #18 (CASE073 / CASE091 as stored, Med-MPD 2 / AirQuant resampled: the root stopped at a trachea-wide
    terminal twig 48-102 mm above the carina; CASE091 at 0.8 mm had no root at all): the twig rule's straight
    ways from the twig's last points, 0.2-0.3 mm inside a wall of 0.66-0.8 mm voxels, left the lumen by
    0.012-0.95 mm.  The rule now measures to the mask's resolution (``_twig_measure``): points less than a voxel
    inside the wall are left out (of the width too), and a way may leave the lumen by less than half a voxel
    (``TWIG_EXIT_VOXELS``: a binary mask's wall is a staircase of voxel faces).  On an analytic SDF (a tube of
    radius 6 voxels with a sheet of ``b`` voxels outside the lumen where the twig's ways cross it): b = 0.3
    passes, 0.7 does not; a point 0.06 voxel inside the wall whose way leaves the lumen by 2 voxels is left out;
    a twig narrower than half the junction is kept whatever its ways."""
    from room_pipeline.anatomy.sdf_field import SdfField
    from room_pipeline.anatomy.trachea_root import TWIG_EXIT_VOXELS, _twig_inside_lumen, _twig_measure

    v = 1e-3                                                           # voxel: 1 mm
    g = np.arange(-12, 13) * v
    X, Y, Z = np.meshgrid(g, g, g, indexing="ij")
    aff = np.diag([v, v, v, 1.0])
    aff[:3, 3] = g[0]

    def field(b: float) -> SdfField:
        sdf = np.hypot(X, Y) - 6 * v                                   # a tube along z, radius 6 voxels
        sheet = (np.abs(X - 2.5 * v) < 0.6 * v) & (Y > 1.5 * v)        # grid planes x = 2, 3 where y >= 2
        return SdfField(np.where(sheet & (sdf < 0), b * v, sdf).astype(np.float32), aff)

    trunk = np.stack([np.zeros(9), np.zeros(9), np.arange(-4, 5) * v], axis=1)
    rad_of = lambda p: 6 * v - np.hypot(p[:, 0], p[:, 1])              # noqa: E731
    twig = np.array([[3.3, 3.6, 0.0], [3.4, 3.2, 0.0]]) * v           # 1.12, 1.33 voxels inside the wall
    for b, inside in ((0.3, True), (0.7, False)):
        f = field(b)
        width, exit_vox = _twig_measure(twig, rad_of(twig), 2.0 * v, trunk, f, v)
        assert width >= 0.5 and exit_vox == pytest.approx(b, abs=1e-6), (b, width, exit_vox)
        assert (exit_vox < TWIG_EXIT_VOXELS) is inside
        assert _twig_inside_lumen(twig, rad_of(twig), 2.0 * v, trunk, f, v) is inside
    # a last point 0.06 voxel inside the wall whose way to the trunk leaves the lumen by 2 voxels: left out
    f = field(2.0)
    shallow = np.array([[4.2, 4.2, 0.0]]) * v
    way = shallow + np.linspace(0.0, 1.0, 41)[:, None] * (trunk[4] - shallow)
    assert f.sample(f.to_index(way))[:, 0].max() == pytest.approx(2.0 * v, rel=1e-6)
    assert rad_of(shallow)[0] < v and _twig_measure(shallow, rad_of(shallow), 2.0 * v, trunk, f, v)[1] == np.inf
    deep = np.array([[1.0, 1.0, 0.0]]) * v
    both = np.vstack([deep, shallow])
    assert _twig_measure(both, rad_of(both), 2.0 * v, trunk, f, v)[1] < 0
    # narrower than half the junction: a side branch, kept whatever its ways
    assert not _twig_inside_lumen(deep, np.array([1.2 * v]), 2.5 * v, trunk, field(0.0), v)


@pytest.mark.parametrize("n_islands", [10, 90])
def test_root_is_the_trachea_among_many_small_islands(n_islands):
    """Issue #18 item 2: airway-model outputs carry 10-90 small disconnected islands (here balls of 1-2.5 mm
    radius, seeded, some above the trachea's top): they are dropped and never hold the root."""
    vol = _border_cut_tree_mask(0.0)
    d = vol.data.copy()
    rng = np.random.default_rng(n_islands)
    idx = np.indices(d.shape)
    lumen = ndimage.binary_dilation(d > 0, iterations=6)
    placed = 0
    while placed < n_islands:
        c = np.array([rng.integers(4, n - 4) for n in d.shape])
        if lumen[tuple(c)]:
            continue
        r = rng.uniform(1.0, 2.5) / 0.8
        d[sum((idx[a] - c[a]) ** 2 for a in range(3)) <= r * r] = 1
        lumen[tuple(slice(max(0, v - 6), v + 7) for v in c)] = True
        placed += 1
    vol = Volume(d, vol.affine)
    res = extract_medial_axis(compute_sdf(vol, SdfParams()), MedialAxisParams())
    g = res.graph
    check_tree(g)
    zt = vol.index_to_world(np.array([[0.0, 0.0, vol.shape[2] - 1.0]]))[0, 2]
    assert res.report["dropped_components"] >= 1
    assert g.root.points[0][2] > zt - 3 * MM and np.hypot(*g.root.points[0][:2]) < 2 * MM, res.report
    assert g.root.length > 25 * MM and len(g.children(g.root.id)) >= 2


FLAT = {"24x10": (12.0, 5.0, 0.0), "20x12": (10.0, 6.0, 0.0), "24x10_tilted_20deg": (12.0, 5.0, 20.0),
        "20x12_tilted_20deg": (10.0, 6.0, 20.0)}


def _flare_mask(top: float, h: float = 0.6) -> Volume:
    """A trachea with a carinal flare, all lengths in mm: round (7 mm radius) down to z = -20, then over 30 mm
    its elliptic cross-section widens along x to 14 mm and narrows along y to 5.5 mm half-axes (aspect 2.5 at
    its bottom, z = -50); main bronchi (5.5 mm radius, 34 deg from vertical) leave from (+-6, 0, -45).  The scan
    is cut at z = ``top`` (the volume's top slice).  Grid spacing ``h``; affine in metres."""
    x, y, z = np.arange(-45, 45.01, h), np.arange(-12, 12.01, h), np.arange(-80, top + 0.01, h)
    X, Y, Z = np.meshgrid(x, y, z, indexing="ij")
    f = np.clip((Z + 20.0) / -30.0, 0.0, 1.0)
    m = (Z >= -50) & ((X / (7 + 7 * f)) ** 2 + (Y / (7 - 1.5 * f)) ** 2 <= 1.0)
    for sx in (-1.0, 1.0):
        d, o = np.array([sx * np.sin(0.6), 0.0, -np.cos(0.6)]), np.array([sx * 6.0, 0.0, -45.0])
        t = np.clip((X - o[0]) * d[0] + (Z - o[2]) * d[2], 0, 35)
        m |= (X - o[0] - t * d[0]) ** 2 + Y ** 2 + (Z - o[2] - t * d[2]) ** 2 <= 5.5 ** 2
    aff = np.diag([h * MM] * 3 + [1.0])
    aff[:3, 3] = [x[0] * MM, y[0] * MM, z[0] * MM]
    return Volume(m.astype(np.uint8), aff)


@pytest.mark.parametrize("top", [-30.0, -36.0])
def test_a_cut_at_the_carinal_flare_is_not_a_flattened_trachea(top):
    """Issue #18 (Med-MPD 1 cut 10 / 5 / 2 mm above its carina): a scan cut 15 / 9 mm above the carina (z = -45)
    through the carinal flare has a flattened top cross-section (aspect 1.7-2.1, its medial set a sheet under the
    -36 cut: the flattened-trachea rule fired there and the route started in a bronchus, 37 mm below the cut).
    The lumen divides into the two main bronchi 21 / 14 mm (3.3 / 2.3 radii) below the top
    (``trachea_divides_below_mm``, bound ``FLARE_DEPTH_RADII``): a flare, read by the round-trachea rules.  The
    route starts at the cut on the axis and the root ends within 6 mm of the carina (measured 5.0 / 4.8 mm) with
    the two main bronchi below it."""
    from room_pipeline.anatomy.medial_axis import FLAT_ASPECT
    from room_pipeline.anatomy.trachea_root import FLARE_DEPTH_RADII

    res = extract_medial_axis(compute_sdf(_flare_mask(top), SdfParams()), MedialAxisParams())
    g = res.graph
    check_tree(g)
    rep = {k: v for k, v in res.report.items() if k.startswith("root") or k.startswith("trachea")}
    assert rep["trachea_aspect_ratio"] > FLAT_ASPECT, rep
    print(f"\nflare cut at z = {top:g} mm: divides {rep['trachea_divides_below_mm']} mm = "
          f"{rep['trachea_divides_below_radii']} radii below the top; root end {g.root.points[-1] / MM} mm")
    assert rep["root_centred"] is False and rep["trachea_carinal_flare"] is True, rep
    assert 0 < rep["trachea_divides_below_radii"] <= FLARE_DEPTH_RADII, rep
    assert g.root.points[0][2] > (top - 3) * MM and np.hypot(*g.root.points[0][:2]) < 1 * MM, rep
    assert np.linalg.norm(g.root.points[-1] - np.array([0, 0, -45]) * MM) < 6 * MM, (g.root.points[-1] / MM, rep)
    assert len(g.children(g.root.id)) == 2 and len(g.branches) == 3, rep


@pytest.mark.parametrize("case", sorted(FLAT))
def test_root_is_the_flattened_tracheas_cut_end(case):
    """Issue #18 (fibrotic lungs, CASE073): a flattened trachea's medial surface is a sheet.  The most
    superior wide point lay at the sheet's edge and the skeleton's lines along the sheet's edges and across its
    top left the root with several wide arms ('no trachea-like root').  The root is now the middle of the top
    cross-section and the sheet's cross-sections along the first path are taken (``_trachea_sheet``): the
    route starts on the trachea's axis at the cut and the trachea is one branch down to the carina."""
    half_x, half_y, tilt = FLAT[case]
    vol = flat_trachea_mask(half_x, half_y, tilt)
    res = extract_medial_axis(compute_sdf(vol, SdfParams()), MedialAxisParams())
    g = res.graph
    check_tree(g)
    top = vol.index_to_world(np.array([[0.0, 0.0, vol.shape[2] - 1.0]]))[0, 2]
    rep = {k: v for k, v in res.report.items() if k.startswith("root") or k.startswith("trachea")}
    assert res.report["root_centred"] is True, rep
    print(f"\n{case}: divides {rep['trachea_divides_below_mm']} mm = {rep['trachea_divides_below_radii']} radii "
          "below the top")
    assert res.report["trachea_carinal_flare"] is False, rep              # not a carinal flare
    assert g.root.points[0][2] > top - 3 * MM, rep                        # starts at the cut ...
    axis_x = np.tan(np.deg2rad(tilt)) * 45 * MM
    assert abs(g.root.points[0][0] - axis_x) < 2 * MM, rep                 # ... in the middle of the cross-section
    assert abs(g.root.points[0][1]) < 2 * MM, rep
    assert g.root.radius[:5].min() > 0.8 * half_y * MM, rep                # on the sheet's widest line, no crease
    assert g.root.length > 30 * MM, rep                                   # the trachea down to near the carina
    assert len(g.children(g.root.id)) == 2, [(b.id, b.parent, round(b.length / MM, 1)) for b in g.branches]
    assert len(g.branches) == 3, [(b.id, b.parent, round(b.length / MM, 1)) for b in g.branches]
    # the root branch stays within 2 mm of the trachea's axis down to 10 mm above the carina
    p = g.root.points[g.root.points[:, 2] > -35 * MM]
    assert np.abs(p[:, 0] - np.tan(np.deg2rad(tilt)) * (p[:, 2] + 45 * MM)).max() < 2 * MM
    assert np.abs(p[:, 1]).max() < 2 * MM


@pytest.mark.parametrize("case,expected", [("round r6", 1.0), ("16x14", 8 / 7), ("20x12", 10 / 6), ("24x10", 12 / 5),
                                           ("16x14_tilted_20deg", 8 * np.cos(np.deg2rad(20)) / 7),
                                           ("20x12_tilted_20deg", 10 * np.cos(np.deg2rad(20)) / 6)])
def test_flattened_trachea_switch_measures_the_cross_section(case, expected):
    """Issue #18: the flattened-trachea switch is the lumen's cross-section aspect ratio normal to the trachea's
    axis (``FLAT_ASPECT``), not the medial points' spread.  The synthetic tracheas are elliptic in horizontal
    slices, so leaning 20 deg along the long axis their normal section is cos(20) shorter along it.  Round and
    16x14 mm stay round (no centring), 20x12 and 24x10 mm switch, with the margins of
    benchmarks/results/anatomy_trachea_aspect.md."""
    from room_pipeline.anatomy.medial_axis import FLAT_ASPECT

    name, _, tilt = case.partition("_tilted_")
    hx, hy = {"round r6": (6.0, 6.0), "16x14": (8.0, 7.0), "20x12": (10.0, 6.0), "24x10": (12.0, 5.0)}[name]
    vol = flat_trachea_mask(hx, hy, float(tilt[:-3]) if tilt else 0.0)
    rep = extract_medial_axis(compute_sdf(vol, SdfParams()), MedialAxisParams()).report
    assert rep["trachea_aspect_ratio"] == pytest.approx(max(expected, 1 / expected), rel=0.06), rep
    assert rep["root_centred"] is bool(max(expected, 1 / expected) > FLAT_ASPECT)


def test_root_arms_tell_a_parallel_line_from_a_way_out():
    """The measure behind CASE073's fix (issue #18): from a root on the trachea's axis, a second skeleton line
    running beside the axis 5 mm away (a flattened trachea's medial sheet, a crease) stays within the
    pruning length of the main arm, while a stretch of trachea above a mid-tube root leaves it."""
    from room_pipeline.anatomy.medial_axis import _root_arms

    down = [(0.0, 0.0, -k) for k in range(1, 41)]                   # main arm: 40 mm down the axis, r 7 mm
    side = [(5.0, 0.0, -k) for k in range(1, 19)]                   # a parallel line, 18 mm, thinning
    up = [(0.0, 0.0, k) for k in range(1, 21)]                      # 20 mm of trachea above the root
    pts = np.array([(0.0, 0.0, 0.0)] + down + side + up) * MM
    rad = np.array([7.0] + [7.0] * 40 + list(np.linspace(6.5, 0.6, 18)) + [6.5] * 20) * MM
    n = len(pts)
    parent = np.full(n, -1)
    parent[1] = 0
    parent[2:41] = np.arange(1, 40)
    parent[41] = 0
    parent[42:59] = np.arange(41, 58)
    parent[59] = 0
    parent[60:] = np.arange(59, n - 1)
    dist = np.zeros(n)
    for i in range(1, n):
        dist[i] = dist[parent[i]] + np.linalg.norm(pts[i] - pts[parent[i]])
    arms = _root_arms(0, np.ones(n, bool), parent, dist, pts, rad, 3.5 * MM)
    keep = 1.5 * 7.0 * MM                                            # prune_factor x root radius
    (L_d, W_d, F_d), (L_s, W_s, F_s), (L_u, W_u, F_u) = arms[1], arms[41], arms[59]
    assert L_d == pytest.approx(40 * MM) and F_d == np.inf
    assert L_s == pytest.approx((17 + np.sqrt(26)) * MM) and W_s >= keep   # long and wide enough ...
    assert F_s == pytest.approx(5 * MM) and F_s < keep                # ... but never leaves the main arm
    assert W_u == pytest.approx(20 * MM) and F_u == pytest.approx(21 * MM) and F_u >= keep   # to the axis below
