"""The airway tree as the navigation sees it (no physics imports): targets, localisation, the operator's words.

``Airways``: the centreline graph (:class:`~room_pipeline.anatomy.centreline.CentrelineGraph`, world RAS+
metres) with nearest-point localisation (branch id, arclength into it).  ``generation_targets``: the branches
of a generation whose route is wide enough for the scope.  ``operator_command``: while the tip is in a branch
ending in a bifurcation on the route, the word an operator watching the screen says ("left", "right", "up",
"down": the image direction from the wrong child's opening to the right one, from the graph and the true
pose).  ``start_pose``: the episode's start in the trachea.
"""
from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial import cKDTree

from ..anatomy.centreline import CentrelineGraph
from ..errors import InputError
from ..io.mesh import Mesh
from ..render.camera import CameraIntrinsics, look_at

MM = 1e-3
COMMANDS = {"left": (-1.0, 0.0), "right": (1.0, 0.0), "up": (0.0, -1.0), "down": (0.0, 1.0)}


@dataclasses.dataclass
class Patient:
    """What an episode needs of one patient: render mesh (true lumen), collision mesh, centreline graph."""

    name: str
    mesh: Mesh
    collision: Mesh
    graph: CentrelineGraph


class Airways:
    """The centreline graph with nearest-point localisation (world metres)."""

    def __init__(self, graph: CentrelineGraph) -> None:
        self.graph = graph
        pts, rad, bid = [], [], []
        self.cum: dict[int, np.ndarray] = {}
        for b in graph.branches:
            seg = np.linalg.norm(np.diff(b.points, axis=0), axis=1)
            self.cum[b.id] = np.concatenate([[0.0], np.cumsum(seg)])
            pts.append(b.points)
            bid.append(np.full(len(b.points), b.id))
            rad.append(np.arange(len(b.points)))
        self.points = np.concatenate(pts)
        self.branch_of = np.concatenate(bid)
        self.index_of = np.concatenate(rad)
        self.tree = cKDTree(self.points)

    def locate(self, p: np.ndarray) -> tuple[int, float]:
        """(branch id, arclength into it in m) of the centreline point nearest to ``p``."""
        _, i = self.tree.query(p)
        b = int(self.branch_of[i])
        return b, float(self.cum[b][self.index_of[i]])

    def distance(self, p: np.ndarray) -> float:
        """Distance (m) from ``p`` to the nearest centreline point of any branch."""
        return float(self.tree.query(p)[0])

    def route(self, target: int) -> list[int]:
        return [b.id for b in self.graph.path_to(target)]

    def route_polyline(self, target: int) -> tuple[np.ndarray, np.ndarray]:
        """Concatenated centreline points root -> target (duplicates at the joints removed) and arclength."""
        P = [self.graph.root.points]
        for b in self.graph.path_to(target)[1:]:
            P.append(b.points[1:] if np.allclose(b.points[0], P[-1][-1]) else b.points)
        P = np.concatenate(P)
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(P, axis=0), axis=1))])
        return P, s


def generation_targets(graph: CentrelineGraph, generation: int, min_radius_mm: float) -> list[int]:
    """Branches of ``generation`` whose route (every branch on it) has a mean radius >= ``min_radius_mm``."""
    out = []
    for b in graph.branches:
        if b.generation != generation:
            continue
        if all(x.mean_radius * 1e3 >= min_radius_mm for x in graph.path_to(b.id)):
            out.append(b.id)
    return sorted(out)


def draw_targets(graph: CentrelineGraph, generation: int, min_radius_mm: float, n: int, seed: int
                 ) -> tuple[list[int], list[int]]:
    """(eligible, drawn): the :func:`generation_targets` and ``n`` of them drawn without replacement by a
    ``numpy.random.default_rng(seed)`` (sorted; all of them when fewer are eligible): the navigation
    benchmark's targets (``navigate.benchmark``)."""
    elig = generation_targets(graph, generation, min_radius_mm)
    rng = np.random.default_rng(seed)
    pick = sorted(rng.choice(elig, size=min(n, len(elig)), replace=False).tolist()) if elig else []
    return elig, pick


def check_target(graph: CentrelineGraph, target: int) -> None:
    ids = {b.id for b in graph.branches}
    if target not in ids:
        raise InputError(f"navigation target branch {target} is not in the centreline graph "
                         f"(branches 0..{max(ids)}; {len(ids)} in all)")
    if graph.branch(target).parent == -1:
        raise InputError(f"navigation target branch {target} is the trachea (the start), not a target")


def start_pose(graph: CentrelineGraph, offset_m: float) -> np.ndarray:
    """Camera-to-world pose ``offset_m`` down the root branch (clipped to 80 % of it), looking along it,
    image up = anterior (+y, RAS+), as the trajectory stage's default."""
    root = graph.root
    seg = np.linalg.norm(np.diff(root.points, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    off = min(offset_m, 0.8 * s[-1])
    i = int(np.clip(np.searchsorted(s, off) - 1, 0, len(s) - 2))
    w = (off - s[i]) / max(s[i + 1] - s[i], 1e-12)
    eye = (1 - w) * root.points[i] + w * root.points[i + 1]
    j = min(len(s) - 1, int(np.searchsorted(s, off + 5 * MM)))
    fwd = root.points[j] - eye
    return look_at(eye, fwd, down=(0.0, -1.0, 0.0))


def operator_command(airways: Airways, target: int, branch: int, pose: np.ndarray,
                     camera: CameraIntrinsics) -> str | None:
    """The word an operator says while the tip is in ``branch``: which child opening to take, or None."""
    route = airways.route(target)
    if branch not in route or branch == target:
        return None
    nxt = route[route.index(branch) + 1]
    kids = airways.graph.children(branch)
    others = [c for c in kids if c.id != nxt]
    if not others:
        return None

    def opening(b) -> np.ndarray:
        s = airways.cum[b.id]
        k = int(min(len(s) - 1, np.searchsorted(s, min(8 * MM, 0.5 * s[-1]))))
        return b.points[k]

    Rinv = pose[:3, :3].T
    a = Rinv @ (opening(airways.graph.branch(nxt)) - pose[:3, 3])
    o = Rinv @ (np.mean([opening(c) for c in others], axis=0) - pose[:3, 3])
    d = a[:2] / max(a[2], 1e-3) - o[:2] / max(o[2], 1e-3)       # image-plane direction (x right, y down)
    if abs(d[0]) >= abs(d[1]):
        return "right" if d[0] > 0 else "left"
    return "down" if d[1] > 0 else "up"


