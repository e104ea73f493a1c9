"""Segmentation metrics (room_pipeline.evaluate.segmentation) on hand-built cases with known answers."""
from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis.extra.numpy import arrays

from room_pipeline.anatomy.tree import AirwayTree, Branch
from room_pipeline.errors import InputError
from room_pipeline.evaluate.segmentation import (covered_points, dice, precision, recall,
                                                 segmentation_metrics, tree_metrics)
from room_pipeline.io.volume import Volume

MM = 1e-3


def _vol(data) -> Volume:
    return Volume(np.asarray(data), np.diag([MM, MM, MM, 1.0]))


def test_overlap_known_values():
    gt = np.zeros((4, 4, 4), dtype=np.uint8)
    pred = np.zeros_like(gt)
    gt.flat[:6] = 1      # 6 truth voxels
    pred.flat[3:7] = 1   # 4 predicted, 3 of them true
    assert dice(_vol(pred), _vol(gt)) == pytest.approx(0.6)
    assert precision(_vol(pred), _vol(gt)) == pytest.approx(0.75)
    assert recall(_vol(pred), _vol(gt)) == pytest.approx(0.5)
    assert dice(pred * 7, gt) == pytest.approx(0.6)  # any value > 0 is foreground


def test_overlap_empty_conventions():
    z = np.zeros((3, 3, 3), dtype=np.uint8)
    o = np.ones_like(z)
    assert dice(z, z) == 1.0 and precision(z, z) == 1.0 and recall(z, z) == 1.0
    assert dice(z, o) == 0.0 and precision(z, o) == 0.0 and recall(z, o) == 0.0
    assert precision(o, z) == 0.0 and recall(o, z) == 0.0


def test_grid_mismatch_raises():
    with pytest.raises(InputError, match="shape"):
        dice(np.zeros((2, 2, 2)), np.zeros((2, 2, 3)))
    a = _vol(np.zeros((2, 2, 2)))
    b = Volume(np.zeros((2, 2, 2)), np.diag([2 * MM, MM, MM, 1.0]))
    with pytest.raises(InputError, match="grid"):
        dice(a, b)


@settings(max_examples=30, deadline=None)
@given(p=arrays(np.bool_, (3, 4, 5)), g=arrays(np.bool_, (3, 4, 5)))
def test_dice_is_harmonic_mean_of_precision_and_recall(p, g):
    d, pr, rc = dice(p, g), precision(p, g), recall(p, g)
    assert 0.0 <= d <= 1.0 and d == pytest.approx(dice(g, p))
    if p.any() and g.any():
        assert d == pytest.approx(0.0 if pr + rc == 0 else 2 * pr * rc / (pr + rc))


# --------------------------------------------------------------------------- tree metrics
def _t_tree() -> AirwayTree:
    """Trachea 40 mm along -z to the origin, two 20 mm children along +x and -x (grid-aligned axes)."""
    P = lambda *v: np.array(v, dtype=float) * MM  # noqa: E731
    return AirwayTree([Branch(0, -1, 0, P(0, 0, 40), P(0, 0, 0), 4 * MM),
                       Branch(1, 0, 1, P(0, 0, 0), P(20, 0, 0), 3 * MM),
                       Branch(2, 0, 1, P(0, 0, 0), P(-20, 0, 0), 3 * MM)])


def _grid_with(pred_fn) -> Volume:
    """1 mm grid, voxel centres at integer mm from (-30, -5, -5) to (30, 5, 45); pred_fn(x, y, z) -> bool."""
    aff = np.diag([MM, MM, MM, 1.0])
    aff[:3, 3] = np.array([-30, -5, -5]) * MM
    x, y, z = np.meshgrid(np.arange(-30, 31), np.arange(-5, 6), np.arange(-5, 46), indexing="ij")
    return Volume(pred_fn(x, y, z).astype(np.uint8), aff)


def test_tree_metrics_known_answer():
    tree = _t_tree()
    # trachea fully covered; child 1 covered for x <= 17 (points with x < 17.5, i.e. 87.5 %);
    # child 2 covered for x >= -10 (points with x > -10.5, i.e. 52.5 %)
    pred = _grid_with(lambda x, y, z: (y == 0) & (((x == 0) & (z >= 0)) | ((z == 0) & (x <= 17) & (x >= -10))))
    cl = tree.centreline(0.3 * MM)  # no sample lands on a voxel boundary (half-integer mm)
    m = tree_metrics(pred, cl, {b.id: b.length for b in tree.branches})
    assert m["branch_coverage"]["0"] == 1.0
    assert m["branch_coverage"]["1"] == pytest.approx(0.875, abs=0.02)
    assert m["branch_coverage"]["2"] == pytest.approx(0.525, abs=0.02)
    assert m["branches_detected"] == pytest.approx(2 / 3)
    assert m["n_branches"] == 3 and m["n_branches_detected"] == 2
    assert m["tree_length_detected"] == pytest.approx((40 + 17.5 + 10.5) / 80, abs=0.01)
    assert m["centreline_length_m"] == pytest.approx(0.08)
    g = m["per_generation"]
    assert g["0"]["tree_length_detected"] == 1.0 and g["0"]["branches_detected"] == 1.0
    assert g["1"]["tree_length_detected"] == pytest.approx(28 / 40, abs=0.02)
    assert g["1"]["branches_detected"] == 0.5
    # by lumen radius: the trachea (4 mm) alone in 3-5 mm, both children (3 mm) in 3-5 mm too; 2-3 mm empty
    r = m["per_radius_mm"]
    assert set(r) == {"3-5"} and r["3-5"]["n_branches"] == 3 and r["3-5"]["n_branches_detected"] == 2
    thin = tree.centreline(0.3 * MM)
    thin["radius"] = np.where(thin["branch"] == 2, 0.9 * MM, thin["radius"])     # child 2 as a 0.9 mm airway
    rt = tree_metrics(pred, thin, {b.id: b.length for b in tree.branches})["per_radius_mm"]
    assert rt["0.75-1"]["n_branches"] == 1 and rt["0.75-1"]["branches_detected"] == 0.0
    assert rt["3-5"]["branches_detected"] == 1.0
    # without branch lengths the weights come from the arclength steps: same answer
    m2 = tree_metrics(pred, cl)
    assert m2["tree_length_detected"] == pytest.approx(m["tree_length_detected"], abs=0.01)
    assert m2["branches_detected"] == m["branches_detected"]
    json.dumps(m)


def test_tree_metrics_extremes_and_outside_points():
    tree = _t_tree()
    cl = tree.centreline(0.5 * MM)
    full = _grid_with(lambda x, y, z: np.ones_like(x, dtype=bool))
    none = _grid_with(lambda x, y, z: np.zeros_like(x, dtype=bool))
    assert tree_metrics(full, cl)["tree_length_detected"] == 1.0
    assert tree_metrics(full, cl)["branches_detected"] == 1.0
    assert tree_metrics(none, cl)["tree_length_detected"] == 0.0
    # points beyond the grid are never covered
    far = np.array([[0.0, 0.0, 1.0]])
    assert not covered_points(full, far).any()
    assert covered_points(full, np.array([[0.0, 0.0, 0.0004]])).all()


def _inside(tree: AirwayTree, p: np.ndarray) -> np.ndarray:
    """Points within some capsule (min_i of the capsule signed distances < 0)."""
    d = np.full(len(p), np.inf)
    for b in tree.branches:
        ab = b.end - b.start
        t = np.clip((p - b.start) @ ab / (ab @ ab), 0, 1)
        d = np.minimum(d, np.linalg.norm(p - b.start - t[:, None] * ab, axis=1) - b.radius)
    return d < 0


def test_segmentation_metrics_bundle():
    tree = _t_tree()
    gt = _grid_with(lambda x, y, z: _inside(tree, np.stack([x, y, z], -1).reshape(-1, 3) * MM).reshape(x.shape))
    m = segmentation_metrics(gt, gt, tree)
    assert m["dice"] == 1.0 and m["precision"] == 1.0 and m["recall"] == 1.0
    assert m["tree_length_detected"] == 1.0 and m["branches_detected"] == 1.0
    assert set(m["per_generation"]) == {"0", "1"}
    half = gt.with_data(gt.data * (np.arange(gt.shape[0]) <= 30)[:, None, None])  # drop child 1 (x > 0)
    m = segmentation_metrics(half, gt, tree)
    assert m["precision"] == 1.0 and m["recall"] < 1.0
    assert m["branches_detected"] == pytest.approx(2 / 3)
    assert m["per_generation"]["1"]["branches_detected"] == 0.5
    json.dumps(m)
    assert "tree_length_detected" not in segmentation_metrics(gt, gt)
