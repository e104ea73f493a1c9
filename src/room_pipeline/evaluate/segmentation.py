"""Airway segmentation accuracy: overlap scores and the ATM'22 tree metrics.

* :func:`dice`, :func:`precision`, :func:`recall` compare two binary masks on
  the same grid (voxels > 0 are foreground).
* :func:`tree_metrics` follows the EXACT'09 / ATM'22 definitions on an
  analytic centreline: tree length detected (TD) is the length-weighted share
  of the ground-truth centreline covered by the prediction; branches detected
  (BD) is the share of ground-truth branches with at least
  ``branch_threshold`` (80 %) of their centreline length covered.  A
  centreline point is covered when the voxel containing it (nearest voxel
  centre, :meth:`Volume.world_to_index`) is foreground in the prediction;
  points outside the grid are not covered.  Unlike the ATM'22 scripts the
  prediction is used as given (no largest-component extraction).
* :func:`segmentation_metrics` bundles all of them, with TD/BD per generation.

All results are plain floats/ints/dicts (JSON-serialisable).
"""
from __future__ import annotations

from typing import Mapping

import numpy as np

from ..errors import InputError
from ..io.volume import Volume

#: a branch counts as detected when this share of its centreline length is covered
BRANCH_DETECTED_FRACTION = 0.8


def _binary(v: Volume | np.ndarray) -> np.ndarray:
    data = np.asarray(v.data if isinstance(v, Volume) else v)
    return data > 0


def _pair(pred: Volume | np.ndarray, gt: Volume | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    p, g = _binary(pred), _binary(gt)
    if p.shape != g.shape:
        raise InputError(f"prediction shape {p.shape} differs from ground-truth shape {g.shape}")
    if isinstance(pred, Volume) and isinstance(gt, Volume) and not np.allclose(pred.affine, gt.affine, atol=1e-9):
        raise InputError("prediction and ground truth are on different grids (affines differ)")
    return p, g


def dice(pred: Volume | np.ndarray, gt: Volume | np.ndarray) -> float:
    """2|P and G| / (|P| + |G|); 1.0 when both are empty."""
    p, g = _pair(pred, gt)
    den = int(np.count_nonzero(p)) + int(np.count_nonzero(g))
    return 1.0 if den == 0 else 2.0 * int(np.count_nonzero(p & g)) / den


def precision(pred: Volume | np.ndarray, gt: Volume | np.ndarray) -> float:
    """|P and G| / |P|; for an empty prediction 1.0 if the truth is empty too, else 0.0."""
    p, g = _pair(pred, gt)
    n = int(np.count_nonzero(p))
    if n == 0:
        return 1.0 if not g.any() else 0.0
    return int(np.count_nonzero(p & g)) / n


def recall(pred: Volume | np.ndarray, gt: Volume | np.ndarray) -> float:
    """|P and G| / |G| (sensitivity); for an empty truth 1.0 if the prediction is empty too, else 0.0."""
    p, g = _pair(pred, gt)
    n = int(np.count_nonzero(g))
    if n == 0:
        return 1.0 if not p.any() else 0.0
    return int(np.count_nonzero(p & g)) / n


def covered_points(pred_mask: Volume, points: np.ndarray) -> np.ndarray:
    """Boolean (N,): the voxel containing each world point (metres) is foreground."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    idx = np.rint(pred_mask.world_to_index(pts)).astype(np.int64)
    shape = np.array(pred_mask.shape)
    inside = np.all((idx >= 0) & (idx < shape), axis=1)
    out = np.zeros(len(pts), dtype=bool)
    if inside.any():
        i = idx[inside]
        out[inside] = np.asarray(pred_mask.data)[i[:, 0], i[:, 1], i[:, 2]] > 0
    return out


def _point_weights(centreline: Mapping[str, np.ndarray],
                   branch_lengths: Mapping[int, float] | None) -> np.ndarray:
    """Centreline length (metres) each point stands for.

    With ``branch_lengths`` a branch's length is shared equally by its
    points; otherwise each point weighs the branch's sampling step (median
    arclength gap; branches with a single point take the overall median step).
    """
    bid = np.asarray(centreline["branch"])
    arc = np.asarray(centreline["arclength"], dtype=np.float64)
    w = np.zeros(len(bid))
    steps: dict[int, float] = {}
    for b in np.unique(bid):
        sel = bid == b
        if branch_lengths is not None and int(b) in branch_lengths:
            w[sel] = branch_lengths[int(b)] / np.count_nonzero(sel)
            continue
        gaps = np.diff(np.sort(arc[sel]))
        gaps = gaps[gaps > 0]
        if len(gaps):
            steps[int(b)] = float(np.median(gaps))
            w[sel] = steps[int(b)]
        else:
            w[sel] = np.nan
    if np.isnan(w).any():
        w[np.isnan(w)] = float(np.median(list(steps.values()))) if steps else 1.0
    return w


#: lumen radius bins (mm) of the per-radius TD / BD (``tree_metrics``: ``per_radius_mm``)
RADIUS_BINS_MM = (0.0, 0.5, 0.75, 1.0, 1.25, 1.5, 2.0, 3.0, 5.0, 100.0)


def tree_metrics(pred_mask: Volume, centreline: Mapping[str, np.ndarray],
                 branch_lengths: Mapping[int, float] | None = None,
                 branch_threshold: float = BRANCH_DETECTED_FRACTION) -> dict:
    """ATM'22 tree length detected (TD) and branches detected (BD), overall and per generation.

    Args:
        pred_mask: predicted airway mask (foreground > 0).
        centreline: as returned by :meth:`AirwayTree.centreline` (``points`` in
            metres, ``branch``, ``generation``, ``arclength``).
        branch_lengths: optional exact branch lengths (metres) by branch id, for weighting.
        branch_threshold: covered share of a branch's length for it to count as detected.

    Returns:
        ``tree_length_detected``, ``branches_detected`` (shares in [0, 1]),
        ``n_branches``, ``n_branches_detected``, ``centreline_length_m``,
        ``per_generation`` (generation as a string -> the same keys) and, when the centreline has ``radius``
        (metres), ``per_radius_mm`` (a branch's median lumen radius in :data:`RADIUS_BINS_MM`, as
        ``"lo-hi"`` -> the same keys; empty bins left out).
    """
    pts = np.asarray(centreline["points"], dtype=np.float64).reshape(-1, 3)
    bid = np.asarray(centreline["branch"]).astype(np.int64)
    gen = np.asarray(centreline["generation"]).astype(np.int64)
    if len(pts) == 0:
        raise InputError("centreline has no points")
    cov = covered_points(pred_mask, pts)
    w = _point_weights(centreline, branch_lengths)

    ids = np.unique(bid)
    frac = {int(b): float(w[(bid == b) & cov].sum() / w[bid == b].sum()) for b in ids}
    bgen = {int(b): int(gen[bid == b][0]) for b in ids}

    def summary(sel_pts: np.ndarray, sel_branches: list[int]) -> dict:
        det = [b for b in sel_branches if frac[b] >= branch_threshold - 1e-12]
        total = float(w[sel_pts].sum())
        return {"tree_length_detected": float(w[sel_pts & cov].sum() / total) if total > 0 else 0.0,
                "branches_detected": len(det) / len(sel_branches) if sel_branches else 0.0,
                "n_branches": len(sel_branches), "n_branches_detected": len(det),
                "centreline_length_m": total}

    out = summary(np.ones(len(pts), dtype=bool), [int(b) for b in ids])
    out["per_generation"] = {str(g): summary(gen == g, [b for b in frac if bgen[b] == g])
                             for g in sorted(set(bgen.values()))}
    if "radius" in centreline:
        # by lumen radius: what a method reaches does not depend on the generation's number (a measured tree's
        # generation 5 is as thin as a grown phantom's generation 8), and the ATM'22 figures hide it
        rad = np.asarray(centreline["radius"], dtype=np.float64)
        brad = {int(b): float(np.median(rad[bid == b])) for b in ids}
        out["per_radius_mm"] = {}
        for lo, hi in zip(RADIUS_BINS_MM[:-1], RADIUS_BINS_MM[1:]):
            sel = [b for b in frac if lo * 1e-3 <= brad[b] < hi * 1e-3]
            if sel:
                out["per_radius_mm"][f"{lo:g}-{hi:g}"] = summary(np.isin(bid, sel), sel)
    out["branch_coverage"] = {str(b): frac[b] for b in sorted(frac)}
    return out


def segmentation_metrics(pred: Volume, gt: Volume, tree=None, step: float | None = None) -> dict:
    """Dice, precision, recall and voxel counts; with an :class:`AirwayTree` also TD/BD.

    ``step`` is the centreline sampling (metres), default half the smallest voxel size.
    Returns a JSON-serialisable dict; tree metrics keys as in :func:`tree_metrics`.
    """
    p, g = _pair(pred, gt)
    out: dict = {"dice": dice(p, g), "precision": precision(p, g), "recall": recall(p, g),
                 "voxels_pred": int(np.count_nonzero(p)), "voxels_gt": int(np.count_nonzero(g)),
                 "voxels_true_positive": int(np.count_nonzero(p & g))}
    if tree is not None:
        step = float(step) if step else 0.5 * float(np.min(pred.spacing))
        cl = tree.centreline(step)
        out.update(tree_metrics(pred, cl, {b.id: b.length for b in tree.branches}))
    return out
