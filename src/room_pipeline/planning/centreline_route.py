"""The centreline route from the root to a target (step 2 of :func:`~room_pipeline.planning.trajectory.plan_path`):
the graph polylines concatenated, with lumen radii, arclength and bifurcation positions, cut to a length."""
from __future__ import annotations

import dataclasses

import numpy as np

from ..anatomy.centreline import CentrelineGraph
from ..conventions import MM
from ..errors import InputError


@dataclasses.dataclass
class _Route:
    points: np.ndarray      # (V, 3) m
    radius: np.ndarray      # (V,) m
    branch: np.ndarray      # (V,) branch id of each vertex
    s: np.ndarray           # (V,) arclength from the start, m
    junctions: np.ndarray   # (J,) arclength of bifurcations on the route, m

    @property
    def length(self) -> float:
        return float(self.s[-1])


def _cut(points, radius, s, lo, hi):
    """Part of a polyline (arclength ``s``) between arclengths lo <= hi, end points interpolated."""
    keep = (s > lo) & (s < hi)
    p0 = np.array([np.interp(lo, s, points[:, k]) for k in range(3)])
    p1 = np.array([np.interp(hi, s, points[:, k]) for k in range(3)])
    pts = np.vstack([p0, points[keep], p1])
    rad = np.concatenate([[np.interp(lo, s, radius)], radius[keep], [np.interp(hi, s, radius)]])
    ss = np.concatenate([[lo], s[keep], [hi]])
    return pts, rad, ss


def _route(graph: CentrelineGraph, branch_id: int, s_in_branch: float, start_offset: float) -> _Route:
    chain = graph.path_to(branch_id)
    pts, rad, bid, junc = [], [], [], []
    offset = 0.0
    for i, b in enumerate(chain):
        seg = np.linalg.norm(np.diff(b.points, axis=0), axis=1)
        s = np.concatenate([[0.0], np.cumsum(seg)])
        last = i == len(chain) - 1
        end = min(s_in_branch, s[-1]) if last else s[-1]
        p, r, ss = _cut(b.points, b.radius, s, 0.0, end)
        if i:
            p, r, ss = p[1:], r[1:], ss[1:]  # the junction point is the parent's last
        pts.append(p); rad.append(r); bid.append(np.full(len(p), b.id))
        ss = ss + offset
        if not last or (end >= s[-1] - 1e-12 and graph.children(b.id)):
            junc.append(offset + s[-1])
        offset += s[-1]
        if i == 0:
            s_all = [ss]
        else:
            s_all.append(ss)
    P, R, Bi, S = np.vstack(pts), np.concatenate(rad), np.concatenate(bid), np.concatenate(s_all)
    # drop repeated points (zero-length segments)
    keep = np.concatenate([[True], np.diff(S) > 1e-12])
    P, R, Bi, S = P[keep], R[keep], Bi[keep], S[keep]
    if start_offset > 0:
        if start_offset >= S[-1]:
            raise InputError(f"target lies before the start ({start_offset / MM:.1f} mm along the route, which is "
                             f"{S[-1] / MM:.1f} mm long)")
        P2, R2, S2 = _cut(P, R, S, start_offset, S[-1])
        B2 = Bi[np.clip(np.searchsorted(S, S2, side="right") - 1, 0, len(S) - 1)]
        P, R, Bi, S = P2, R2, B2, S2 - start_offset
        junc = [j - start_offset for j in junc]
    return _Route(P, R, Bi, S, np.asarray([j for j in junc if 0 <= j <= S[-1] + 1e-12], dtype=np.float64))


def _truncate(route: _Route, s_end: float) -> _Route:
    P, R, S = _cut(route.points, route.radius, route.s, 0.0, s_end)
    Bi = route.branch[np.clip(np.searchsorted(route.s, S, side="left"), 0, len(route.s) - 1)]
    keep = np.concatenate([[True], np.diff(S) > 1e-12])
    return _Route(P[keep], R[keep], Bi[keep], S[keep], route.junctions[route.junctions <= s_end + 1e-12])
