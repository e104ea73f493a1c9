"""Sampling-based local planner: from the camera to the farthest free visible point of a depth map.

Choice.  The paper used VP-STO (Jankowski et al. 2023: via-point stochastic trajectory optimisation with
CMA-ES).  VP-STO's PyPI package plans joint-space trajectories of rigid arms with time parametrisation;
a continuum scope that advances follow-the-leader instead needs a *curve* whose curvature never exceeds the
scope's bending limit.  So this module is a small VP-STO-like optimiser of our own: the path is a chain of
``segments`` constant-curvature arcs (piecewise-constant-curvature, the scope's own kinematic model, so the
curvature bound is exact by construction: every sample's curvature vector is clipped to ``kappa_max``),
and the cross-entropy method (Gaussian over the 2 x ``segments`` curvature components, elite refit,
``iterations`` rounds of ``samples`` paths) minimises

    cost = min_j |p_j - goal|                                     (m, the path is cut at its closest point)
         + w_collision * (max_j v_j + mean_j v_j)                 (m)
         + w_bending * L * mean |kappa|^2 / kappa_max^2           (m)

where ``v_j`` is how far the scope's collision sphere at path point ``j`` (radius ``scope_radius_mm`` +
``margin_mm``) reaches into the point cloud (KD-tree distance) or behind the observed surface (the depth
map at the point's pixel: space behind what the camera sees is not known to be free; points leaving the
field of view count as unknown too, except within ``unobserved_mm`` of the camera, where the scope itself
is).  Every random draw comes from ``numpy.random.default_rng(seed)``: same inputs and seed -> same path.

The goal (:func:`choose_goal`) is the farthest *free* visible point: every depth sample pulled back along its
ray by 1, 2, 3 and 5 times the scope radius + margin, kept when its clearance to the cloud is at least that; the far free
candidates form the openings of the lumen ahead: local maxima of the smoothed depth map (window
``opening_size`` of the image width) at >= ``far_fraction`` of the farthest, each owning the free candidates
nearest to it in the image; without a command the deepest opening wins, with an operator command (a unit
image direction, e.g. "left" = (-1, 0)) the opening lying farthest that way relative to the others.  The
goal is, among that opening's free candidates at >= ``deep_fraction`` of its deepest, the one nearest (in the
image) to its depth maximum (with a command and a single opening: the one lying farthest the commanded way).

Frames and units: camera frame OpenCV (x right, y down, z forward), metres; curvature 1/m.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any, Mapping

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from ..config.params import params_from_dict
from ..errors import ConfigError, InputError
from .perception import LocalCloud

MM = 1e-3


@dataclasses.dataclass(frozen=True)
class PlannerParams:
    """Planner knobs (lengths in mm as the names say, curvature 1/m)."""

    scope_radius_mm: float = 2.5          # collision-sphere radius: Ambu aScope 4 Regular, 5.0 mm outer diameter
    margin_mm: float = 0.2                # extra clearance the optimiser keeps (the collision flag uses the radius alone)
    kappa_max: float = 45.71              # 1/m, the scope's bending limit q1_max / (2 gamma l) (robot geometry)
    segments: int = 3                     # constant-curvature arcs per path
    step_mm: float = 1.0                  # spacing of the collision spheres along the path
    max_length_mm: float = 40.0           # longest path planned
    min_length_mm: float = 3.0            # shortest path planned
    samples: int = 48                     # paths per cross-entropy round
    iterations: int = 4                   # cross-entropy rounds
    elite_fraction: float = 0.15
    w_collision: float = 20.0
    w_bending: float = 0.002
    unobserved_mm: float = 4.0            # path points nearer than this (planar z) are not checked against the view
    far_fraction: float = 0.4             # openings: depth maxima at >= this fraction of the farthest free depth
    opening_size: float = 0.2             # openings: local-maximum window, fraction of the image width
    deep_fraction: float = 0.8            # the goal is among an opening's free points this deep (of its deepest)
    min_region_px: int = 3                # openings owning fewer free candidates (sub-sampled pixels) are ignored
    w_centre: float = 0.0                 # weight of the centring term (0: off)
    centre_mm: float = 2.0                # ... which charges path points nearer the cloud than radius + margin + this
    single_opening: str = "side"          # with a command and one opening: side = its deep point farthest the
                                          # commanded way; centre = its deepest spot (the command only picks openings)
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("scope_radius_mm", "kappa_max", "step_mm", "max_length_mm", "min_length_mm"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ConfigError(f"navigate.planner.{name} must be > 0, got {v!r}")
        for name in ("samples", "iterations", "segments"):
            if int(getattr(self, name)) < 1:
                raise ConfigError(f"navigate.planner.{name} must be >= 1")
        if not 0 < self.elite_fraction <= 1:
            raise ConfigError("navigate.planner.elite_fraction must be in (0, 1]")
        if not 0 < self.far_fraction <= 1:
            raise ConfigError("navigate.planner.far_fraction must be in (0, 1]")
        if self.min_length_mm > self.max_length_mm:
            raise ConfigError("navigate.planner.min_length_mm must be <= max_length_mm")
        if self.single_opening not in ("side", "centre"):
            raise ConfigError(f"navigate.planner.single_opening must be side or centre, got {self.single_opening!r}")
        if self.w_centre < 0 or self.centre_mm < 0:
            raise ConfigError("navigate.planner.w_centre and centre_mm must be >= 0")
        if self.margin_mm < 0 or self.unobserved_mm < 0:
            raise ConfigError("navigate.planner.margin_mm and unobserved_mm must be >= 0")

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None) -> "PlannerParams":
        return params_from_dict(cls, d, "navigate.planner")


@dataclasses.dataclass
class Goal:
    """The chosen goal: camera-frame point (m), its depth, its clearance to the cloud (m), region size (px)."""

    point: np.ndarray
    depth: float
    clearance: float
    region_px: int
    regions: int


@dataclasses.dataclass
class Plan:
    """A planned path in the camera frame.

    points: (M, 3) m, from the camera (first point = origin); tangents (M, 3) unit; arclength (M,) m;
    curvature: (segments, 2) curvature vector of each arc in its local frame, 1/m (|.| <= kappa_max);
    clearance: (M,) distance from each path point to the point cloud, m; collision_free: every sphere
    (scope radius) clear of the cloud and in front of the observed surface; cost: the optimiser's.
    """

    points: np.ndarray
    tangents: np.ndarray
    arclength: np.ndarray
    curvature: np.ndarray
    clearance: np.ndarray
    behind_surface: np.ndarray
    collision_free: bool
    cost: float
    goal: np.ndarray

    @property
    def length(self) -> float:
        return float(self.arclength[-1]) if len(self.arclength) else 0.0

    def max_curvature(self) -> float:
        return float(np.linalg.norm(self.curvature, axis=1).max()) if len(self.curvature) else 0.0

    def at(self, s: float) -> tuple[np.ndarray, np.ndarray]:
        """Point and unit tangent at arclength ``s`` (m), clamped to the path."""
        s = min(max(s, 0.0), self.length)
        i = int(np.searchsorted(self.arclength, s, side="right")) - 1
        i = min(max(i, 0), len(self.arclength) - 2) if len(self.arclength) > 1 else 0
        if len(self.arclength) < 2:
            return self.points[0].copy(), self.tangents[0].copy()
        w = (s - self.arclength[i]) / max(self.arclength[i + 1] - self.arclength[i], 1e-12)
        p = (1 - w) * self.points[i] + w * self.points[i + 1]
        t = (1 - w) * self.tangents[i] + w * self.tangents[i + 1]
        return p, t / np.linalg.norm(t)

    def to_world(self, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(points, tangents) in the world frame for a camera-to-world ``pose`` (4x4)."""
        R, t = pose[:3, :3], pose[:3, 3]
        return self.points @ R.T + t, self.tangents @ R.T


PULL_BACK = (1.0, 2.0, 3.0, 5.0)


def _candidates(cloud: LocalCloud, tree: cKDTree, back: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every depth sample pulled back along its ray by ``back`` x PULL_BACK m (a ray grazing an oblique wall
    needs more than ``back`` to clear it): (points (N, 3), clearance (N,), index (N, 2) (row, col))."""
    p = cloud.points
    n = np.linalg.norm(p, axis=1, keepdims=True)
    cs, ids = [], []
    pix = (cloud.pixels / cloud.stride).round().astype(int)[:, ::-1]         # (row, col) in the sub-sampled grid
    for f in PULL_BACK:
        c = p - f * back * p / np.maximum(n, 1e-12)
        ok = (n[:, 0] > f * back) & (c[:, 2] > 0)
        cs.append(c[ok])
        ids.append(pix[ok])
    c = np.concatenate(cs)
    idx = np.concatenate(ids)
    clear = tree.query(c)[0] if len(c) else np.zeros(0)
    return c, clear, idx


def choose_goal(cloud: LocalCloud, params: PlannerParams, command: np.ndarray | None = None,
                tree: cKDTree | None = None) -> Goal | None:
    """The farthest free visible point (camera frame), in the region the ``command`` points to; None if none."""
    if len(cloud.points) == 0:
        return None
    tree = tree or cKDTree(cloud.points)
    need = (params.scope_radius_mm + params.margin_mm) * MM
    c, clear, idx = _candidates(cloud, tree, need)
    free = clear >= need * 0.999
    if not free.any():
        return None
    c, clear, idx = c[free], clear[free], idx[free]
    z = c[:, 2]
    # openings of the lumen ahead: local maxima of the (smoothed) free depth image deeper than far_fraction of
    # the farthest; every free candidate at >= half that depth belongs to the opening nearest to it in the image
    h, w = cloud.depth.shape
    zs = ndimage.gaussian_filter(cloud.depth, sigma=max(1.0, w / 48))
    k = max(3, int(round(w * params.opening_size)))
    peaks = (zs == ndimage.maximum_filter(zs, size=k)) & (zs >= params.far_fraction * zs.max()) & (cloud.depth > 0)
    plab, npk = ndimage.label(ndimage.binary_dilation(peaks, iterations=1))
    cents = np.array([np.argwhere(plab == q).mean(axis=0) for q in range(1, npk + 1)]) if npk else \
        idx[[int(np.argmax(z))]].astype(float)
    near = z >= 0.5 * params.far_fraction * z.max()
    cand = np.flatnonzero(near)
    d2 = ((idx[cand][:, None, :] - cents[None, :, :]) ** 2).sum(axis=2)
    owner = np.argmin(d2, axis=1)
    sizes = np.bincount(owner, minlength=len(cents))
    regions = [q for q in range(len(cents)) if sizes[q] >= params.min_region_px] or [int(np.argmax(sizes))]
    if command is not None and len(regions) > 1:
        cmd = np.asarray(command, float)
        uv = cents[regions][:, ::-1]                                  # (u, v)
        pick = regions[int(np.argmax((uv - uv.mean(axis=0)) @ cmd))]
    else:
        depth_of = [z[cand[owner == q]].max() for q in regions]
        pick = regions[int(np.argmax(depth_of))]
    inside = cand[owner == pick]
    # among the opening's free points at >= deep_fraction of its deepest: the one nearest (in the image) to its deepest spot, the far centre of that lumen;
    # with a command and a single opening (the next bifurcation not resolved yet), its deep free point lying
    # farthest the commanded way, so the tip is already on that side when the two openings part
    deep = inside[z[inside] >= params.deep_fraction * z[inside].max()]
    if command is not None and len(regions) == 1 and params.single_opening == "side":
        j = deep[int(np.argmax(idx[deep][:, ::-1] @ np.asarray(command, float)))]
    else:
        j = deep[np.argmin(((idx[deep] - cents[pick]) ** 2).sum(axis=1))]
    return Goal(point=c[j].copy(), depth=float(z[j]), clearance=float(clear[j]), region_px=int(sizes[pick]),
                regions=len(regions))


def _rollout(K: np.ndarray, length: float, step: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Paths of (S, segments, 2) curvature vectors: points and tangents (S, n+1, 3), arclength (n+1,)."""
    S, nseg, _ = K.shape
    n = max(2, int(math.ceil(length / step)))
    ds = length / n
    seg = np.minimum((np.arange(n) * nseg) // n, nseg - 1)
    R = np.broadcast_to(np.eye(3), (S, 3, 3)).copy()
    P = np.zeros((S, n + 1, 3))
    T = np.zeros((S, n + 1, 3))
    T[:, 0] = R[:, :, 2]
    p = np.zeros((S, 3))
    for j in range(n):
        k = K[:, seg[j]]                                       # (S, 2) local curvature vector
        kn = np.linalg.norm(k, axis=1)
        a = kn * ds
        u = np.zeros((S, 3))                                   # rotation axis e_z x b, local frame
        nz = kn > 0
        u[nz, 0] = -k[nz, 1] / kn[nz]
        u[nz, 1] = k[nz, 0] / kn[nz]
        ux = np.zeros((S, 3, 3))
        ux[:, 0, 2], ux[:, 2, 0] = u[:, 1], -u[:, 1]
        ux[:, 1, 2], ux[:, 2, 1] = -u[:, 0], u[:, 0]
        ux[:, 0, 1], ux[:, 1, 0] = -u[:, 2], u[:, 2]
        half = 0.5 * a
        Rh = np.eye(3) + np.sin(half)[:, None, None] * ux + (1 - np.cos(half))[:, None, None] * (ux @ ux)
        R = R @ Rh
        p = p + ds * R[:, :, 2]
        R = R @ Rh
        P[:, j + 1] = p
        T[:, j + 1] = R[:, :, 2]
    return P, T, np.arange(n + 1) * ds


def _violations(P: np.ndarray, tree: cKDTree, cloud: LocalCloud, radius: float, unobserved: float
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per path point: distance to the cloud, how far the sphere reaches into the cloud, how far behind the view."""
    S, M, _ = P.shape
    flat = P.reshape(-1, 3)
    dist = tree.query(flat)[0].reshape(S, M) if tree.n else np.full((S, M), np.inf)
    into = np.maximum(0.0, radius - dist)
    cam = cloud.camera
    z = flat[:, 2]
    zs = np.maximum(z, 1e-9)
    u, v = cam.project_normalized(flat[:, 0] / zs, flat[:, 1] / zs)   # the camera's own model (lens included)
    h, w = cloud.depth.shape
    jj = np.rint(u / cloud.stride).astype(int)
    ii = np.rint(v / cloud.stride).astype(int)
    inside = (z > 0) & (jj >= 0) & (jj < w) & (ii >= 0) & (ii < h)
    d = np.zeros(len(flat))
    d[inside] = cloud.depth[ii[inside], jj[inside]]
    behind = np.where(inside, np.where(d > 0, np.maximum(0.0, z - (d - radius)), 0.0), radius)
    behind[z < unobserved] = 0.0
    return dist, into, behind.reshape(S, M)


def plan_path(cloud: LocalCloud, goal: np.ndarray, params: PlannerParams,
              tree: cKDTree | None = None) -> Plan:
    """Cross-entropy search over constant-curvature arc chains from the camera to ``goal`` (camera frame, m)."""
    goal = np.asarray(goal, float).reshape(3)
    if not np.all(np.isfinite(goal)) or goal[2] <= 0:
        raise InputError(f"planner goal must be finite and in front of the camera, got {goal.tolist()}")
    tree = tree or cKDTree(cloud.points if len(cloud.points) else np.zeros((0, 3)))
    rng = np.random.default_rng(params.seed)
    kmax = params.kappa_max
    r_opt = (params.scope_radius_mm + params.margin_mm) * MM
    r_col = params.scope_radius_mm * MM
    unobs = params.unobserved_mm * MM
    g = float(np.linalg.norm(goal))
    length = min(max(1.15 * g, params.min_length_mm * MM), params.max_length_mm * MM)
    # initial mean: the single arc tangent to the view axis through the goal (curvature 2 |g_perp| / |g|^2)
    perp = np.array([goal[0], goal[1]])
    mu = np.tile(2.0 * perp / max(g * g, 1e-12), (params.segments, 1))
    mu = _clip(mu[None], kmax)[0]
    sigma = np.full_like(mu, 0.5 * kmax)
    n_elite = max(1, int(round(params.elite_fraction * params.samples)))
    best = (np.inf, None)

    def evaluate(K):
        P, T, s = _rollout(K, length, params.step_mm * MM)
        dg = np.linalg.norm(P - goal, axis=2)
        cut = np.argmax(-dg, axis=1)                          # closest point to the goal: the path ends there
        M = P.shape[1]
        keep = np.arange(M)[None, :] <= cut[:, None]
        dist, into, behind = _violations(P, tree, cloud, r_opt, unobs)
        v = np.where(keep, into + behind, 0.0)
        cnt = keep.sum(axis=1)
        if params.w_centre > 0:      # centring: mean shortfall of the clearance below radius + margin + centre_mm
            v_c = np.where(keep & (P[:, :, 2] >= unobs), np.maximum(0.0, r_opt + params.centre_mm * MM - dist), 0.0)
            centre = params.w_centre * v_c.sum(axis=1) / cnt
        else:
            centre = 0.0
        bend = (np.linalg.norm(K, axis=2) ** 2).mean(axis=1) / kmax ** 2
        cost = dg[np.arange(len(K)), cut] + params.w_collision * (v.max(axis=1) + v.sum(axis=1) / cnt) \
            + params.w_bending * s[cut] * bend + centre
        return cost, P, T, s, cut

    for _ in range(params.iterations):
        K = mu[None] + sigma[None] * rng.standard_normal((params.samples, *mu.shape))
        K[0] = mu
        K = _clip(K, kmax)
        cost, P, T, s, cut = evaluate(K)
        order = np.argsort(cost, kind="stable")
        if cost[order[0]] < best[0]:
            i = order[0]
            best = (float(cost[i]), (K[i].copy(), P[i, : cut[i] + 1], T[i, : cut[i] + 1], s[: cut[i] + 1]))
        elite = K[order[:n_elite]]
        mu = elite.mean(axis=0)
        sigma = np.maximum(elite.std(axis=0), 0.02 * kmax)
    cost, (Kb, Pb, Tb, sb) = best
    if len(sb) < 2:                                           # the goal is at the camera: a one-step stub
        Pb, Tb, sb = np.vstack([Pb, Pb]), np.vstack([Tb, Tb]), np.array([0.0, 0.0])
    dist, into, behind = _violations(Pb[None], tree, cloud, r_col, unobs)
    free = bool((into.max() <= 0.0) and (behind.max() <= 0.0))
    return Plan(points=Pb, tangents=Tb, arclength=sb, curvature=Kb, clearance=dist[0], behind_surface=behind[0],
                collision_free=free, cost=cost, goal=goal)


def _clip(K: np.ndarray, kmax: float) -> np.ndarray:
    """Curvature vectors scaled down to |k| <= kmax (last axis)."""
    n = np.linalg.norm(K, axis=-1, keepdims=True)
    return K * np.minimum(1.0, kmax / np.maximum(n, 1e-12))


def free_centre(cloud: LocalCloud, params: PlannerParams, goal: np.ndarray, depth_m: float,
                tree: cKDTree | None = None, band_m: float = 1.5e-3) -> np.ndarray | None:
    """The centre of the free lumen ``depth_m`` ahead (camera frame, m), on the way to ``goal``; None if none.

    The free candidates of :func:`choose_goal` (depth samples pulled back along their rays, clearance to the
    cloud >= scope radius + margin) within ``band_m`` of the planar depth ``depth_m`` form the free cross-
    section(s) of the lumen there; the one (8-connected in the image) reaching nearest to the goal's pixel is
    the lumen the goal lies in, and its clearance^2-weighted mean point is its centre (the most central free
    points weigh most).  A tip steered to it stays mid-lumen and takes the goal's opening at a bifurcation;
    being a point of the anatomy (not of the view), it does not move as the view turns.
    """
    if len(cloud.points) == 0:
        return None
    tree = tree or cKDTree(cloud.points)
    need = (params.scope_radius_mm + params.margin_mm) * MM
    c, clear, idx = _candidates(cloud, tree, need)
    sel = (clear >= need * 0.999) & (np.abs(c[:, 2] - depth_m) <= band_m)
    if not sel.any():
        return None
    c, clear, idx = c[sel], clear[sel], idx[sel]
    h, w = cloud.depth.shape
    mask = np.zeros((h, w), bool)
    rr, cc = np.clip(idx[:, 0], 0, h - 1), np.clip(idx[:, 1], 0, w - 1)
    mask[rr, cc] = True
    lab, n = ndimage.label(ndimage.binary_dilation(mask, iterations=1), structure=np.ones((3, 3)))
    own = lab[rr, cc]
    g = np.asarray(goal, float)
    u, v = cloud.camera.project_normalized(g[0] / max(g[2], 1e-9), g[1] / max(g[2], 1e-9))
    gpx = np.array([v / cloud.stride, u / cloud.stride])
    d2 = ((np.stack([rr, cc], 1) - gpx) ** 2).sum(axis=1)
    pick = own[int(np.argmin(d2))]
    m = own == pick
    wgt = clear[m] ** 2
    return (c[m] * wgt[:, None]).sum(axis=0) / wgt.sum()
