"""Accuracy of an extracted centreline graph against a reference (e.g. the phantom's exact graph).

All functions take :class:`~room_pipeline.anatomy.centreline.CentrelineGraph`
objects (metres).  Polylines are densified to ``voxel / 10`` before distances
are taken, so figures do not depend on either graph's sampling step.

Definitions (see :func:`centreline_metrics`):

* **distance** extracted -> true centreline (every extracted point to the
  nearest point of the true polylines) and true -> extracted, mean / median /
  p95 in metres and voxels;
* a true branch is **detected** when at least ``coverage`` (0.8) of its length
  lies within ``radius_fraction`` (0.5) x its radius (at least one voxel) of the
  extracted centreline; rates for all branches, for branches at least
  ``min_radius_voxels`` (2) voxels in radius and per generation;
* an extracted branch is **spurious** when less than half of its length lies
  within ``radius_fraction`` x the local true radius (at least one voxel) of the
  true centreline;
* **bifurcation error**: each true bifurcation point (last point of a branch
  with two or more children) to the nearest extracted bifurcation node.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..anatomy.centreline import CentrelineGraph


def densify(graph: CentrelineGraph, step: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Points every <= ``step`` along every branch: (points, radius, branch id, segment length weight)."""
    P, R, B, W = [], [], [], []
    for b in graph.branches:
        p, r = b.points, b.radius
        for s in range(len(p) - 1):
            seg = float(np.linalg.norm(p[s + 1] - p[s]))
            n = max(1, int(np.ceil(seg / step)))
            t = (np.arange(n) + 0.5) / n
            P.append(p[s] + t[:, None] * (p[s + 1] - p[s]))
            R.append(r[s] + t * (r[s + 1] - r[s]))
            B.append(np.full(n, b.id))
            W.append(np.full(n, seg / n))
    if not P:
        return np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int64), np.zeros(0)
    return np.concatenate(P), np.concatenate(R), np.concatenate(B).astype(np.int64), np.concatenate(W)


def bifurcation_points(graph: CentrelineGraph) -> np.ndarray:
    """(K, 3) junction points: the distal end of every branch with >= 2 children."""
    pts = [b.points[-1] for b in graph.branches if len(graph.children(b.id)) >= 2]
    return np.array(pts).reshape(-1, 3)


def _stats(d: np.ndarray, w: np.ndarray, voxel: float, prefix: str) -> dict:
    if len(d) == 0:
        return {f"{prefix}_mean_m": float("nan"), f"{prefix}_median_m": float("nan"),
                f"{prefix}_p95_m": float("nan"), f"{prefix}_mean_vox": float("nan")}
    mean = float(np.average(d, weights=w))
    med, p95 = float(np.median(d)), float(np.percentile(d, 95))
    return {f"{prefix}_mean_m": mean, f"{prefix}_median_m": med, f"{prefix}_p95_m": p95,
            f"{prefix}_mean_vox": mean / voxel, f"{prefix}_median_vox": med / voxel, f"{prefix}_p95_vox": p95 / voxel}


def centreline_metrics(extracted: CentrelineGraph, truth: CentrelineGraph, voxel_size: float,
                       radius_fraction: float = 0.5, coverage: float = 0.8,
                       min_radius_voxels: float = 2.0) -> dict:
    """Distance, detection, spurious-branch and bifurcation figures (JSON-serialisable dict).

    Args:
        extracted, truth: centreline graphs in metres.
        voxel_size: metres per voxel, for the ``*_vox`` figures and the one-voxel tolerance floor.
    """
    step = voxel_size / 10.0
    Pe, Re, Be, We = densify(extracted, step)
    Pt, Rt, Bt, Wt = densify(truth, step)
    out: dict = {"voxel_size_m": voxel_size, "n_true_branches": len(truth.branches),
                 "n_extracted_branches": len(extracted.branches)}
    if len(Pe) == 0 or len(Pt) == 0:
        out.update({"detection_rate": 0.0, "detection_rate_large": 0.0, "spurious_fraction": float("nan")})
        return out
    kt, ke = cKDTree(Pt), cKDTree(Pe)
    d_et, i_et = kt.query(Pe)
    d_te, _ = ke.query(Pt)
    out.update(_stats(d_et, We, voxel_size, "dist_ext_to_true"))
    out.update(_stats(d_te, Wt, voxel_size, "dist_true_to_ext"))

    # detection of true branches
    tol_t = np.maximum(radius_fraction * Rt, voxel_size)
    hit_t = d_te <= tol_t
    gen = {b.id: b.generation for b in truth.branches}
    per_branch = []
    for b in truth.branches:
        m = Bt == b.id
        cov = float(np.sum(Wt[m] * hit_t[m]) / max(np.sum(Wt[m]), 1e-300))
        per_branch.append((b.id, b.generation, b.mean_radius, cov, cov >= coverage))
    det = np.array([p[4] for p in per_branch])
    large = np.array([p[2] >= min_radius_voxels * voxel_size for p in per_branch])
    out["detection_rate"] = float(det.mean())
    out["n_true_branches_large"] = int(large.sum())
    out["detection_rate_large"] = float(det[large].mean()) if large.any() else float("nan")
    out["missed_large_branch_ids"] = [int(p[0]) for p, L in zip(per_branch, large) if L and not p[4]]
    gens = sorted(set(gen.values()))
    out["detection_by_generation"] = {
        str(g): {"n": int(sum(p[1] == g for p in per_branch)),
                 "detected": int(sum(p[1] == g and p[4] for p in per_branch)),
                 "rate": float(np.mean([p[4] for p in per_branch if p[1] == g]))} for g in gens}

    # spurious extracted branches
    tol_e = np.maximum(radius_fraction * Rt[i_et], voxel_size)
    on = d_et <= tol_e
    spurious = []
    for b in extracted.branches:
        m = Be == b.id
        frac = float(np.sum(We[m] * on[m]) / max(np.sum(We[m]), 1e-300))
        if frac < 0.5:
            spurious.append(b.id)
    out["n_spurious"] = len(spurious)
    out["spurious_fraction"] = len(spurious) / max(len(extracted.branches), 1)
    out["spurious_branch_ids"] = spurious

    # bifurcations
    bt, be = bifurcation_points(truth), bifurcation_points(extracted)
    out["n_true_bifurcations"], out["n_extracted_bifurcations"] = len(bt), len(be)
    if len(bt) and len(be):
        db, _ = cKDTree(be).query(bt)
        out["bifurcation_error_median_m"] = float(np.median(db))
        out["bifurcation_error_mean_m"] = float(np.mean(db))
        out["bifurcation_error_p95_m"] = float(np.percentile(db, 95))
    else:
        out["bifurcation_error_median_m"] = float("nan")
    # the same among the true bifurcations that were found: the branch and two or more of its children
    # detected (where a tree is found only in part, the figure above mostly counts the misses)
    found = {p[0] for p in per_branch if p[4]}
    bt_found = np.array([b.points[-1] for b in truth.branches
                         if b.id in found and sum(c.id in found for c in truth.children(b.id)) >= 2]).reshape(-1, 3)
    out["n_true_bifurcations_detected"] = len(bt_found)
    if len(bt_found) and len(be):
        db, _ = cKDTree(be).query(bt_found)
        out["bifurcation_error_detected_median_m"] = float(np.median(db))
        out["bifurcation_error_detected_p95_m"] = float(np.percentile(db, 95))
    else:
        out["bifurcation_error_detected_median_m"] = float("nan")
    return out
