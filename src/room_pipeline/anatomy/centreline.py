"""Centreline graphs: the navigation tree of the airway (branches as polylines with radii).

A :class:`CentrelineGraph` is a rooted tree of :class:`GraphBranch` es.  Each
branch is a polyline ordered from its proximal end (the bifurcation it leaves,
or the trachea entry for the root) to its distal end (the next bifurcation or a
leaf), with the lumen radius at every point.  Consecutive branches share their
junction point: a child's first point equals its parent's last point.
Lengths and radii in metres, world frame RAS+ (see :mod:`room_pipeline.conventions`).

It is produced by the ``medial_axis`` stage from the lumen SDF and, for the
phantom, exactly from the :class:`~room_pipeline.anatomy.tree.AirwayTree`
(:func:`from_airway_tree`), so planning code can be tested on ground truth.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from .tree import AirwayTree


@dataclasses.dataclass
class GraphBranch:
    """One branch: ``points`` (K, 3) metres from proximal to distal, ``radius`` (K,) metres."""

    id: int
    parent: int
    generation: int
    points: np.ndarray
    radius: np.ndarray

    def __post_init__(self) -> None:
        self.points = np.asarray(self.points, dtype=np.float64).reshape(-1, 3)
        self.radius = np.asarray(self.radius, dtype=np.float64).reshape(-1)
        if len(self.points) != len(self.radius):
            raise ValueError(f"branch {self.id}: {len(self.points)} points but {len(self.radius)} radii")
        if len(self.points) < 2:
            raise ValueError(f"branch {self.id}: a branch needs at least 2 points")

    @property
    def length(self) -> float:
        return float(np.linalg.norm(np.diff(self.points, axis=0), axis=1).sum())

    @property
    def mean_radius(self) -> float:
        """Length-weighted mean radius, metres."""
        seg = np.linalg.norm(np.diff(self.points, axis=0), axis=1)
        if seg.sum() == 0:
            return float(self.radius.mean())
        mid = 0.5 * (self.radius[1:] + self.radius[:-1])
        return float((mid * seg).sum() / seg.sum())


@dataclasses.dataclass
class CentrelineGraph:
    """Rooted tree of branches; ``branches[i].parent == -1`` only for the root (the trachea)."""

    branches: list[GraphBranch]

    def __post_init__(self) -> None:
        self._by_id = {b.id: b for b in self.branches}
        roots = [b.id for b in self.branches if b.parent == -1]
        if len(self.branches) and len(roots) != 1:
            raise ValueError(f"a centreline graph needs exactly one root, found {len(roots)}")

    @property
    def root(self) -> GraphBranch:
        return next(b for b in self.branches if b.parent == -1)

    def branch(self, bid: int) -> GraphBranch:
        return self._by_id[bid]

    def children(self, bid: int) -> list[GraphBranch]:
        return [b for b in self.branches if b.parent == bid]

    def leaves(self) -> list[GraphBranch]:
        parents = {b.parent for b in self.branches}
        return [b for b in self.branches if b.id not in parents]

    def path_to(self, bid: int) -> list[GraphBranch]:
        """Branches from the root down to ``bid`` (inclusive)."""
        out = [self.branch(bid)]
        while out[-1].parent != -1:
            out.append(self.branch(out[-1].parent))
        return out[::-1]

    def all_points(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Concatenated (points, radius, branch id) of every branch."""
        if not self.branches:
            return np.zeros((0, 3)), np.zeros(0), np.zeros(0, dtype=np.int64)
        return (np.concatenate([b.points for b in self.branches]),
                np.concatenate([b.radius for b in self.branches]),
                np.concatenate([np.full(len(b.points), b.id, dtype=np.int64) for b in self.branches]))

    def to_dict(self) -> dict:
        return {"units": "m", "frame": "RAS+",
                "convention": "polylines ordered proximal -> distal; a child's first point is its parent's last",
                "branches": [{"id": b.id, "parent": b.parent, "generation": b.generation,
                              "children": [c.id for c in self.children(b.id)],
                              "length": b.length, "mean_radius": b.mean_radius,
                              "points": np.round(b.points, 9).tolist(),
                              "radius": np.round(b.radius, 9).tolist()} for b in self.branches]}

    @staticmethod
    def from_dict(d: dict) -> "CentrelineGraph":
        return CentrelineGraph([GraphBranch(int(b["id"]), int(b["parent"]), int(b["generation"]),
                                            np.asarray(b["points"]), np.asarray(b["radius"]))
                                for b in d["branches"]])


def from_airway_tree(tree: AirwayTree, step: float) -> CentrelineGraph:
    """The exact centreline graph of a capsule tree, sampled every <= ``step`` metres.

    The root starts at the trachea's free (superior) end.  A capsule whose
    parent has no other child continues that airway (a kink, not a
    bifurcation), so chains of such capsules become one graph branch; graph
    nodes are bifurcations and leaves only, and a branch's generation counts
    the bifurcations above it.  Radii are those of the capsules.
    """
    n_children = {b.id: 0 for b in tree.branches}
    for b in tree.branches:
        if b.parent != -1:
            n_children[b.parent] += 1

    def samples(b) -> tuple[np.ndarray, np.ndarray]:
        n = max(1, int(np.ceil(b.length / step)))
        t = np.linspace(0.0, 1.0, n + 1)
        return b.start + t[:, None] * (b.end - b.start), np.full(n + 1, b.radius)

    out: list[GraphBranch] = []
    # (capsule id starting a graph branch, graph parent id, generation)
    stack = [(tree.branches[0].id if tree.branches[0].parent == -1 else
              next(b.id for b in tree.branches if b.parent == -1), -1, 0)]
    while stack:
        first, gparent, gen = stack.pop()
        pts, rad = samples(tree.branch(first))
        cur = first
        while n_children[cur] == 1:  # continuation: append the lone child
            cur = tree.children(cur)[0].id
            p2, r2 = samples(tree.branch(cur))
            pts, rad = np.vstack([pts, p2[1:]]), np.concatenate([rad, r2[1:]])
        out.append(GraphBranch(first, gparent, gen, pts, rad))
        for c in reversed(tree.children(cur)):
            stack.append((c.id, first, gen + 1))
    out.sort(key=lambda b: b.id)
    return CentrelineGraph(out)
