"""Tests of the procedural phantom (room_pipeline.anatomy.phantom)."""
from __future__ import annotations

import csv
import dataclasses
import os
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from room_pipeline.anatomy.centreline import from_airway_tree
from room_pipeline.anatomy.phantom import (Phantom, PhantomParams, grow_tree, kitaoka_angle,
                                           lung_signed_distance, make_phantom, segment_distances,
                                           wall_thickness)
from room_pipeline.anatomy.tree import nearest_branch
from room_pipeline.conventions import MM
from room_pipeline.errors import ConfigError

REPO = Path(__file__).resolve().parents[1]
SCHMIDT_CSV = Path(os.environ.get("ROOM_SHARED_DATA", REPO.parent / "shared" / "data")) \
    / "airway_trees" / "schmidt2004" / "TreeData.csv"

#: coarse, cheap variant used by most tests (about 2 M voxels)
SMALL = dict(spacing_mm=1.5, min_diameter_mm=3.0, lung_points=6000)


@pytest.fixture(scope="module")
def small() -> Phantom:
    return make_phantom(PhantomParams.from_dict(SMALL), seed=3)


@pytest.fixture(scope="module")
def default_tree():
    return grow_tree(PhantomParams(), np.random.default_rng(0))


@pytest.fixture(scope="module")
def default_run() -> tuple[Phantom, float]:
    """The one default-size phantom (seed 0) and its make_phantom wall time, shared by the tests."""
    t0 = time.perf_counter()
    ph = make_phantom(PhantomParams(), seed=0)
    return ph, time.perf_counter() - t0


# ----------------------------------------------------------------------------- config


def test_unknown_key_is_config_error():
    with pytest.raises(ConfigError, match="unknown key 'phantom.trachea_diam'"):
        PhantomParams.from_dict({"trachea_diam": 17})
    with pytest.raises(ConfigError):
        PhantomParams.from_dict({"spacing_mm": [1.0, -1.0, 1.0]})
    with pytest.raises(ConfigError):
        PhantomParams.from_dict({"min_diameter_mm": "two"})


def test_yaml_lists_every_field_with_its_default():
    d = yaml.safe_load((REPO / "conf" / "phantom" / "default.yaml").read_text())
    assert set(d) == {f.name for f in dataclasses.fields(PhantomParams)}
    assert PhantomParams.from_dict(d) == PhantomParams()
    assert PhantomParams.from_dict({"spacing_mm": 0.9}).spacing_mm == (0.9, 0.9, 0.9)


# ----------------------------------------------------------------------------- tree


def _check_rooted_tree(tree):
    ids = [b.id for b in tree.branches]
    assert len(ids) == len(set(ids))
    roots = [b for b in tree.branches if b.parent == -1]
    assert len(roots) == 1 and roots[0].id == 0 and roots[0].generation == 0
    for b in tree.branches:
        if b.parent == -1:
            continue
        p = tree.branch(b.parent)
        n_kids = len(tree.children(p.id))
        assert n_kids <= 2
        # generation counts bifurcations: a lone daughter continues its parent's airway
        assert b.generation == p.generation + (1 if n_kids == 2 else 0)
        np.testing.assert_array_equal(b.start, p.end)  # children start at the parent's end
        assert b.radius < p.radius
        assert b.length > 0


def _non_adjacent_gaps(tree) -> np.ndarray:
    """Lumen gaps (segment distance - r1 - r2, metres) of every capsule pair that is not
    parent/child, grandparent/grandchild or siblings (the pairs grow_tree keeps apart)."""
    br = tree.branches
    index = {b.id: i for i, b in enumerate(br)}
    S = np.array([b.start for b in br])
    E = np.array([b.end for b in br])
    R = np.array([b.radius for b in br])
    par = np.array([index.get(b.parent, -1) for b in br])
    gpar = np.where(par >= 0, par[np.maximum(par, 0)], -1)
    gpar[par < 0] = -1
    idx = np.arange(len(br))
    adjacent = np.eye(len(br), dtype=bool)
    for rel in (par, gpar):
        adjacent |= rel[:, None] == idx[None, :]
        adjacent |= rel[None, :] == idx[:, None]
    adjacent |= (par[:, None] == par[None, :]) & (par[:, None] >= 0)
    gap = segment_distances(S[:, None], E[:, None], S[None], E[None]) - R[:, None] - R[None, :]
    return gap[np.triu(~adjacent, 1)]


def test_default_tree_is_valid_and_deep(default_tree):
    t = default_tree
    _check_rooted_tree(t)
    gens = np.array([b.generation for b in t.branches])
    assert t.max_generation >= 6
    assert all((gens == g).any() for g in range(7))
    # every branch at least min_diameter across: several voxels at 0.7 mm
    assert min(b.radius for b in t.branches) * 2 >= 2.0 * MM - 1e-12


def test_trachea_and_main_bronchi(default_tree):
    t = default_tree
    tr = t.branch(0)
    assert tr.name == "trachea"
    assert 16 * MM <= 2 * tr.radius <= 18 * MM
    assert 100 * MM <= tr.length <= 120 * MM
    np.testing.assert_allclose(tr.direction, [0, 0, -1])
    rmb, lmb = t.children(0)
    assert (rmb.name, lmb.name) == ("RMB", "LMB")
    assert rmb.end[0] > 0 > lmb.end[0]  # RAS+: right is +x
    angle = lambda b: np.degrees(np.arccos(-b.direction[2]))  # noqa: E731  angle to the tracheal axis
    assert angle(rmb) < angle(lmb)     # right main bronchus steeper ...
    assert rmb.length < lmb.length     # ... and shorter
    assert rmb.radius > lmb.radius     # and wider (it supplies the larger lung)


def test_radius_decreases_with_generation(default_tree):
    gens = np.array([b.generation for b in default_tree.branches])
    rad = np.array([b.radius for b in default_tree.branches])
    means = [rad[gens == g].mean() for g in range(7)]
    assert all(a > b for a, b in zip(means, means[1:]))
    assert np.corrcoef(gens, rad)[0, 1] < -0.5


def test_kitaoka_rules(default_tree):
    """Flow-diameter rule d0^n = d1^n + d2^n and the flow-based branching angles."""
    n = PhantomParams().flow_exponent
    checked = 0
    for p in default_tree.branches:
        kids = default_tree.children(p.id)
        if p.generation < 1 or len(kids) != 2:
            continue
        r = [(k.radius / p.radius) ** n for k in kids]
        assert sum(r) == pytest.approx(1.0, rel=1e-9)
        for k, rk in zip(kids, r):
            ang = np.arccos(np.clip(p.direction @ k.direction, -1, 1))
            assert ang == pytest.approx(kitaoka_angle(rk, n), abs=1e-6)
        checked += 1
    assert checked > 20
    # symmetric split: cos(theta) = 1 / (2 * 0.5^(2/n)), about 37.5 deg for n = 2.8
    assert kitaoka_angle(0.5, 2.8) == pytest.approx(np.arccos(1 / (2 * 0.5 ** (2 / 2.8))))
    assert kitaoka_angle(0.1) > kitaoka_angle(0.5)  # the minor daughter bends more


@settings(max_examples=6, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_random_seeds_stay_in_lungs_and_deep(seed):
    params = PhantomParams()
    tree = grow_tree(params, np.random.default_rng(seed))
    assert tree.max_generation >= 6
    _check_rooted_tree(tree)
    # beyond the main bronchi every branch ends inside a lung; one that starts with its
    # capsule inside a lung keeps its whole capsule inside
    for b in tree.branches:
        if b.name in ("trachea", "RMB", "LMB"):
            continue
        sd = lung_signed_distance(np.stack([b.start, b.end]), params)
        assert sd[1] <= 1e-9
        if sd[0] <= -b.radius:
            assert sd[1] <= -b.radius + 1e-9


def test_segment_distances_closed_form():
    """Closed-form segment-segment distance vs dense sampling (general, parallel, degenerate cases)."""
    rng = np.random.default_rng(7)
    p0, p1, q0, q1 = (rng.normal(size=(100, 3)) for _ in range(4))
    q1[:20] = q0[:20] + 0.7 * (p1[:20] - p0[:20])   # parallel
    q1[20:30] = q0[20:30]                            # second segment a point
    p1[30:40] = p0[30:40]                            # first segment a point
    q0[40:50], q1[40:50] = p0[40:50], p1[40:50]      # identical
    got = segment_distances(p0, p1, q0, q1)
    t = np.linspace(0, 1, 301)
    a = p0[:, None] + t[None, :, None] * (p1 - p0)[:, None]
    b = q0[:, None] + t[None, :, None] * (q1 - q0)[:, None]
    brute = np.linalg.norm(a[:, :, None] - b[:, None, :], axis=-1).min(axis=(1, 2))
    assert np.all(got <= brute + 1e-12)
    np.testing.assert_allclose(got, brute, atol=5e-3)
    # one segment against many broadcasts
    one = segment_distances(p0[0], p1[0], q0, q1)
    assert one.shape == (100,) and one[0] == pytest.approx(got[0])
    np.testing.assert_allclose(one, segment_distances(np.broadcast_to(p0[0], q0.shape),
                                                      np.broadcast_to(p1[0], q0.shape), q0, q1))


@pytest.mark.parametrize("seed", range(6))
def test_non_adjacent_branches_keep_clearance(seed):
    """No two capsules other than parent/child, grandparent/grandchild or siblings come closer
    than r1 + r2 + min_branch_clearance_mm (collision avoidance, our deviation from Kitaoka)."""
    params = PhantomParams()
    tree = grow_tree(params, np.random.default_rng(seed))
    gaps = _non_adjacent_gaps(tree)
    assert len(gaps) > 1000
    assert gaps.min() >= params.min_branch_clearance_mm * MM - 1e-9, f"min gap {gaps.min() / MM:.3f} mm"


def test_clearance_is_a_parameter():
    base = grow_tree(PhantomParams(), np.random.default_rng(0))
    wide = grow_tree(PhantomParams(min_branch_clearance_mm=4.0), np.random.default_rng(0))
    assert _non_adjacent_gaps(wide).min() >= 4.0 * MM - 1e-9
    assert len(wide) < len(base)
    with pytest.raises(ConfigError):
        PhantomParams(min_branch_clearance_mm=-1.0)


def test_generation_counts_bifurcations(default_tree):
    """A lone daughter keeps its parent's generation; the centreline graph (which merges such
    continuation chains) has the same generations, and >= 6 bifurcation generations."""
    t = default_tree
    kids = {b.id: t.children(b.id) for b in t.branches}
    lone = [k[0] for k in kids.values() if len(k) == 1]
    assert len(lone) > 10
    for c in lone:
        assert c.generation == t.branch(c.parent).generation
    for b in t.branches:
        if len(kids[b.id]) == 2:
            assert all(k.generation == b.generation + 1 for k in kids[b.id])
    graph = from_airway_tree(t, 2 * MM)
    for gb in graph.branches:
        assert gb.generation == t.branch(gb.id).generation
    assert max(gb.generation for gb in graph.branches) == t.max_generation >= 6


# ----------------------------------------------------------------------------- volumes


def test_determinism(small):
    again = make_phantom(PhantomParams.from_dict(SMALL), seed=3)
    assert again.ct.data.tobytes() == small.ct.data.tobytes()
    assert again.sdf.data.tobytes() == small.sdf.data.tobytes()
    np.testing.assert_array_equal(again.ct.affine, small.ct.affine)
    other = grow_tree(PhantomParams.from_dict(SMALL), np.random.default_rng(4))
    assert len(other) != len(small.tree) or any(
        not np.array_equal(a.end, b.end) for a, b in zip(other.branches, small.tree.branches))


def test_volume_types_and_affine(small):
    ph = small
    assert ph.ct.data.dtype == np.int16 and ph.mask.data.dtype == np.uint8
    assert ph.sdf.data.dtype == np.float32 and ph.sdf_exact.data.dtype == bool
    for v in (ph.mask, ph.sdf, ph.sdf_exact):
        assert v.shape == ph.ct.shape
        np.testing.assert_array_equal(v.affine, ph.ct.affine)
    A = ph.ct.affine
    np.testing.assert_allclose(A[:3, :3], np.diag([1.5 * MM] * 3))
    assert ph.ct.superior_axis() == (2, 1)
    # the whole tree, including the trachea's top end, is inside the field of view
    lo, hi = ph.tree.bounds()
    ijk_lo, ijk_hi = ph.ct.world_to_index(np.stack([lo, hi]))
    assert np.all(ijk_lo >= 0) and np.all(ijk_hi <= np.array(ph.ct.shape) - 1)
    assert ph.mask.data[:, :, -1].sum() == 0


def test_mask_sdf_and_exact(small):
    ph = small
    np.testing.assert_array_equal(ph.mask.data, (ph.sdf.data < 0).astype(np.uint8))
    band = PhantomParams.from_dict(SMALL).sdf_band_mm * MM
    assert ph.sdf.data.max() <= band + 1e-9
    assert ph.sdf.data.min() >= -ph.tree.branch(0).radius - 1e-6
    # stored values equal the whole tree's AirwayTree.sdf where inside the band
    rng = np.random.default_rng(0)
    near = np.argwhere(np.abs(ph.sdf.data) < band)
    lumen = np.argwhere(ph.mask.data > 0)
    pick = np.concatenate([near[rng.choice(len(near), 3000)], lumen[rng.choice(len(lumen), 1000)]])
    ref, ref_exact = ph.tree.sdf(ph.ct.index_to_world(pick))
    got = ph.sdf.data[tuple(pick.T)]
    np.testing.assert_allclose(got, ref, atol=1e-6)
    np.testing.assert_array_equal(ph.sdf_exact.data[tuple(pick.T)], ref_exact)
    # clipped far field is not flagged exact; most of the band is
    assert not ph.sdf_exact.data[ph.sdf.data >= band].any()
    assert ph.sdf_exact.data[np.abs(ph.sdf.data) < band].mean() > 0.9


def test_hu_layers_exact_without_scanner_model():
    """Without PSF, noise and texture every pure voxel has its layer's HU."""
    params = PhantomParams.from_dict({**SMALL, "spacing_mm": 1.2, "psf_sigma_voxels": 0, "noise_sigma_hu": 0,
                                      "texture_sigma_hu": 0})
    ph = make_phantom(params, seed=1)
    ct, sdf = ph.ct.data, ph.sdf.data
    h = 1.2 * MM
    assert np.all(ct[sdf < -h / 2] == -1000)
    assert np.all(ct[:2, :2, :] == -1000)  # corners: air outside the body
    # wall interior voxels (farther than h/2 from both wall surfaces)
    idx = np.argwhere((sdf > h / 2) & (sdf < 5 * MM))
    pts = ph.ct.index_to_world(idx)
    _, bid = nearest_branch(ph.tree.centreline(0.5 * MM), pts)
    t = wall_thickness(np.array([ph.tree.branch(b).radius for b in bid]), params)
    inner = sdf[tuple(idx.T)] < t - h / 2
    assert inner.sum() > 100
    assert np.all(ct[tuple(idx[inner].T)] == 40)
    # deep parenchyma
    far = np.argwhere(sdf >= 5 * MM)[::7]
    deep = lung_signed_distance(ph.ct.index_to_world(far), params) < -2 * h
    assert np.all(ct[tuple(far[deep].T)] == -850)


def test_hu_ranges_realistic(small):
    ph, params = small, PhantomParams.from_dict(SMALL)
    ct, sdf = ph.ct.data.astype(float), ph.sdf.data
    assert -1010 < ct[sdf < -3 * MM].mean() < -980          # lumen
    far = np.argwhere(sdf >= 5 * MM)[::5]
    lung = lung_signed_distance(ph.ct.index_to_world(far), params) < -5 * MM
    par = ct[tuple(far[lung].T)]
    assert -870 < par.mean() < -830 and 20 < par.std() < 60  # textured parenchyma + noise
    # intrapulmonary airway walls stand out from the parenchyma
    assert ct[(sdf > 0) & (sdf < 1.5 * MM)].mean() > par.mean() + 150
    assert ct.min() >= -1024 and ct.max() < 400


def test_crop_top_cuts_trachea():
    params = PhantomParams.from_dict({**SMALL, "spacing_mm": 2.0, "crop_top_mm": 20.0})
    ph = make_phantom(params, seed=3)
    top = ph.ct.index_to_world(np.array([[0, 0, ph.ct.shape[2] - 1]]))[0, 2]
    assert top <= ph.tree.branch(0).start[2] - 20 * MM + 1e-9
    assert ph.mask.data[:, :, -1].sum() > 10  # the trachea leaves through the top slice
    assert (ph.ct.data[:, :, -1][ph.mask.data[:, :, -1] > 0] < -500).all()


def test_anisotropic_spacing():
    params = PhantomParams.from_dict({**SMALL, "spacing_mm": [1.4, 1.6, 2.2]})
    ph = make_phantom(params, seed=3)
    np.testing.assert_allclose(ph.ct.spacing, np.array([1.4, 1.6, 2.2]) * MM)
    np.testing.assert_array_equal(ph.mask.data, (ph.sdf.data < 0).astype(np.uint8))
    # lumen volume close to the tree's analytic volume estimate (within PV / overlap slack)
    vox = np.prod(ph.ct.spacing)
    approx = sum(np.pi * b.radius ** 2 * b.length for b in ph.tree.branches)
    assert 0.7 < ph.mask.data.sum() * vox / approx < 1.3


def test_default_size_run(default_run):
    """The one default-size run: figures and the trachea inside the volume (its time is printed, not asserted:
    tests never bound wall-clock time; the phantom's cost is in benchmarks/)."""
    ph, wall = default_run
    n = int(np.prod(ph.ct.shape))
    print(f"default phantom: shape {ph.ct.shape}, {n / 1e6:.1f} M voxels, {len(ph.tree)} branches, "
          f"max generation {ph.tree.max_generation}, {wall:.1f} s")
    assert 15e6 < n < 45e6
    assert ph.tree.max_generation >= 6
    assert ph.mask.data[:, :, -1].sum() == 0 and ph.mask.data.sum() > 0
    np.testing.assert_allclose(ph.ct.spacing, 0.7 * MM)
    # HU at 0.7 mm: lumen, trachea wall (mid-wall, in the mediastinum), parenchyma
    params = PhantomParams()
    ct, sdf = ph.ct.data, ph.sdf.data
    assert -1010 < ct[sdf < -3 * MM].mean() < -980
    k0, k1 = (int(round(v)) for v in ph.ct.world_to_index(np.array([[0, 0, 20 * MM], [0, 0, 90 * MM]]))[:, 2])
    t = wall_thickness(ph.tree.branch(0).radius, params)
    s = sdf[:, :, k0:k1]
    wall = ct[:, :, k0:k1][(s > 0.35 * t) & (s < 0.75 * t)]
    assert 0 < wall.mean() < 80


# ----------------------------------------------------------------------------- reference data


def test_radius_matches_schmidt_generations_0_to_5(default_tree):
    if not SCHMIDT_CSV.is_file():
        pytest.skip(f"Schmidt 2004 reference tree not available: {SCHMIDT_CSV}")
    with SCHMIDT_CSV.open() as fh:
        rows = list(csv.DictReader(fh))
    ref_g = np.array([int(r["generation"]) for r in rows])
    ref_r = np.array([float(r["radius"]) for r in rows]) * MM
    gens = np.array([b.generation for b in default_tree.branches])
    rad = np.array([b.radius for b in default_tree.branches])
    for g in range(6):
        ratio = rad[gens == g].mean() / ref_r[ref_g == g].mean()
        assert 0.5 <= ratio <= 2.0, f"generation {g}: phantom/Schmidt radius ratio {ratio:.2f}"


# ----------------------------------------------------------------------------- lumen topology

#: Why the marching-cubes Euler test is xfail (measured, seeds 0-9, after collision avoidance):
#: the capsule union has a sharp, sub-voxel crevice at every carina (the wedge between sibling
#: lumens thins to zero at the crotch) and at every parent-cap shoulder.  Sampled on a grid, these
#: crevices are bridged or pinched off depending on the grid offset, which gives spurious handles
#: and cavities: chi of the level-0 surface is 2 on only a few seeds with either marching-cubes
#: method (Lewiner: 0 at seed 0; Lorensen: 2 at seed 0 but 0 / 6 / -4 with extra components on
#: others), and level sets shifted into the lumen do no better.  Before the fix chi was -12
#: (Lewiner) at seed 0; the loops from intersecting branches are gone (test (a) checks every
#: non-adjacent pair analytically), the rest are sampling artefacts of the ground-truth shape.
CREVICE_ARTEFACTS = ("sub-voxel carina crevices of the capsule union give grid-dependent handles in "
                     "marching cubes (chi 0 at seed 0, Lewiner); see the comment above")


def _surface_topology(sdf: np.ndarray) -> tuple[int, int]:
    """(Euler characteristic V - E + F, connected components) of the zero level set of ``sdf``.

    skimage marching cubes (default Lewiner method) at level 0 on the volume
    cropped to the lumen (plus 2 voxels) and padded with positive values, so
    the surface is closed; E counts unique undirected edges.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from skimage.measure import marching_cubes

    inside = np.argwhere(sdf < 0)
    lo = np.maximum(inside.min(axis=0) - 2, 0)
    hi = inside.max(axis=0) + 3
    vol = np.pad(sdf[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]], 1, constant_values=max(float(sdf.max()), 1e-3))
    verts, faces, _, _ = marching_cubes(vol, level=0.0)
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    edges, count = np.unique(edges, axis=0, return_counts=True)
    assert np.all(count == 2)  # closed 2-manifold: every edge in exactly two triangles
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(len(verts), len(verts)))
    return len(verts) - len(edges) + len(faces), connected_components(graph, directed=False)[0]


def _mask_components(mask: np.ndarray) -> int:
    from scipy import ndimage
    return ndimage.label(mask > 0, structure=np.ones((3, 3, 3)))[1]


@pytest.fixture(scope="module")
def coarse_phantoms() -> dict[int, Phantom]:
    """Seeds 1 and 2 at 1.0 mm spacing (cheaper than the default 0.7 mm)."""
    return {seed: make_phantom(PhantomParams(spacing_mm=1.0), seed=seed) for seed in (1, 2)}


def test_mask_is_one_26_connected_component(default_run, coarse_phantoms):
    assert _mask_components(default_run[0].mask.data) == 1
    for ph in coarse_phantoms.values():
        assert _mask_components(ph.mask.data) == 1


@pytest.mark.xfail(reason=CREVICE_ARTEFACTS, strict=False)
def test_default_lumen_surface_is_a_sphere(default_run):
    """Marching cubes of the seed-0 ground-truth SDF: one closed surface with chi = 2."""
    chi, n_surfaces = _surface_topology(default_run[0].sdf.data)
    print(f"seed 0, 0.7 mm: chi {chi}, {n_surfaces} surface(s)")
    assert (n_surfaces, chi) == (1, 2)


@pytest.mark.xfail(reason=CREVICE_ARTEFACTS, strict=False)
@pytest.mark.parametrize("seed", [1, 2])
def test_coarse_lumen_surface_is_a_sphere(coarse_phantoms, seed):
    chi, n_surfaces = _surface_topology(coarse_phantoms[seed].sdf.data)
    print(f"seed {seed}, 1.0 mm: chi {chi}, {n_surfaces} surface(s)")
    assert (n_surfaces, chi) == (1, 2)
