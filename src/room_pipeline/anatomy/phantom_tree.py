"""The procedural phantom's lungs and bronchial tree (:func:`grow_tree`), rasterised into a CT by
:mod:`~room_pipeline.anatomy.phantom`.

Tree model
    A simplified space-filling form of the 3-D branching algorithm of
    Kitaoka, Takaki & Suki, "A three-dimensional model of the human airway
    tree", J Appl Physiol 87:2207-2217 (1999), written here from the rules:

    * the trachea (vertical, along -z from the larynx) and the two main bronchi
      are given anatomically: the right main bronchus is steeper (smaller
      angle to the tracheal axis) and shorter than the left;
    * each lung is a cloud of points filling a dome-topped half-ellipsoid; the
      points are the "region" (the volume to be supplied) of a branch; a main
      bronchus owns its lung's points;
    * a branch's region is split in two by a plane that contains the branch
      axis and is perpendicular to the daughters' branching plane; that
      branching plane is the parent's rotated about the parent axis by about
      90 degrees (plus a seeded jitter);
    * the flow ratio ``r`` of a daughter is its share of the region's points;
      diameters follow the flow-diameter rule ``d = d0 r^(1/n)``, ``n = 2.8``;
    * branching angles follow Kitaoka's minimum-work formulas
      ``cos th1 = (1 + r^(4/n) - (1-r)^(4/n)) / (2 r^(2/n))`` (and ``r -> 1-r``
      for the other daughter); a daughter points at that angle from the parent
      axis, towards its sub-region's centroid (azimuth of the centroid about
      the parent axis: for a plane split this is, up to the point scatter, the
      common branching plane);
    * length = ``length_to_diameter`` (3) x diameter, clipped so that the
      branch stays inside its sub-region (no longer than the sub-region's
      extent along the branch) and inside the lung (the capsule stays inside
      the lung shape);
    * a daughter thinner than ``min_diameter_mm`` or a region with fewer than
      ``min_region_points`` points ends the recursion;
    * generation counts bifurcations (trachea = 0): a parent left with a single
      daughter (the other one too thin, without room, or dropped for a
      collision, below) does not bifurcate; that lone daughter continues the
      same airway past a kink and keeps its parent's generation (as
      :func:`~room_pipeline.anatomy.centreline.from_airway_tree`, which merges
      such chains into one graph branch); daughters of a bifurcation get
      generation + 1.

    Deviation from Kitaoka et al.: collision avoidance.  Kitaoka's rules keep
    branches inside their own (disjoint) regions but do not stop a branch from
    passing close to, or through, a branch of a neighbouring region, which
    would give the lumen loops (it would no longer be a tree) and merge
    separate airways once partial volume and the PSF blur the CT.  Here every
    new daughter is checked against every existing capsule except its parent,
    its grandparent (ancestors within one generation, which it touches at the
    junction anyway) and its sibling: the closed-form segment-to-segment
    distance must be at least ``r_new + r_other + min_branch_clearance_mm``.
    A daughter that violates this at full length is shortened (bisection on
    its length) down to at most ``max(diameter, min_branch_length_mm)``; if
    even that violates it (or, for a hilar branch, the shortened end is no
    longer inside a lung) the daughter is not grown and its sub-region is left
    unsupplied.  A shortened daughter keeps its region and is split further;
    its own daughters are checked in turn when they are created, so the rule
    holds for every pair of non-adjacent capsules of the final tree.

Lengths in metres (:class:`~room_pipeline.anatomy.phantom_params.PhantomParams` holds millimetres and
degrees); pure, every random choice from the caller's generator.
"""
from __future__ import annotations

from collections import deque

import numpy as np

from ..conventions import MM
from .phantom_params import PhantomParams
from .tree import AirwayTree, Branch


def _lung_shapes(params: PhantomParams) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """(centre, semi-axes, base z) of the right and left lung, metres; carina at the origin.

    Each lung is the upper half (z >= base) of an axis-aligned ellipsoid
    centred on its base plane: a dome whose apex is
    ``lung_apex_above_carina_mm`` above the carina.
    """
    out = []
    base = (params.lung_apex_above_carina_mm - params.lung_height_mm) * MM
    for side, width in ((+1.0, params.lung_width_mm), (-1.0, params.lung_width_mm * params.left_lung_width_ratio)):
        a = 0.5 * width * MM
        centre = np.array([side * (params.mediastinum_half_width_mm * MM + a), 0.0, base])
        out.append((centre, np.array([a, 0.5 * params.lung_depth_mm * MM, params.lung_height_mm * MM]), base))
    return out


def _half_ellipsoid_sd(x, y, z, centre, axes, base):
    """Approximate signed distance (metres, <0 inside) to one lung; broadcasts x, y, z.

    First-order ellipsoid distance ``(q - 1) / |grad q|`` (accurate near the
    surface) intersected with the half-space ``z >= base``.
    """
    u = (x - centre[0]) / axes[0]
    v = (y - centre[1]) / axes[1]
    w = (z - centre[2]) / axes[2]
    q = u * u + v * v + w * w
    g = 2.0 * np.sqrt((u / axes[0]) ** 2 + (v / axes[1]) ** 2 + (w / axes[2]) ** 2)
    s = (q - 1.0) / np.maximum(g, 1e-6)
    return np.maximum(s, base - z)


def lung_signed_distance(points: np.ndarray, params: PhantomParams) -> np.ndarray:
    """Approximate signed distance (metres, <0 inside) of (N, 3) points to the union of the two lungs."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    return np.minimum.reduce([_half_ellipsoid_sd(p[:, 0], p[:, 1], p[:, 2], c, a, b)
                              for c, a, b in _lung_shapes(params)])


def _sample_lung(centre, axes, base, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` points uniform in one half-ellipsoid lung (rejection sampling in its box)."""
    out = np.empty((0, 3))
    lo = np.array([centre[0] - axes[0], centre[1] - axes[1], base])
    hi = np.array([centre[0] + axes[0], centre[1] + axes[1], base + axes[2]])
    while len(out) < n:
        p = lo + rng.random((2 * n, 3)) * (hi - lo)
        q = (((p - centre) / axes) ** 2).sum(axis=1)
        out = np.concatenate([out, p[q <= 1.0]])
    return out[:n]


# --------------------------------------------------------------------------- tree growth


def kitaoka_angle(r: float, n: float = 2.8) -> float:
    """Branching angle (radians) to the parent axis of a daughter carrying flow fraction ``r``.

    Kitaoka et al. 1999 (minimum-work optimum with ``d ~ flow^(1/n)``):
    ``cos th = (1 + r^(4/n) - (1 - r)^(4/n)) / (2 r^(2/n))``.
    """
    r = float(np.clip(r, 1e-9, 1.0))
    c = (1.0 + r ** (4.0 / n) - (1.0 - r) ** (4.0 / n)) / (2.0 * r ** (2.0 / n))
    return float(np.arccos(np.clip(c, -1.0, 1.0)))


def _rotate(v: np.ndarray, axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotate ``v`` about unit ``axis`` by ``angle`` radians (Rodrigues)."""
    return (v * np.cos(angle) + np.cross(axis, v) * np.sin(angle)
            + axis * float(axis @ v) * (1.0 - np.cos(angle)))


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def _clip_length(start, u, length, radius, pts, params) -> float:
    """Length of a daughter: ``length`` clipped to its sub-region and to the lung.

    The branch is no longer than its sub-region's extent along ``u``.  A
    branch starting with its capsule inside a lung ends before the capsule
    would leave it.  A hilar branch (starting in the mediastinum, next to the
    main bronchi) runs on until its end point is inside a lung, even beyond
    ``length``.  0 means there is no room for the branch.
    """
    extent = float(((pts - start) @ u).max())
    if extent <= 0:
        return 0.0
    if lung_signed_distance(start[None], params)[0] > -radius:
        s = np.linspace(0.0, extent, 65)[1:]
        entered = np.nonzero(lung_signed_distance(start + s[:, None] * u, params) <= 0)[0]
        if not len(entered):
            return 0.0
        first = int(entered[0])
        s_end = max(min(length, extent), float(s[first]))
        if lung_signed_distance((start + s_end * u)[None], params)[0] <= 0:
            return s_end
        return float(s[first])
    length = min(length, extent)
    s = np.linspace(0.0, length, 33)
    inside = lung_signed_distance(start + s[:, None] * u, params) <= -radius
    out = np.nonzero(~inside)[0]
    return float(s[out[0] - 1]) if len(out) else length


def segment_distances(p0: np.ndarray, p1: np.ndarray, q0: np.ndarray, q1: np.ndarray) -> np.ndarray:
    """Closed-form distance between segment ``p0 p1`` and each segment ``q0[i] q1[i]`` (metres).

    ``p0``, ``p1`` broadcast against ``q0``, ``q1`` (..., 3).  The closest-point
    parameters of the infinite lines are clamped to the segments in the
    standard order (Ericson, Real-Time Collision Detection, 5.1.9), which is
    exact for segments, including parallel and zero-length ones.
    """
    d1 = np.asarray(p1, dtype=np.float64) - p0
    d2 = np.asarray(q1, dtype=np.float64) - q0
    r = np.asarray(p0, dtype=np.float64) - q0
    a = np.einsum("...i,...i->...", d1, d1)
    e = np.einsum("...i,...i->...", d2, d2)
    b = np.einsum("...i,...i->...", d1, d2)
    c = np.einsum("...i,...i->...", d1, r)
    f = np.einsum("...i,...i->...", d2, r)
    a, e, b, c, f = np.broadcast_arrays(a, e, b, c, f)
    tiny = 1e-30
    a_ = np.where(a > tiny, a, 1.0)
    e_ = np.where(e > tiny, e, 1.0)
    den = a * e - b * b
    # s on the first segment: line-line optimum (0 for parallel or degenerate segments) ...
    s = np.where(den > 1e-12 * a * e, np.clip((b * f - c * e) / np.where(den > 0, den, 1.0), 0.0, 1.0), 0.0)
    s = np.where(e > tiny, s, np.clip(-c / a_, 0.0, 1.0))  # second segment a point: project it
    s = np.where(a > tiny, s, 0.0)
    # ... then t on the second for that s; if t leaves [0, 1], clamp it and recompute s
    t = np.where(e > tiny, (b * s + f) / e_, 0.0)
    s = np.where(t < 0.0, np.clip(-c / a_, 0.0, 1.0), np.where(t > 1.0, np.clip((b - c) / a_, 0.0, 1.0), s))
    s = np.where(a > tiny, s, 0.0)
    t = np.clip(t, 0.0, 1.0)
    v = r + s[..., None] * d1 - t[..., None] * d2
    return np.sqrt(np.einsum("...i,...i->...", v, v))


class _Clearance:
    """Capsules grown so far, for the collision check of new branches (see the module docstring)."""

    def __init__(self, clearance: float) -> None:
        self.clearance = clearance
        self.start = np.empty((0, 3))
        self.end = np.empty((0, 3))
        self.radius = np.empty(0)
        self.n = 0

    def add(self, b: Branch) -> None:
        if self.n == len(self.radius):  # grow the buffers geometrically
            cap = max(64, 2 * self.n)
            for name, shape in (("start", (cap, 3)), ("end", (cap, 3)), ("radius", (cap,))):
                buf = np.empty(shape)
                buf[:self.n] = getattr(self, name)[:self.n]
                setattr(self, name, buf)
        self.start[self.n], self.end[self.n], self.radius[self.n] = b.start, b.end, b.radius
        self.n += 1

    def fit(self, start: np.ndarray, u: np.ndarray, length: float, radius: float, min_length: float,
            exclude: list[int]) -> float:
        """Longest length <= ``length`` keeping the clearance to every capsule not in ``exclude``.

        Returns ``length`` if the full branch is clear, else the largest clear
        length found by bisection in ``[min_length, length]``, or 0 if even
        ``min_length`` (or ``length`` when it is shorter) is not clear.
        Capsule ids are their insertion order (= branch ids).
        """
        keep = np.ones(self.n, dtype=bool)
        keep[[i for i in exclude if 0 <= i < self.n]] = False
        q0, q1 = self.start[:self.n][keep], self.end[:self.n][keep]
        need = radius + self.radius[:self.n][keep] + self.clearance
        # cheap prefilter: bounding spheres of the full-length branch and each capsule
        mid = start + 0.5 * length * u
        reach = 0.5 * length + 0.5 * np.linalg.norm(q1 - q0, axis=1) + need
        near = np.linalg.norm(0.5 * (q0 + q1) - mid, axis=1) < reach
        q0, q1, need = q0[near], q1[near], need[near]
        if not len(need):
            return length

        def clear(L: float) -> bool:
            return bool(np.all(segment_distances(start, start + L * u, q0, q1) >= need))

        if clear(length):
            return length
        lo = min(min_length, length)
        if lo >= length or not clear(lo):
            return 0.0
        hi = length
        for _ in range(20):  # distance to a segment is non-increasing in the branch length
            if hi - lo < 1e-5 * MM:
                break
            mid_l = 0.5 * (lo + hi)
            if clear(mid_l):
                lo = mid_l
            else:
                hi = mid_l
        return lo


def grow_tree(params: PhantomParams, rng: np.random.Generator) -> AirwayTree:
    """Grow the bronchial tree (Kitaoka et al. 1999, simplified; see the module docstring).

    The carina is at the world origin, the trachea runs along -z from
    ``(0, 0, trachea_length)``; +x is the patient's right (RAS+).  Branch ids
    are assigned breadth-first; names: 'trachea', 'RMB', 'LMB'.  Metres.
    Generations count bifurcations (a lone daughter keeps its parent's) and
    non-adjacent capsules keep ``min_branch_clearance_mm`` apart (see the
    module docstring).
    """
    n = params.flow_exponent
    shapes = _lung_shapes(params)
    vols = np.array([np.prod(a) for _, a, _ in shapes])
    n_right = int(round(params.lung_points * vols[0] / vols.sum()))
    clouds = [_sample_lung(*shapes[0], n_right, rng),
              _sample_lung(*shapes[1], params.lung_points - n_right, rng)]

    d0 = params.trachea_diameter_mm * MM
    carina = np.zeros(3)
    trachea = Branch(0, -1, 0, carina + [0.0, 0.0, params.trachea_length_mm * MM], carina, d0 / 2, "trachea")
    branches = [trachea]
    grown = _Clearance(params.min_branch_clearance_mm * MM)
    grown.add(trachea)
    queue: deque = deque()
    coronal_normal = np.array([0.0, 1.0, 0.0])  # the carina's branching plane is coronal
    r_right = len(clouds[0]) / (len(clouds[0]) + len(clouds[1]))
    for side, r, ang, length, name, cloud in (
            (+1.0, r_right, params.rmb_angle_deg, params.rmb_length_mm, "RMB", clouds[0]),
            (-1.0, 1.0 - r_right, params.lmb_angle_deg, params.lmb_length_mm, "LMB", clouds[1])):
        a = np.deg2rad(ang)
        u = np.array([side * np.sin(a), 0.0, -np.cos(a)])
        b = Branch(len(branches), 0, 1, carina, carina + length * MM * u, 0.5 * d0 * r ** (1.0 / n), name)
        branches.append(b)
        grown.add(b)
        queue.append((b, cloud, coronal_normal))

    jitter = np.deg2rad(params.plane_rotation_jitter_deg)
    dmin = params.min_diameter_mm * MM
    lmin = params.min_branch_length_mm * MM
    while queue:
        parent, pts, plane_normal = queue.popleft()
        if len(pts) < params.min_region_points or parent.generation >= params.max_generation:
            continue
        axis = parent.direction
        bp = parent.end
        # daughters' branching plane: the parent's rotated ~90 deg about the parent axis
        nb = _rotate(plane_normal, axis, np.pi / 2 + rng.uniform(-jitter, jitter))
        nb = _unit(nb - (nb @ axis) * axis)
        m = np.cross(nb, axis)  # normal of the space-dividing plane (contains the axis, perpendicular to nb)
        side = (pts - bp) @ m > 0
        if side.all() or not side.any():  # the region lies on one side of the axis: no bifurcation
            continue
        kids: list[Branch] = []
        for sub in (pts[side], pts[~side]):
            r = len(sub) / len(pts)
            d = 2 * parent.radius * r ** (1.0 / n)
            if d < dmin:
                continue
            theta = kitaoka_angle(r, n)
            c = sub.mean(axis=0) - bp
            perp = c - (c @ axis) * axis
            if np.linalg.norm(perp) < 1e-9:
                perp = m if side.mean() > 0 else -m
            u = np.cos(theta) * axis + np.sin(theta) * _unit(perp)
            length = _clip_length(bp, u, params.length_to_diameter * d, d / 2, sub, params)
            if length < d / 2:  # no room for a branch in this sub-region
                continue
            # collision avoidance (our deviation from Kitaoka): not counting the parent, the
            # grandparent and the sibling, shorten the branch or drop it
            exclude = [parent.id, parent.parent] + [k.id for k in kids]
            fitted = grown.fit(bp, u, length, d / 2, max(d, lmin), exclude)
            if fitted <= 0.0:
                continue
            if fitted < length and lung_signed_distance((bp + fitted * u)[None], params)[0] > 0:
                continue  # a hilar branch shortened back out of the lung
            child = Branch(len(branches), parent.id, parent.generation + 1, bp.copy(), bp + fitted * u, d / 2)
            branches.append(child)
            grown.add(child)
            kids.append(child)
            queue.append((child, sub, nb))
        if len(kids) == 1:  # no bifurcation: the lone daughter continues the parent's airway
            kids[0].generation = parent.generation
    return AirwayTree(branches)
