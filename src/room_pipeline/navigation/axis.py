"""The lumen's local axis from one depth map: the centres of the lumen's cross-sections ahead of the camera.

A pixel whose ray meets the wall deeper than ``z`` (planar depth; no hit = beyond the far plane) looks through
the air at the plane ``z``: the set of such pixels, ``depth > z``, is the lumen's free cross-section at ``z``
as seen (its rim is where the wall crosses the plane).  On a pinhole camera every pixel covers the same area
of a plane ``z = const``, so the cross-section's centre is ``z`` times the mean normalised ray ``(x/z, y/z)``
of its pixels.  Stepping ``z`` from the camera outward, the cross-sections are nested (a deeper one lies inside
a shallower one); where one splits in two, the lumen forks: the operator's command (a unit image direction)
picks the child lying farthest that way (without one, the deepest; when the openings part more than 60 deg
across the command's direction, the fork is not the commanded one: the opening nearest the image centre, the
lumen the scope is in, e.g. a sibling seen sideways just past a carina), and the walk continues inside it only.
A cross-section touching the image border is cut by the field of view: its centre is biased toward the view
axis (such centres are used only when every cross-section is cut and no fork is seen).  The axis (:class:`LumenAxis`
``polyline``): the parent lumen's centres from the first uncut cross-section on, up to ``lead_m`` before the
fork (the closed loop's ``axis_lead_mm``, 15 mm: the turn starts before the carina's tip, where the
cross-sections part, as a centreline's branch point lies before it; 15 measured better than 6 on the
benchmark), then the chosen child's centres; with no parent centre before that, straight from the camera to the child's centres.  :func:`axis_target` returns its
point ``lookahead_m`` beyond the camera's foot on it (the first centre when the camera is behind it): the
depth-only counterpart of the oracle's target (``lookahead`` along the centreline route from the tip's nearest
point), a point of the anatomy that pulls an off-axis tip back to the lumen's middle and turns it into the
commanded child.

Frames and units: camera frame OpenCV (x right, y down, z forward), metres; depth planar z, m (0 = no hit).
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
from scipy import ndimage

from ..render.camera import CameraIntrinsics

_EIGHT = np.ones((3, 3), bool)


@dataclasses.dataclass
class LumenAxis:
    """centres: (K, 3) cross-section centres (camera frame, m), nearest first; usable: (K,) not cut by the
    field of view; split_m: planar depth of the first fork on the chosen way (None: no fork seen);
    polyline: (M, 3) the axis from the camera's plane on (see :func:`lumen_axis`); openings: (u, v, pixels)
    of the openings at that fork (image centroid), pick: the index of the chosen one (None without a fork),
    pick_by: what chose it (held | command | centre | deepest)."""

    centres: np.ndarray
    usable: np.ndarray
    split_m: float | None
    polyline: np.ndarray
    openings: list | None = None
    pick: int | None = None
    pick_by: str | None = None


def lumen_axis(depth: np.ndarray, camera: CameraIntrinsics, command=None, step_m: float = 1e-3,
               lead_m: float = 6e-3, min_px: int = 4, min_share: float = 0.1,
               prefer: np.ndarray | None = None, hold_tol_m: float | None = None) -> LumenAxis | None:
    """The local lumen axis seen in ``depth`` ((H, W) planar depth, m; 0 = no hit); None when no parent
    cross-section is usable and no fork is seen.  ``command``: unit image direction (u right, v down) picking
    the child at a fork (without one, the deepest); ``prefer`` (camera-frame point, m, ahead of the camera):
    at a fork, the child whose image centroid is nearest its projection wins instead (the caller's memory of
    the child it chose in earlier frames); components of fewer than ``min_px`` pixels or ``min_share``
    of the largest are not openings; ``step_m``: spacing of the cross-sections; ``lead_m``: see the module
    docstring; ``hold_tol_m`` (None: off): a ``prefer`` point nearer than the split minus this is ignored: it
    lies before the fork, in the parent lumen (a point held at an earlier fork), and picks no child of this one."""
    d = np.asarray(depth, dtype=np.float64)
    d = np.where(np.isfinite(d) & (d > 0), d, np.inf)
    fin = d[np.isfinite(d)]
    if fin.size == 0:
        return None
    h, w = d.shape
    vv, uu = np.mgrid[0:h, 0:w]
    q = camera.rays_at(np.stack([uu, vv], axis=-1).astype(np.float64))[..., :2]   # (H, W, 2) x/z, y/z
    top = float(np.quantile(fin, 0.98)) if np.isinf(d).sum() == 0 else float(fin.max()) + step_m
    chosen = np.ones((h, w), bool)
    cents, usable, split, openings, pick_i, pick_by = [], [], None, None, None, None
    for z in np.arange(step_m, top, step_m):
        hole = (d > z) & chosen
        lab, n = ndimage.label(hole, structure=_EIGHT)
        if n == 0:
            break
        sizes = np.bincount(lab.ravel(), minlength=n + 1)[1:]
        keep = [k for k in range(n) if sizes[k] >= max(min_px, min_share * sizes.max())]
        if not keep:
            break
        if len(keep) > 1:
            uv = np.array([[uu[lab == k + 1].mean(), vv[lab == k + 1].mean()] for k in keep])
            by = None
            if prefer is not None and prefer[2] > 0 and (hold_tol_m is None or prefer[2] >= z - hold_tol_m):
                pu, pv = camera.project_normalized(prefer[0] / prefer[2], prefer[1] / prefer[2])
                pick, by = keep[int(np.argmin(((uv - [pu, pv]) ** 2).sum(axis=1)))], "held"  # the child chosen before
            elif command is not None:
                cmd = np.asarray(command, float)
                i = int(np.argmax((uv - uv.mean(axis=0)) @ cmd))
                gap = uv[i] - np.delete(uv, i, axis=0).mean(axis=0)
                if gap @ cmd >= 0.5 * np.linalg.norm(gap):          # the openings part the commanded way
                    pick, by = keep[i], "command"
                else:              # they part across it: not the commanded fork; stay in the lumen straight ahead
                    pick, by = keep[int(np.argmin(((uv - [camera.cx, camera.cy]) ** 2).sum(axis=1)))], "centre"
            else:
                pick, by = keep[int(np.argmax([d[lab == k + 1].max() for k in keep]))], "deepest"
            if split is None:
                split = float(z)
                openings = [[round(float(a), 1), round(float(b), 1), int(sizes[k])] for (a, b), k in zip(uv, keep)]
                pick_i, pick_by = keep.index(pick), by
        else:
            pick = keep[0]
        chosen = lab == pick + 1
        cut = chosen[0].any() or chosen[-1].any() or chosen[:, 0].any() or chosen[:, -1].any()
        m = q[chosen].mean(axis=0)
        cents.append([z * m[0], z * m[1], z])
        usable.append(not cut)
        if any(usable) and z > cents[usable.index(True)][2] + lead_m + 20e-3:
            break                                              # far enough: the target lies within the first mm
    if not cents:
        return None
    C, U = np.array(cents), np.array(usable, bool)
    before = C[:, 2] < split - lead_m if split is not None else np.ones(len(C), bool)
    first = int(np.argmax(U)) if U.any() else len(C)
    parent = before & (np.arange(len(C)) >= first)        # from the first cross-section the view does not cut
    if not parent.any() and split is None:
        parent = before                                    # all cut, no fork: the biased ones (about straight on)
    child = C[C[:, 2] >= split] if split is not None else np.zeros((0, 3))
    if not parent.any() and not len(child):
        return None
    start = C[parent] if parent.any() else np.zeros((1, 3))
    return LumenAxis(centres=C, usable=U, split_m=split, polyline=np.vstack([start, child]), openings=openings,
                     pick=pick_i, pick_by=pick_by)


def axis_target(axis: LumenAxis, lookahead_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(point, unit tangent) on the axis polyline ``lookahead_m`` beyond the camera's foot on it (camera frame,
    m; the foot: the polyline's point nearest the camera, its first point when the camera is behind it; past
    its end, straight on along the last segment)."""
    L = axis.polyline
    if len(L) == 1:
        L = np.vstack([L, L[0] + [0.0, 0.0, 1e-3]])
    seg = np.diff(L, axis=0)
    n = np.linalg.norm(seg, axis=1)
    ok = n > 1e-12
    L = np.vstack([L[:1], L[1:][ok]])
    seg, n = seg[ok], n[ok]
    if len(seg) == 0:
        return L[0] + [0.0, 0.0, lookahead_m], np.array([0.0, 0.0, 1.0])
    t = np.clip(-(L[:-1] * seg).sum(axis=1) / n ** 2, 0.0, 1.0)
    foot = L[:-1] + t[:, None] * seg
    i = int(np.argmin(np.linalg.norm(foot, axis=1)))
    cum = np.concatenate([[0.0], np.cumsum(n)])
    s = cum[i] + t[i] * n[i] + lookahead_m
    k = int(min(len(seg) - 1, np.searchsorted(cum, s, side="right") - 1))
    d = seg[k] / n[k]
    return L[k] + (s - cum[k]) * d, d


def tube_clearance(point: np.ndarray, depth: np.ndarray, camera: CameraIntrinsics, tree, start_m: float = 1e-3,
                   step_m: float = 5e-4, end_m: float = 0.0) -> float:
    """Clearance of the straight segment from the camera to ``point`` (camera frame, m) in one depth map, m: the
    smallest distance from its points (every ``step_m`` from ``start_m`` on) to the observed wall (``tree``: a
    cKDTree of the back-projected cloud), or minus how far a point lies behind the observed surface (its pixel's
    planar depth nearer than it: the segment goes through a wall the camera sees).  A scope of radius ``r``
    can go straight to ``point`` when this is >= ``r``.  ``depth``: (H, W) planar depth, m (0 = no hit)."""
    p = np.asarray(point, float).reshape(3)
    n = float(np.linalg.norm(p))
    if n <= start_m:
        return math.inf
    P = p[None, :] * (np.arange(start_m, n - end_m + 1e-12, step_m) / n)[:, None]
    P = P[P[:, 2] > 1e-6]
    if not len(P):
        return math.inf
    u, v = camera.project_normalized(P[:, 0] / P[:, 2], P[:, 1] / P[:, 2])
    h, w = depth.shape
    jj, ii = np.rint(u).astype(int), np.rint(v).astype(int)
    inside = (jj >= 0) & (jj < w) & (ii >= 0) & (ii < h)
    d = np.zeros(len(P))
    d[inside] = np.asarray(depth, float)[ii[inside], jj[inside]]
    behind = inside & (d > 0) & (d < P[:, 2])
    if behind.any():
        return -float((P[behind, 2] - d[behind]).max())
    return float(tree.query(P)[0].min()) if tree is not None and tree.n else math.inf


def wall_ahead(points: np.ndarray, radius_m: float) -> float:
    """Planar depth of the nearest observed wall point within ``radius_m`` of the view axis (camera-frame cloud
    ``points`` (N, 3), m): how far the scope, of that radius, can go straight on; inf when none."""
    P = np.asarray(points, float).reshape(-1, 3)
    m = np.hypot(P[:, 0], P[:, 1]) <= radius_m
    return float(P[m, 2].min()) if m.any() else math.inf
