"""Targets of the camera paths (step 1 of :func:`~room_pipeline.planning.trajectory.plan_path`): branch ids
or points (Med-MPD ``target.txt``, config), mapped to the centreline, and the per-sequence target choice."""
from __future__ import annotations

import dataclasses
import math
import os
from pathlib import Path

import numpy as np

from ..anatomy.centreline import CentrelineGraph
from ..conventions import MM
from ..errors import ConfigError, InputError
from .trajectory_params import TrajectoryParams


def read_target_file(path: str | os.PathLike) -> np.ndarray:
    """Target points of a Med-MPD ``target.txt`` -> (N, 3) metres, world RAS+.

    The file holds whitespace-separated numbers, a multiple of three (one
    number per line in Med-MPD): x y z in **millimetres** in the NIfTI world
    (scanner RAS+) frame of the patient's ``bronchialTree.nii.gz``, i.e. our
    world frame up to the unit.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"target file not found: {path}")
    try:
        vals = np.array(path.read_text().split(), dtype=np.float64)
    except ValueError as exc:
        raise InputError(f"{path}: target file must hold numbers (x y z in mm): {exc}") from exc
    if vals.size == 0 or vals.size % 3 or not np.all(np.isfinite(vals)):
        raise InputError(f"{path}: expected finite x y z triples in mm, got {vals.size} numbers")
    return vals.reshape(-1, 3) * MM


def _points_from_config(points) -> np.ndarray:
    if isinstance(points, (str, os.PathLike)):
        return read_target_file(points)
    if isinstance(points, (list, tuple)) and points and all(isinstance(p, (str, os.PathLike)) for p in points):
        return np.concatenate([read_target_file(p) for p in points])
    try:
        arr = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError):
        raise ConfigError(f"trajectory.points must be [[x, y, z], ...] in metres or a file path, got {points!r}") from None
    if arr.ndim == 1 and arr.size == 3:
        arr = arr[None]
    if arr.ndim != 2 or arr.shape[1] != 3 or len(arr) == 0 or not np.all(np.isfinite(arr)):
        raise ConfigError(f"trajectory.points must be [[x, y, z], ...] in metres, got shape {arr.shape}")
    return arr


@dataclasses.dataclass
class TargetInfo:
    """Where a trajectory goes.

    Attributes:
        kind: 'branch' (a branch's last point) or 'point'.
        branch_id: graph branch the path ends in.
        point: end of the path (a centreline point), metres.
        requested: the requested target point (metres) or the branch end for 'branch'.
        distance: requested point to the centreline point it maps to, metres.
        reached: False when ``unreachable: nearest`` replaced the target by the nearest reachable one.
        note: why, when not reached.
        stop_distance: straight-line distance from the last camera position to ``requested``, metres.
        stop_reason: 'reached' | 'target_outside_lumen' (a point target off the airways: the route ends at the
            airway point nearest it) | 'lumen_narrower_than_scope' (min_lumen_radius_mm) | 'curvature_limit'
            (kappa_max) | 'clearance' (the wall margin cannot be kept); the first cause met along the route.
    """

    kind: str
    branch_id: int
    point: np.ndarray
    requested: np.ndarray
    distance: float = 0.0
    reached: bool = True
    note: str = ""
    stop_distance: float = 0.0
    stop_reason: str = "reached"

    def to_dict(self) -> dict:
        return {"kind": self.kind, "branch_id": int(self.branch_id),
                "point": np.round(self.point, 9).tolist(), "requested": np.round(self.requested, 9).tolist(),
                "distance": float(self.distance), "reached": bool(self.reached), "note": self.note,
                "stop_distance": float(self.stop_distance), "stop_reason": self.stop_reason}


def _graph_segments(graph: CentrelineGraph):
    """All centreline segments: A, B (S,3), rA, rB (S,), branch (S,), arclength of A within its branch."""
    A, B, rA, rB, bid, s0 = [], [], [], [], [], []
    for b in graph.branches:
        seg = np.linalg.norm(np.diff(b.points, axis=0), axis=1)
        A.append(b.points[:-1]); B.append(b.points[1:])
        rA.append(b.radius[:-1]); rB.append(b.radius[1:])
        bid.append(np.full(len(seg), b.id)); s0.append(np.concatenate([[0.0], np.cumsum(seg)[:-1]]))
    return (np.concatenate(A), np.concatenate(B), np.concatenate(rA), np.concatenate(rB),
            np.concatenate(bid), np.concatenate(s0))


def subtree(graph: CentrelineGraph, bid: int) -> set[int]:
    """Ids of branch ``bid`` and every branch below it."""
    out, stack = set(), [int(bid)]
    while stack:
        b = stack.pop()
        out.add(b)
        stack.extend(c.id for c in graph.children(b))
    return out


def map_target_point(graph: CentrelineGraph, point, tolerance: float, nearest: bool = False,
                     within: tuple[int, float] | None = None) -> tuple[int, float, np.ndarray, float]:
    """Map a target point (metres) to a centreline point: ``(branch id, arclength in branch, point, distance)``.

    The chosen centreline point is the nearest one whose lumen (radius ``r``)
    contains the target within ``tolerance`` (``|p - c| <= r + tolerance``).
    If there is none: :class:`InputError`, or with ``nearest`` the centreline
    point whose lumen surface is nearest (min ``|p - c| - r``).  ``within``:
    ``(branch id, arclength)`` of a centreline point: only the airways below it
    (that branch from there on and every branch below it) are considered: where
    a scope that has reached that point can go on to.
    """
    p = np.asarray(point, dtype=np.float64).reshape(3)
    A, B, rA, rB, bid, s0 = _graph_segments(graph)
    if within is not None:
        keep = np.isin(bid, list(subtree(graph, within[0])))
        seg_len = np.linalg.norm(B - A, axis=1)
        keep &= (bid != within[0]) | (s0 + seg_len > within[1])
        A, B, rA, rB, bid, s0 = A[keep], B[keep], rA[keep], rB[keep], bid[keep], s0[keep]
    ab = B - A
    L2 = np.einsum("ij,ij->i", ab, ab)
    t = np.clip(np.einsum("ij,ij->i", p - A, ab) / np.maximum(L2, 1e-300), 0.0, 1.0)
    c = A + t[:, None] * ab
    d = np.linalg.norm(p - c, axis=1)
    r = rA + t * (rB - rA)
    inside = d <= r + tolerance
    if inside.any():
        k = int(np.flatnonzero(inside)[np.argmin(d[inside])])
    else:
        k = int(np.argmin(d - r))
        if not nearest:
            raise InputError(
                f"target ({', '.join(f'{v / MM:.1f}' for v in p)}) mm is outside the airway tree: "
                f"{(d[k] - r[k]) / MM:.1f} mm beyond the lumen of branch {int(bid[k])} "
                f"(tolerance {tolerance / MM:.1f} mm; use unreachable: nearest to go to the nearest airway)")
    return int(bid[k]), float(s0[k] + t[k] * math.sqrt(L2[k])), c[k], float(d[k])


def select_targets(graph: CentrelineGraph, params: TrajectoryParams, below: int | None = None) -> list:
    """The configured targets: branch ids (leaves, random_leaves) or (3,) points in metres (points).

    ``below``: a branch id (a user start pose's): leaves are drawn only from the branches below it, the ones
    a route from that start can reach (every leaf below it when the start lies deeper than ``max_generation``)."""
    if params.targets == "points":
        return list(_points_from_config(params.points))
    g = params.max_generation
    allowed = subtree(graph, below) if below is not None else None
    pool = [b.id for b in graph.branches
            if (g is None or b.generation <= g) and (not graph.children(b.id) or b.generation == g)
            and (allowed is None or b.id in allowed)]
    if not pool and allowed is not None:
        # the start lies deeper than max_generation: the leaves below it, whatever their generation
        pool = [b.id for b in graph.branches if b.id in allowed and not graph.children(b.id)]
    if not pool:
        raise ConfigError(f"trajectory: no leaves up to generation {g}"
                          + (f" below branch {below} (the start pose's)" if below is not None else ""))
    if params.targets == "leaves":
        return pool
    rng = np.random.default_rng(params.seed)
    return [int(i) for i in rng.choice(pool, size=min(params.n, len(pool)), replace=False)]
