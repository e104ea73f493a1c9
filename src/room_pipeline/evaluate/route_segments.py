"""Route segments of a camera sequence (trachea, each bifurcation region, distal branches) for per-segment scores.

Each frame's camera centre (world metres, the frame of ``centreline_graph.json``)
is placed on the airway centreline graph:

* **bifurcation region** ``bifurcation_<k>``: the centre lies within
  ``radius_factor`` x the parent's lumen radius of a branch point (the last
  point of a branch that has children).  ``k`` numbers the regions in the
  order the route first enters them (1, 2, ...); the record names the parent
  branch and its generation.  This is where the view turns and the scene
  splits: the hard part of a route.
* **trachea**: otherwise, the nearest centreline point belongs to the root branch;
* **distal**: otherwise (generation >= 1, away from a branch point).

Scores per segment use the frame pairs with both frames in that segment
(``bifurcations`` pools the pairs inside any one bifurcation region).
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..anatomy.centreline import CentrelineGraph

TRACHEA, DISTAL = "trachea", "distal"


def label_frames(centres_m: np.ndarray, graph: CentrelineGraph, radius_factor: float = 2.0
                 ) -> tuple[list[str], dict]:
    """(per-frame segment labels, {bifurcation label: {"parent_branch", "generation", "point_m", "radius_m"}})."""
    c = np.asarray(centres_m, dtype=np.float64).reshape(-1, 3)
    if radius_factor <= 0:
        raise ValueError("radius_factor must be > 0")
    pts, _, bid = graph.all_points()
    if len(c) == 0:
        return [], {}
    if len(pts) == 0:
        return [DISTAL] * len(c), {}
    _, idx = cKDTree(pts).query(c)
    root = graph.root.id
    labels = [TRACHEA if int(bid[k]) == root else DISTAL for k in idx]
    forks = [b for b in graph.branches if graph.children(b.id)]
    if forks:
        fp = np.array([b.points[-1] for b in forks])
        fr = np.array([max(float(b.radius[-1]), 1e-9) for b in forks])
        d = np.linalg.norm(c[:, None, :] - fp[None, :, :], axis=2) / fr[None, :]
        near = d.argmin(axis=1)
        inside = d[np.arange(len(c)), near] < radius_factor
        names: dict[int, str] = {}
        regions = {}
        for f in range(len(c)):
            if not inside[f]:
                continue
            b = forks[int(near[f])]
            if b.id not in names:
                names[b.id] = f"bifurcation_{len(names) + 1}"
                regions[names[b.id]] = {"parent_branch": int(b.id), "generation": int(b.generation),
                                        "point_m": np.round(b.points[-1], 6).tolist(),
                                        "radius_m": round(float(b.radius[-1]), 6)}
            labels[f] = names[b.id]
        return labels, regions
    return labels, {}
