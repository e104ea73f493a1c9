"""The built-in procedural phantom patient: a grown bronchial tree rasterised into a CT.

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

CT model
    Layers mixed with partial-volume coverage ``clip(0.5 - s / h, 0, 1)`` from
    a signed distance ``s`` (``h`` = mean voxel size): outside air, a body
    (elliptic cylinder: subcutaneous fat rim, soft tissue inside, which is also
    the mediastinum around the trachea), the two lungs (parenchyma with
    spatially correlated Gaussian texture), the airway wall (outer surface =
    capsules of radius ``r + t(r)`` with ``t = wall_thickness_ratio * 2r +
    wall_thickness_offset_mm``; the ratio 0.15 is a modelling choice inside the
    commonly quoted normal range of CT wall-thickness / lumen-diameter of about
    0.1-0.2, not a fit to data) and the lumen (air).  The result is blurred by a
    Gaussian PSF (``psf_sigma_voxels``), white Gaussian noise is added and the
    values are rounded to int16 HU in [-1024, 3071].

Ground truth
    ``mask`` = voxel centre inside the lumen union (``sdf < 0``); ``sdf`` comes
    from :meth:`AirwayTree.sdf` (metres, negative in the lumen), evaluated on
    every lumen voxel and on every outside voxel closer than ``sdf_band_mm``
    to the lumen, spatially tiled so that each tile only sees its nearby
    branches (same values as the whole tree).  Farther outside it is clipped
    to ``+sdf_band_mm``.  ``sdf_exact`` is True where the stored value is the
    true signed distance: inside the band and not flagged by the tree's
    junction test; clipped far-field voxels are False.

All functions are pure (no file I/O).  Parameters are millimetres / degrees /
HU in :class:`PhantomParams` (the YAML's units) and metres everywhere else.
"""
from __future__ import annotations

import dataclasses
from collections import deque
from typing import Any, Mapping

import numpy as np
from scipy import ndimage

from ..conventions import MM
from ..errors import ConfigError
from ..io.volume import Volume
from .tree import AirwayTree, Branch

# --------------------------------------------------------------------------- parameters


@dataclasses.dataclass
class PhantomParams:
    """All knobs of the phantom; field names are the keys of ``conf/phantom/default.yaml``.

    Lengths in millimetres, angles in degrees, intensities in HU.
    """

    # --- tree: anatomical start
    trachea_diameter_mm: float = 17.0
    trachea_length_mm: float = 110.0
    rmb_angle_deg: float = 25.0            # right main bronchus, angle to the tracheal axis
    lmb_angle_deg: float = 45.0
    rmb_length_mm: float = 25.0
    lmb_length_mm: float = 50.0
    # --- tree: Kitaoka growth
    flow_exponent: float = 2.8             # n in d = d0 r^(1/n)
    length_to_diameter: float = 3.0
    min_diameter_mm: float = 2.0
    max_generation: int = 20
    min_branch_clearance_mm: float = 1.5   # lumen gap kept between non-adjacent branches
    min_branch_length_mm: float = 2.0      # a branch shortened for clearance stays >= max(this, diameter)
    min_region_points: int = 8
    plane_rotation_jitter_deg: float = 20.0
    lung_points: int = 20000               # both lungs together
    # --- lung / body geometry
    lung_width_mm: float = 100.0           # right lung, left-right extent
    left_lung_width_ratio: float = 0.85    # left lung narrower (heart)
    lung_depth_mm: float = 110.0           # antero-posterior extent
    lung_height_mm: float = 140.0          # base to apex
    lung_apex_above_carina_mm: float = 20.0
    mediastinum_half_width_mm: float = 18.0
    chest_wall_mm: float = 12.0            # lung surface to skin
    fat_thickness_mm: float = 5.0          # subcutaneous fat rim
    # --- grid
    spacing_mm: tuple = (0.7, 0.7, 0.7)    # voxel size along x (R), y (A), z (S)
    margin_mm: float = 10.0
    crop_top_mm: float = 0.0               # >0: volume top this far below the trachea top (trachea cut)
    sdf_band_mm: float = 5.0
    # --- intensities
    hu_air: float = -1000.0
    hu_wall: float = 40.0
    hu_parenchyma: float = -850.0
    hu_soft_tissue: float = 40.0
    hu_fat: float = -100.0
    wall_thickness_ratio: float = 0.15     # x lumen diameter
    wall_thickness_offset_mm: float = 0.3
    texture_sigma_hu: float = 25.0
    texture_correlation_mm: float = 2.0
    psf_sigma_voxels: float = 0.7
    noise_sigma_hu: float = 20.0

    def __post_init__(self) -> None:
        sp = self.spacing_mm
        if isinstance(sp, (int, float)):
            sp = (sp, sp, sp)
        try:
            sp = tuple(float(v) for v in sp)
        except (TypeError, ValueError):
            raise ConfigError(f"phantom.spacing_mm must be a number or 3 numbers, got {self.spacing_mm!r}") from None
        if len(sp) != 3 or min(sp) <= 0:
            raise ConfigError(f"phantom.spacing_mm must be 1 or 3 positive numbers (mm), got {self.spacing_mm!r}")
        self.spacing_mm = sp
        for f in dataclasses.fields(self):
            if f.name == "spacing_mm":
                continue
            v = getattr(self, f.name)
            want = int if f.type in ("int", int) else float
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise ConfigError(f"phantom.{f.name} must be a number, got {v!r}")
            if want is int and float(v) != int(v):
                raise ConfigError(f"phantom.{f.name} must be an integer, got {v!r}")
            setattr(self, f.name, want(v))
        positive = ("trachea_diameter_mm", "trachea_length_mm", "rmb_length_mm", "lmb_length_mm",
                    "flow_exponent", "length_to_diameter", "min_diameter_mm", "lung_points",
                    "lung_width_mm", "left_lung_width_ratio", "lung_depth_mm", "lung_height_mm",
                    "sdf_band_mm", "texture_correlation_mm")
        for name in positive:
            if getattr(self, name) <= 0:
                raise ConfigError(f"phantom.{name} must be > 0, got {getattr(self, name)}")
        nonneg = ("margin_mm", "crop_top_mm", "chest_wall_mm", "fat_thickness_mm", "mediastinum_half_width_mm",
                  "wall_thickness_ratio", "wall_thickness_offset_mm", "texture_sigma_hu",
                  "psf_sigma_voxels", "noise_sigma_hu", "plane_rotation_jitter_deg", "max_generation",
                  "min_branch_clearance_mm", "min_branch_length_mm")
        for name in nonneg:
            if getattr(self, name) < 0:
                raise ConfigError(f"phantom.{name} must be >= 0, got {getattr(self, name)}")
        if self.fat_thickness_mm > self.chest_wall_mm:
            raise ConfigError("phantom.fat_thickness_mm must not exceed phantom.chest_wall_mm")
        if self.min_region_points < 2:
            raise ConfigError(f"phantom.min_region_points must be >= 2, got {self.min_region_points}")
        if not 0 < self.rmb_angle_deg < 90 or not 0 < self.lmb_angle_deg < 90:
            raise ConfigError("phantom.rmb_angle_deg / lmb_angle_deg must be in (0, 90)")

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None) -> "PhantomParams":
        """Build from a config section; an unknown key raises :class:`ConfigError` naming it."""
        d = dict(d or {})
        known = {f.name for f in dataclasses.fields(cls)}
        for key in d:
            if key not in known:
                raise ConfigError(f"phantom: unknown config key '{key}' (known: {', '.join(sorted(known))})")
        return cls(**d)

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["spacing_mm"] = list(self.spacing_mm)
        return d


def wall_thickness(radius: np.ndarray | float, params: PhantomParams) -> np.ndarray | float:
    """Airway wall thickness (metres) for a lumen radius (metres)."""
    return params.wall_thickness_ratio * 2.0 * np.asarray(radius) + params.wall_thickness_offset_mm * MM


# --------------------------------------------------------------------------- lungs


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


# --------------------------------------------------------------------------- rasterisation


@dataclasses.dataclass
class Phantom:
    """A phantom patient: the tree and its CT with exact ground truth on the same grid.

    ``ct`` int16 HU; ``mask`` uint8 (1 = voxel centre in the lumen);
    ``sdf`` float32 metres (negative in the lumen; exact within
    ``sdf_band_mm`` and everywhere inside, clipped to +band beyond);
    ``sdf_exact`` bool (stored sdf equals the true value).
    """

    tree: AirwayTree
    ct: Volume
    mask: Volume
    sdf: Volume
    sdf_exact: Volume


def _coverage(s: np.ndarray, h: float) -> np.ndarray:
    """Fraction of a voxel of width ``h`` inside a surface at signed distance ``s`` (linear ramp)."""
    out = 0.5 - s / np.float32(h)
    np.clip(out, 0.0, 1.0, out=out)
    return out


def _mix(base: np.ndarray, value, frac: np.ndarray) -> None:
    """In place: base <- base + frac * (value - base)."""
    base += frac * (value - base)


def _body_ellipse(params: PhantomParams) -> tuple[np.ndarray, np.ndarray]:
    """Centre (x, y) and semi-axes (metres) of the body's elliptic cross-section."""
    lo = np.full(2, np.inf)
    hi = np.full(2, -np.inf)
    for c, a, _ in _lung_shapes(params):
        lo = np.minimum(lo, c[:2] - a[:2])
        hi = np.maximum(hi, c[:2] + a[:2])
    centre = 0.5 * (lo + hi)
    # an ellipse through the lungs' bounding box corners would be sqrt(2) too big; the
    # lungs are ellipses too, so the box half-sizes plus the chest wall enclose them
    return centre, 0.5 * (hi - lo) + params.chest_wall_mm * MM


def _ellipse_sd(x, y, centre, axes):
    u = (x - centre[0]) / axes[0]
    v = (y - centre[1]) / axes[1]
    g = 2.0 * np.sqrt((u / axes[0]) ** 2 + (v / axes[1]) ** 2)
    return (u * u + v * v - 1.0) / np.maximum(g, 1e-6)


def _grid(tree: AirwayTree, params: PhantomParams) -> tuple[np.ndarray, tuple[int, int, int]]:
    """Affine (voxel -> world metres, axis-aligned RAS+) and shape of the phantom's field of view.

    The tree's bounding box plus ``margin_mm``, widened in x/y to hold the body
    outline plus ``margin_mm`` of air; the top is lowered by ``crop_top_mm``.
    """
    sp = np.array(params.spacing_mm) * MM
    margin = params.margin_mm * MM
    lo, hi = tree.bounds(margin)
    bc, ba = _body_ellipse(params)
    lo[:2] = np.minimum(lo[:2], bc - ba - margin)
    hi[:2] = np.maximum(hi[:2], bc + ba + margin)
    if params.crop_top_mm > 0:
        hi[2] = tree.branch(0).start[2] - params.crop_top_mm * MM
    shape = tuple(int(v) for v in np.floor((hi - lo) / sp).astype(int) + 1)
    affine = np.eye(4)
    affine[:3, :3] = np.diag(sp)
    affine[:3, 3] = lo
    return affine, shape  # type: ignore[return-value]


def _capsule_min_distance(tree: AirwayTree, xs, ys, zs, margin: float, wall: np.ndarray
                          ) -> tuple[np.ndarray, np.ndarray]:
    """Min over branches of the capsule signed distances of the lumen and of the wall's outer surface.

    Each branch is evaluated only on the voxel sub-box of its capsule grown by
    ``margin`` (metres); elsewhere the result is ``+inf``.  Outside the lumen
    the lumen value is the exact distance to the union.  float32 arrays.
    """
    shape = (len(xs), len(ys), len(zs))
    d_lumen = np.full(shape, np.inf, dtype=np.float32)
    d_outer = np.full(shape, np.inf, dtype=np.float32)
    axes = (xs, ys, zs)
    sp = np.array([xs[1] - xs[0] if len(xs) > 1 else 1.0, ys[1] - ys[0] if len(ys) > 1 else 1.0,
                   zs[1] - zs[0] if len(zs) > 1 else 1.0])
    origin = np.array([xs[0], ys[0], zs[0]])
    for b, t in zip(tree.branches, wall):
        grow = b.radius + t + margin
        lo = np.ceil((np.minimum(b.start, b.end) - grow - origin) / sp).astype(int)
        hi = np.floor((np.maximum(b.start, b.end) + grow - origin) / sp).astype(int) + 1
        lo = np.maximum(lo, 0)
        hi = np.minimum(hi, shape)
        if np.any(hi <= lo):
            continue
        px = axes[0][lo[0]:hi[0], None, None] - b.start[0]
        py = axes[1][None, lo[1]:hi[1], None] - b.start[1]
        pz = axes[2][None, None, lo[2]:hi[2]] - b.start[2]
        ab = b.end - b.start
        L2 = float(ab @ ab)
        t_ax = (px * ab[0] + py * ab[1] + pz * ab[2]) / L2 if L2 > 0 else np.zeros_like(px * py * pz)
        np.clip(t_ax, 0.0, 1.0, out=t_ax)
        dist = np.sqrt((px - t_ax * ab[0]) ** 2 + (py - t_ax * ab[1]) ** 2 + (pz - t_ax * ab[2]) ** 2)
        sl = (slice(lo[0], hi[0]), slice(lo[1], hi[1]), slice(lo[2], hi[2]))
        np.minimum(d_lumen[sl], dist - b.radius, out=d_lumen[sl])
        np.minimum(d_outer[sl], dist - b.radius - t, out=d_outer[sl])
    return d_lumen, d_outer


def _tree_sdf_tiled(tree: AirwayTree, ijk: np.ndarray, affine: np.ndarray, band: float,
                    tile: int = 32) -> tuple[np.ndarray, np.ndarray]:
    """:meth:`AirwayTree.sdf` at voxel indices ``ijk`` (N, 3), tile by tile with nearby branches only.

    A branch whose bounding box grown by ``band`` misses a tile is skipped by
    the tree's own band test for every point of that tile and cannot cover a
    foot point within ``band`` of it, so the values equal the whole tree's.
    """
    out = np.empty(len(ijk))
    exact = np.empty(len(ijk), dtype=bool)
    if len(ijk) == 0:
        return out, exact
    keys = ijk // tile
    kid = (keys[:, 0] * (keys[:, 1].max() + 1) + keys[:, 1]) * (keys[:, 2].max() + 1) + keys[:, 2]
    order = np.argsort(kid, kind="stable")
    starts = np.r_[0, np.nonzero(np.diff(kid[order]))[0] + 1, len(order)]
    blo = np.array([np.minimum(b.start, b.end) - b.radius for b in tree.branches]) - band
    bhi = np.array([np.maximum(b.start, b.end) + b.radius for b in tree.branches]) + band
    for s, e in zip(starts[:-1], starts[1:]):
        sel = order[s:e]
        pts = ijk[sel] @ affine[:3, :3].T + affine[:3, 3]
        plo, phi = pts.min(axis=0), pts.max(axis=0)
        near = np.all((blo <= phi) & (bhi >= plo), axis=1)
        sub = AirwayTree([b for b, k in zip(tree.branches, near) if k])
        out[sel], exact[sel] = sub.sdf(pts, band=band)
    return out, exact


def rasterise(tree: AirwayTree, params: PhantomParams, rng: np.random.Generator) -> Phantom:
    """CT (int16 HU) and ground truth of ``tree`` on the phantom's grid; see the module docstring."""
    affine, shape = _grid(tree, params)
    sp = np.diag(affine)[:3]
    xs, ys, zs = (affine[a, 3] + sp[a] * np.arange(shape[a]) for a in range(3))
    h = float(np.mean(sp))
    band = params.sdf_band_mm * MM
    wall = np.array([wall_thickness(b.radius, params) for b in tree.branches])
    box_margin = max(band, 3 * h * (1 + params.psf_sigma_voxels))

    # ---- airway distances: cheap per-branch boxes, then the exact tree SDF near the surface
    d_lumen, d_outer = _capsule_min_distance(tree, xs, ys, zs, box_margin, wall)
    ijk = np.argwhere(d_lumen < band)
    r_max = max(b.radius for b in tree.branches)
    vals, ex = _tree_sdf_tiled(tree, ijk, affine, max(band, r_max + 2 * h))
    sdf = np.full(shape, band, dtype=np.float32)
    exact = np.zeros(shape, dtype=bool)
    sdf[tuple(ijk.T)] = vals
    exact[tuple(ijk.T)] = ex
    sdf[sdf > band] = band  # outside values beyond the band are clipped ...
    exact &= sdf < band     # ... and are then not exact
    mask = (sdf < 0).astype(np.uint8)
    del ijk, vals, ex

    # ---- tissue layers, outside in
    x32, y32, z32 = (a.astype(np.float32) for a in (xs, ys, zs))
    hu = np.full(shape, params.hu_air, dtype=np.float32)
    bc, ba = _body_ellipse(params)
    s_body = _ellipse_sd(x32[:, None], y32[None, :], bc, ba).astype(np.float32)
    _mix(hu, np.float32(params.hu_fat), _coverage(s_body, h)[:, :, None])
    inner = ba - params.fat_thickness_mm * MM
    s_inner = _ellipse_sd(x32[:, None], y32[None, :], bc, inner).astype(np.float32)
    _mix(hu, np.float32(params.hu_soft_tissue), _coverage(s_inner, h)[:, :, None])

    s_lung = np.full(shape, np.inf, dtype=np.float32)
    for c, a, base in _lung_shapes(params):
        np.minimum(s_lung, _half_ellipsoid_sd(x32[:, None, None], y32[None, :, None], z32[None, None, :],
                                              c.astype(np.float32), a.astype(np.float32), np.float32(base)),
                   out=s_lung)
    lung = _coverage(s_lung, h)
    del s_lung
    texture = rng.standard_normal(shape, dtype=np.float32)
    corr = params.texture_correlation_mm * MM / sp
    texture = ndimage.gaussian_filter(texture, corr, mode="reflect", truncate=3.0)
    texture *= np.float32(params.texture_sigma_hu / max(float(texture.std()), 1e-12))
    texture += np.float32(params.hu_parenchyma)
    hu += lung * (texture - hu)
    del texture, lung

    _mix(hu, np.float32(params.hu_wall), _coverage(d_outer, h))
    del d_outer
    _mix(hu, np.float32(params.hu_air), _coverage(d_lumen, h))
    del d_lumen

    # ---- scanner: PSF, noise, quantisation
    if params.psf_sigma_voxels > 0:
        hu = ndimage.gaussian_filter(hu, params.psf_sigma_voxels, mode="nearest", truncate=3.0)
    if params.noise_sigma_hu > 0:
        hu += np.float32(params.noise_sigma_hu) * rng.standard_normal(shape, dtype=np.float32)
    np.rint(hu, out=hu)
    np.clip(hu, -1024, 3071, out=hu)
    ct = hu.astype(np.int16)
    del hu
    return Phantom(tree=tree, ct=Volume(ct, affine), mask=Volume(mask, affine.copy()),
                   sdf=Volume(sdf, affine.copy()), sdf_exact=Volume(exact, affine.copy()))


def make_phantom(params: PhantomParams, seed: int) -> Phantom:
    """Grow the tree and rasterise the CT; same ``params`` and ``seed`` give identical arrays."""
    rng = np.random.default_rng(seed)
    tree = grow_tree(params, rng)
    return rasterise(tree, params, rng)
