"""A measured tree as a phantom patient (``phantoms.<id>.tree``, :mod:`room_pipeline.anatomy.reference_tree`).

The branch table's reading (parents, generations, frames, the carina at the origin), every malformed table
ending in one :class:`InputError` line naming the file, the lungs built around the tree, the stage's pin of
the table's bytes, and (shared data, slow) the Schmidt et al. 2004 reference tree through every stage with
its exact ground truth.
"""
from __future__ import annotations

import hashlib
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from room_pipeline.anatomy.phantom import rasterise
from room_pipeline.anatomy.phantom_params import PhantomParams
from room_pipeline.anatomy.reference_tree import hull_lungs, read_tree_table
from room_pipeline.config.compose import PhantomEntry
from room_pipeline.errors import ConfigError, InputError

from .conftest import REPO, shared_path

HEADER = "id,generation,lobe,radius,x1,y1,z1,x2,y2,z2\n"
#: a trachea (10 mm above the carina at (100, 50, 200) mm) and two main bronchi, each with two daughters
Y_TREE = [
    (0, 0, -1, 7.0, 100, 50, 300, 100, 50, 200),
    (1, 1, -1, 5.0, 100, 50, 200, 140, 50, 160),
    (2, 1, -1, 5.0, 100, 50, 200, 70, 50, 150),
    (3, 2, 1, 3.0, 140, 50, 160, 160, 60, 120),
    (4, 2, 1, 3.0, 140, 50, 160, 150, 40, 110),
    (5, 2, 2, 3.0, 70, 50, 150, 50, 60, 110),
    (6, 2, 2, 3.0, 70, 50, 150, 60, 40, 100),
]


def _table(tmp_path: Path, rows, header: str = HEADER, name: str = "tree.csv") -> Path:
    p = tmp_path / name
    p.write_text(header + "".join(",".join(str(v) for v in r) + "\n" for r in rows))
    return p


def test_table_read_parents_generations_and_carina_at_origin(tmp_path):
    tree = read_tree_table(_table(tmp_path, Y_TREE))
    assert len(tree) == 7 and tree.max_generation == 2
    root = tree.branch(0)
    assert root.parent == -1 and root.generation == 0
    np.testing.assert_allclose(root.end, 0.0, atol=1e-12)                    # carina at the world origin
    np.testing.assert_allclose(root.start, [0.0, 0.0, 0.1], atol=1e-12)      # metres
    assert root.radius == pytest.approx(7e-3)
    for b in tree.branches[1:]:
        parent = tree.branch(b.parent)
        assert b.generation == parent.generation + 1
        np.testing.assert_allclose(b.start, parent.end, atol=1e-12)
    assert sorted(len(tree.children(b.id)) for b in tree.branches) == [0, 0, 0, 0, 2, 2, 2]


def test_table_row_order_and_numbering_do_not_matter(tmp_path):
    a = read_tree_table(_table(tmp_path, Y_TREE, name="a.csv"))
    shuffled = [Y_TREE[i] for i in (4, 0, 6, 2, 1, 5, 3)]
    shuffled = [(99 - k, 7, 0, *r[3:]) for k, r in enumerate(shuffled)]  # ids and generations wrong on purpose
    b = read_tree_table(_table(tmp_path, shuffled, name="b.csv"))
    key = lambda t: sorted((tuple(np.round(x.start, 9)), tuple(np.round(x.end, 9)), x.generation) for x in t.branches)
    assert key(a) == key(b)


def test_lps_table_negates_x_and_y(tmp_path):
    ras = read_tree_table(_table(tmp_path, Y_TREE), "RAS")
    lps = read_tree_table(_table(tmp_path, Y_TREE), "LPS")
    for r, l in zip(ras.branches, lps.branches):
        np.testing.assert_allclose(l.end, r.end * [-1, -1, 1], atol=1e-12)


@pytest.mark.parametrize("case", ["missing_column", "not_a_number", "nan", "zero_radius", "zero_length",
                                  "two_roots", "two_parents", "loop", "empty", "binary", "missing_file"])
def test_bad_table_one_line_naming_the_file(tmp_path, case):
    rows = [list(r) for r in Y_TREE]
    header = HEADER
    if case == "missing_column":
        header = HEADER.replace(",radius", ",rad")
    elif case == "not_a_number":
        rows[3][4] = "abc"
    elif case == "nan":
        rows[3][5] = "nan"
    elif case == "zero_radius":
        rows[2][3] = 0.0
    elif case == "zero_length":
        rows[6][7:10] = rows[6][4:7]
    elif case == "two_roots":
        rows[5][4:7] = [0, 0, 0]
    elif case == "two_parents":
        rows[2][7:10] = rows[1][7:10]       # both main bronchi end at one point: its daughters' start joins two
    elif case == "loop":
        rows.append([7, 3, 0, 1.0, 160, 60, 120, 100, 50, 200])   # a branch back to the carina: two parents
    elif case == "empty":
        rows = []
    path = _table(tmp_path, rows, header)
    if case == "binary":
        path.write_bytes(b"\xff\xfe\x00\x01" * 50)
    if case == "missing_file":
        path = tmp_path / "absent.csv"
    with pytest.raises(InputError) as exc:
        read_tree_table(path)
    msg = str(exc.value)
    assert "\n" not in msg and str(path) in msg, msg


def test_hull_lungs_hold_the_lobar_branches_and_leave_the_mediastinum(tmp_path):
    tree = read_tree_table(_table(tmp_path, Y_TREE))
    params = PhantomParams(spacing_mm=(1.0, 1.0, 1.0), sdf_band_mm=3.0)
    xs = np.arange(-80, 80, 1.0) * 1e-3
    ys = np.arange(-40, 40, 1.0) * 1e-3
    zs = np.arange(-120, 20, 1.0) * 1e-3
    sd = hull_lungs(tree, params, reach_mm=15.0)(xs, ys, zs)
    assert sd.shape == (len(xs), len(ys), len(zs)) and sd.dtype == np.float32
    idx = lambda p: tuple(int(round((v - a[0]) / 1e-3)) for v, a in zip(p, (xs, ys, zs)))
    for b in tree.branches:
        if b.generation >= 2:
            mid = 0.5 * (b.start + b.end)
            assert sd[idx(mid)] == pytest.approx(-15e-3, abs=1.6e-3)  # on the axis: reach inside (coarse grid)
    assert sd[idx([0.0, 0.0, -0.01])] > 0                              # the mediastinum is no lung
    assert sd[idx([0.075, 0.035, -0.115])] > 0                        # far from every branch


def test_rasterised_reference_tree_has_exact_ground_truth(tmp_path):
    tree = read_tree_table(_table(tmp_path, Y_TREE))
    params = PhantomParams(spacing_mm=(1.0, 1.0, 1.0), sdf_band_mm=3.0)
    ph = rasterise(tree, params, np.random.default_rng(0), lungs=hull_lungs(tree, params))
    m = np.asarray(ph.mask.data) > 0
    assert m.any() and (np.asarray(ph.sdf.data)[m] < 0).all()
    ct = np.asarray(ph.ct.data)
    assert ct[m].mean() < -800                           # air in the lumen
    assert (ct > -200).mean() > 0.2                       # soft tissue: the field of view lies inside the body
    # the field of view is the tree's box + margin: nothing of the body outline's air
    assert (ct < -990).mean() < 0.05
    again = rasterise(tree, params, np.random.default_rng(0), lungs=hull_lungs(tree, params))
    assert np.array_equal(np.asarray(again.ct.data), ct)  # same seed -> same bytes


def test_entry_needs_the_tables_sha256_and_a_known_frame():
    with pytest.raises(ConfigError, match="tree_sha256 is required"):
        PhantomEntry(seed=0, tree="t.csv")
    with pytest.raises(ConfigError, match="RAS or LPS"):
        PhantomEntry(seed=0, tree="t.csv", tree_frame="RSA", tree_sha256="0" * 64)


def test_stage_refuses_a_table_whose_bytes_changed(tmp_path):
    from room_pipeline.stages.phantom import _reference_tree

    path = _table(tmp_path, Y_TREE)
    good = hashlib.sha256(path.read_bytes()).hexdigest()
    tree, source = _reference_tree(PhantomEntry(seed=0, tree=str(path), tree_sha256=good))
    assert len(tree) == 7 and source["tree_sha256"] == good
    path.write_text(path.read_text().replace("7.0", "7.5"))
    with pytest.raises(InputError, match="differs from the config's tree_sha256") as exc:
        _reference_tree(PhantomEntry(seed=0, tree=str(path), tree_sha256=good))
    assert "\n" not in str(exc.value)


# --------------------------------------------------------------------------- the Schmidt reference tree

SCHMIDT = ("airway_trees", "schmidt2004", "TreeData.csv")


@pytest.mark.shared
def test_schmidt_table_reads_as_the_published_tree():
    path = shared_path(*SCHMIDT)
    tree = read_tree_table(path, "LPS")
    assert len(tree) == 3597 and tree.max_generation == 17      # Schmidt et al. 2004: 3597 branches, gen 0-17
    counts = {len(tree.children(b.id)) for b in tree.branches}
    assert counts == {0, 2}                                        # strictly bifurcating
    rad = np.array([b.radius for b in tree.branches]) * 1e3
    assert rad.min() == pytest.approx(0.28, abs=0.01) and rad.max() == pytest.approx(7.81, abs=0.01)
    mains = sorted(tree.children(0), key=lambda b: b.end[0])
    left, right = mains[0], mains[1]
    # in RAS+ the right main bronchus lies toward +x and is the shorter, wider, steeper one
    assert right.end[0] > 0 > left.end[0]
    assert right.length < left.length and right.radius > left.radius
    trachea = tree.branch(0)
    assert trachea.start[1] > 0 and trachea.start[2] > 0.1        # the trachea runs down and back to the carina
    cfg = (REPO / "conf" / "patients" / "reference_tree.yaml").read_text()
    assert hashlib.sha256(path.read_bytes()).hexdigest() in cfg     # the config pins these bytes


def test_config_error_names_the_phantom_before_any_work(tmp_path):
    from room_pipeline.config.compose import compose
    from room_pipeline.config.validate import validate_config

    cfg = compose(["patients=reference_tree", "~phantoms.schmidt2004.tree_sha256"], conf_dir=REPO / "conf")
    with pytest.raises(ConfigError, match=r"^phantoms\.schmidt2004: tree_sha256 is required") as exc:
        validate_config(cfg)
    assert "\n" not in str(exc.value)


def test_hull_lungs_on_the_coarse_grid_stay_near_the_full_resolution_transform(tmp_path, monkeypatch):
    import room_pipeline.anatomy.reference_tree as rt

    tree = read_tree_table(_table(tmp_path, Y_TREE))
    params = PhantomParams()
    xs, ys, zs = (np.arange(lo, hi, 0.7e-3) for lo, hi in ((-0.08, 0.08), (-0.04, 0.04), (-0.12, 0.02)))
    coarse = rt.hull_lungs(tree, params)(xs, ys, zs)
    monkeypatch.setattr(rt, "LUNG_STRIDE", 1)
    full = rt.hull_lungs(tree, params)(xs, ys, zs)
    edge = np.abs(full) < 2e-3
    assert edge.sum() > 1000
    # the axis points snap to the 1.4 mm grid: at most half its diagonal (1.21 mm) plus interpolation
    assert np.abs(coarse - full)[edge].max() < 1.6e-3
