"""Camera trajectories from the trachea to targets in the airway tree (ROOM method).

Pipeline of :func:`plan_path`
    1. **Target.**  A branch id (the path ends at the branch's last point) or a
       point (metres, world RAS+).  A point is mapped to the nearest centreline
       point whose lumen contains it (``|p - c| <= r(c) + target_tolerance_mm``);
       the path ends at that *centreline* point (the requested point and the
       distance are kept in :class:`TargetInfo`).
    2. **Route.**  The graph polylines from the root down to the target,
       concatenated (a child's first point is its parent's last), starting at
       the root's first point or ``start_offset_mm`` along it, cut at the target.
    3. **Smoothing** (:func:`smooth_route`), in millimetres internally.  The
       route is resampled every ``smoothing_step_mm`` (reference points ``C_i``)
       and the path points ``P_i`` solve the convex problem
       ``min sum |P_{i-1} - 2 P_i + P_{i+1}|^2 / h^3 + centring_weight * h * sum |P_i - C_i|^2``
       (discrete bending energy ``int kappa^2 ds`` plus a weak pull to the
       centreline) subject to **clearance** ``|P_i - C_i| <= min(r_i, -sdf(C_i)) - margin_i``
       (a ball inside the lumen around each reference point, so a point in it is at
       least ``margin_i`` from the wall) and **curvature**
       ``|P_{i-1} - 2 P_i + P_{i+1}| / h^2 <= curvature_safety * kappa_max``
       (second-order cones), by ADMM (:class:`_Admm`: one banded Cholesky solve
       per iteration).  The start point and start direction (along the trachea: the
       chord over the route's first 2 lumen radii, >= 5 mm) and the end point are fixed; the end direction is free.  When the
       discrete (Menger) curvature of the result still exceeds the aim (the path
       is shorter than the route, so its spacing is below ``h``) the aim is
       tightened and the problem re-solved.  When ADMM stalls, no path keeps
       both constraints: the least-bending path inside the balls is returned
       (clearance wins: never a path through the wall) and the curvature check
       fails there.  Then the true SDF (``sdf_fn``) is evaluated on the path:
       where the clearance is below the margin the balls shrink locally (the
       path is pulled back toward the centreline) and the solve resumes, up to
       ``relax_iterations`` times.  ``margin_i = min(max(clearance_fraction * r,
       clearance_min_mm), clearance_max_fraction * min(r, -sdf(C_i)))``.
    4. **Check.**  Curvature of the final C2 cubic spline through the smoothed
       points (``|r' x r''| / |r'|^3``, checked every ~0.1 mm and at every pose)
       must be ``<= kappa_max``; ``-sdf_fn`` at every path point and every pose
       must be ``>= margin``.  Failures make the target *unreachable*:
       ``unreachable: error`` raises a one-line :class:`InputError`;
       ``unreachable: nearest`` plans to the **nearest reachable target**: the
       route is cut ``nearest_backoff_mm`` before the first failing point (in
       route arclength) and re-planned, repeatedly, so the result is the deepest
       point of the same route the scope can reach (``TargetInfo.reached`` is
       False and ``note`` says why).  A target *point* outside every lumen by
       more than the tolerance maps, under ``nearest``, to the centreline point
       whose lumen surface is closest to it (min ``|p - c| - r(c)``).
    5. **Timing.**  Poses at ``rate_hz`` (10 Hz): the advance speed is
       ``speed_mm_s`` times a factor falling smoothly (raised cosine) to
       ``bifurcation_slowdown`` at a bifurcation (within
       ``bifurcation_distance_mm`` of it, measured along the path) and times
       ``1 - (1 - curvature_slowdown) * min(kappa / kappa_max, 1)``, so samples are
       denser at bifurcations and in bends.  Timestamps are ``k / rate_hz``
       seconds; the last pose is exactly at the target (that final step is
       shorter than the others).
    6. **Orientation.**  Camera +z (view) = path tangent.  Roll by parallel
       transport (rotation-minimising frame, double reflection method of Wang
       et al., ACM TOG 2008): no twist about the view axis, continuous, no flips.
       Initial roll: image up (camera -y) is the world direction closest to
       **anterior** (+y, RAS+) -- the usual bronchoscopic display, the posterior
       membranous wall of the trachea at 6 o'clock -- or superior
       (``image_up: superior``); when the view is within ~11 deg of that
       direction the other one is used.  Optional view jitter
       (``view_jitter_deg`` > 0): a seeded, temporally smooth (Gaussian,
       ``view_jitter_time_s``) random rotation about the camera x and y axes whose
       angle has that root-mean-square over the sequence; roll is untouched.
    7. **Joint space** (``joint_plan``, an option: ``joint_plan.enabled``, off in the default config): the poses of steps 5-6 become
       ``path_poses`` (what the shaft follows and the camera aims at) and the camera poses are the
       forward kinematics of a joint trajectory ``q(t)`` of the scope (:mod:`.joint_plan`: the
       constant-curvature bending segment with its base on the path, position/view trade-off,
       roll continuity, joint and rate limits, the scope body kept in the lumen), so the simulator
       can execute the plan; ``joint_plan`` in ``trajectory.json`` says how far it departs from
       the path.  ``clearance`` is then measured at those camera positions.

Poses are 4x4 camera-to-world in the OpenCV camera frame (x right, y down, z
forward), world RAS+ metres, as in :mod:`room_pipeline.conventions`.
All functions are pure; the caller writes files (``Trajectory.to_dict`` for
``metadata/trajectory.json``, :func:`timestamps_dict` for ``timestamps.json``,
``Trajectory.to_tum`` for a TUM trajectory).
"""
from __future__ import annotations

import dataclasses
import math
import os
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np
from scipy import sparse
from scipy.interpolate import CubicSpline
from scipy.ndimage import gaussian_filter1d, map_coordinates, maximum_filter1d
from scipy.spatial.transform import Rotation

from ..anatomy.centreline import CentrelineGraph
from ..conventions import MM, metadata_block
from ..errors import ConfigError, InputError
from ..io.tum import parse_tum, tum_text  # noqa: F401 (parse_tum re-exported for old imports)
from ..robot.kinematics import DEFAULT_GEOMETRY, ScopeGeometry

SdfFn = Callable[[np.ndarray], np.ndarray]

TARGET_MODES = ("leaves", "random_leaves", "points")
UNREACHABLE_MODES = ("error", "nearest")
IMAGE_UP = ("anterior", "superior")
_WORLD_UP = {"anterior": np.array([0.0, 1.0, 0.0]), "superior": np.array([0.0, 0.0, 1.0])}


# --------------------------------------------------------------------------- parameters


@dataclasses.dataclass
class TrajectoryParams:
    """Knobs of the trajectory planner; field names are the keys of ``conf/trajectory/default.yaml``.

    Lengths in millimetres (``_mm``), speeds mm/s, curvature 1/m, times s, angles deg.
    """

    targets: str = "random_leaves"       # leaves | random_leaves | points
    max_generation: int | None = 6       # leaves: terminal branches of the tree cut at this generation (null: all leaves)
    n: int = 3                           # random_leaves: how many
    seed: int = 0                        # random_leaves: RNG seed
    points: Any = None                   # points: [[x, y, z], ...] metres, or a Med-MPD target.txt path (mm), or a list of paths
    target_tolerance_mm: float = 1.0     # a target point may lie this far outside a centreline point's lumen
    unreachable: str = "nearest"         # error | nearest
    start_offset_mm: float = 10.0        # start this far along the root branch from its first point
    min_lumen_radius_mm: float = 3.5     # the route ends where the lumen radius falls below this (0 = off)
    kappa_max: float | None = None       # 1/m; null: the scope geometry's q1_max / (2 gamma l) = 45.71
    curvature_safety: float = 0.95       # the smoother aims at this fraction of kappa_max
    clearance_fraction: float = 0.25     # margin = max(fraction * r, clearance_min_mm) ...
    clearance_min_mm: float = 0.3
    clearance_max_fraction: float = 0.5  # ... clipped to this fraction of r and of -sdf at the centreline
    smoothing_step_mm: float = 0.5       # point spacing of the smoother
    centring_weight: float = 1e-4        # pull to the centreline vs bending energy, 1/mm^4
    max_iterations: int = 3000           # ADMM iterations per smoothing solve
    relax_iterations: int = 6            # local margin raises after checking against the SDF
    nearest_backoff_mm: float = 3.0      # unreachable: nearest: cut the route this far before a failure
    rate_hz: float = 10.0                # pose rate
    speed_mm_s: float = 5.0              # advance speed away from bifurcations, straight path
    bifurcation_slowdown: float = 0.5    # speed factor at a bifurcation
    bifurcation_distance_mm: float = 5.0 # slow-down zone half-length along the path
    curvature_slowdown: float = 0.5      # speed factor at kappa = kappa_max (linear in kappa)
    image_up: str = "anterior"           # anterior | superior: world direction of image up at the start
    view_jitter_deg: float = 0.0         # RMS angle of the smooth view-direction jitter (0: off)
    view_jitter_time_s: float = 1.0      # correlation time (Gaussian sigma) of the jitter
    jitter_seed: int = 0
    joint_plan: Any = None               # null: camera poses on the path | mapping (JointPlanParams keys): the
                                         # poses are the forward kinematics of a joint-space plan (planning/joint_plan.py)

    def __post_init__(self) -> None:
        def num(name: str, integer: bool = False, optional: bool = False):
            v = getattr(self, name)
            if v is None and optional:
                return
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ConfigError(f"trajectory.{name} must be a finite number, got {v!r}")
            if integer:
                if float(v) != int(v):
                    raise ConfigError(f"trajectory.{name} must be an integer, got {v!r}")
                setattr(self, name, int(v))
            else:
                setattr(self, name, float(v))

        for name in ("n", "seed", "max_iterations", "relax_iterations", "jitter_seed"):
            num(name, integer=True)
        num("max_generation", integer=True, optional=True)
        num("kappa_max", optional=True)
        for name in ("target_tolerance_mm", "start_offset_mm", "min_lumen_radius_mm", "curvature_safety", "clearance_fraction",
                     "clearance_min_mm", "clearance_max_fraction", "smoothing_step_mm", "centring_weight",
                     "nearest_backoff_mm", "rate_hz", "speed_mm_s", "bifurcation_slowdown",
                     "bifurcation_distance_mm", "curvature_slowdown", "view_jitter_deg", "view_jitter_time_s"):
            num(name)
        for name, choices in (("targets", TARGET_MODES), ("unreachable", UNREACHABLE_MODES), ("image_up", IMAGE_UP)):
            if getattr(self, name) not in choices:
                raise ConfigError(f"trajectory.{name} must be one of {', '.join(choices)}, got {getattr(self, name)!r}")
        positive = ("smoothing_step_mm", "rate_hz", "speed_mm_s", "nearest_backoff_mm", "view_jitter_time_s",
                    "n", "max_iterations")
        for name in positive:
            if getattr(self, name) <= 0:
                raise ConfigError(f"trajectory.{name} must be > 0, got {getattr(self, name)}")
        nonneg = ("target_tolerance_mm", "start_offset_mm", "min_lumen_radius_mm", "clearance_fraction", "clearance_min_mm",
                  "centring_weight", "bifurcation_distance_mm", "view_jitter_deg", "relax_iterations",
                  "max_generation")
        for name in nonneg:
            v = getattr(self, name)
            if v is not None and v < 0:
                raise ConfigError(f"trajectory.{name} must be >= 0, got {v}")
        for name in ("curvature_safety", "bifurcation_slowdown", "curvature_slowdown"):
            if not 0 < getattr(self, name) <= 1:
                raise ConfigError(f"trajectory.{name} must be in (0, 1], got {getattr(self, name)}")
        if not 0 <= self.clearance_max_fraction < 1:
            raise ConfigError(f"trajectory.clearance_max_fraction must be in [0, 1), got {self.clearance_max_fraction}")
        if self.kappa_max is not None and self.kappa_max <= 0:
            raise ConfigError(f"trajectory.kappa_max must be > 0 (1/m) or null, got {self.kappa_max}")
        if self.targets == "points" and self.points is None:
            raise ConfigError("trajectory.points is required when trajectory.targets is 'points'")
        if self.joint_plan is not None:
            from .joint_plan import JointPlanParams
            if not isinstance(self.joint_plan, Mapping):
                raise ConfigError(f"trajectory.joint_plan must be null or a mapping, got {self.joint_plan!r}")
            self.joint_plan = {str(k): v for k, v in self.joint_plan.items()}
            enabled = self.joint_plan.pop("enabled", True)
            if not isinstance(enabled, bool):
                raise ConfigError(f"trajectory.joint_plan.enabled must be true or false, got {enabled!r}")
            JointPlanParams.from_dict(self.joint_plan)
            if not enabled:                  # the section's settings are checked, then the path poses are used
                self.joint_plan = None
        if self.points is not None and not isinstance(self.points, (str, os.PathLike, list, tuple, np.ndarray)):
            raise ConfigError(f"trajectory.points must be a list of [x, y, z] (m) or a target file path, got {self.points!r}")

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None) -> "TrajectoryParams":
        """Build from a config section; an unknown key raises :class:`ConfigError` naming it."""
        d = dict(d or {})
        known = [f.name for f in dataclasses.fields(cls)]
        for key in d:
            if key not in known:
                raise ConfigError(f"trajectory: unknown config key '{key}' (known: {', '.join(known)})")
        return cls(**d)

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        if isinstance(self.points, np.ndarray):
            d["points"] = self.points.tolist()
        elif isinstance(self.points, os.PathLike):
            d["points"] = os.fspath(self.points)
        return d


# --------------------------------------------------------------------------- SDF evaluators


def volume_sdf_fn(volume, outside: float = 1.0) -> SdfFn:
    """Trilinear interpolation of an SDF :class:`~room_pipeline.io.volume.Volume` (metres).

    Points outside the grid read ``outside`` metres (outside the lumen).
    """
    data = np.asarray(volume.data, dtype=np.float64)
    inv = np.linalg.inv(volume.affine)

    def fn(points: np.ndarray) -> np.ndarray:
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        ijk = p @ inv[:3, :3].T + inv[:3, 3]
        return map_coordinates(data, ijk.T, order=1, mode="constant", cval=float(outside), prefilter=False)

    return fn


def as_sdf_fn(sdf) -> SdfFn:
    """An SDF evaluator ``(N, 3) metres -> (N,) metres`` from a Volume, an AirwayTree or a callable.

    A callable may return ``(sdf, exact)`` like :meth:`AirwayTree.sdf`; the first item is used.
    """
    from ..anatomy.tree import AirwayTree
    from ..io.volume import Volume

    if isinstance(sdf, Volume):
        return volume_sdf_fn(sdf)
    if isinstance(sdf, AirwayTree):
        return lambda p: sdf.sdf(p)[0]
    if not callable(sdf):
        raise ConfigError(f"sdf_fn must be a callable, a Volume or an AirwayTree, got {type(sdf).__name__}")

    def fn(points: np.ndarray) -> np.ndarray:
        out = sdf(np.asarray(points, dtype=np.float64).reshape(-1, 3))
        if isinstance(out, tuple):
            out = out[0]
        return np.asarray(out, dtype=np.float64).reshape(-1)

    return fn


# --------------------------------------------------------------------------- targets


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


def map_target_point(graph: CentrelineGraph, point, tolerance: float, nearest: bool = False
                     ) -> tuple[int, float, np.ndarray, float]:
    """Map a target point (metres) to a centreline point: ``(branch id, arclength in branch, point, distance)``.

    The chosen centreline point is the nearest one whose lumen (radius ``r``)
    contains the target within ``tolerance`` (``|p - c| <= r + tolerance``).
    If there is none: :class:`InputError`, or with ``nearest`` the centreline
    point whose lumen surface is nearest (min ``|p - c| - r``).
    """
    p = np.asarray(point, dtype=np.float64).reshape(3)
    A, B, rA, rB, bid, s0 = _graph_segments(graph)
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


def select_targets(graph: CentrelineGraph, params: TrajectoryParams) -> list:
    """The configured targets: branch ids (leaves, random_leaves) or (3,) points in metres (points)."""
    if params.targets == "points":
        return list(_points_from_config(params.points))
    g = params.max_generation
    pool = [b.id for b in graph.branches
            if (g is None or b.generation <= g) and (not graph.children(b.id) or b.generation == g)]
    if not pool:
        raise ConfigError(f"trajectory: no leaves up to generation {g}")
    if params.targets == "leaves":
        return pool
    rng = np.random.default_rng(params.seed)
    return [int(i) for i in rng.choice(pool, size=min(params.n, len(pool)), replace=False)]


# --------------------------------------------------------------------------- route


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


# --------------------------------------------------------------------------- smoothing


@dataclasses.dataclass
class SmoothResult:
    """Output of :func:`smooth_route` (millimetres inside, metres here).

    Attributes:
        points: (N, 3) smoothed path, metres.
        route_s: (N,) route arclength each point projects to, metres.
        margin: (N,) required clearance, metres.
        clearance: (N,) ``-sdf_fn`` at the points, metres.
        max_curvature: discrete (Menger) curvature max, 1/m.
        ok_clearance, ok_curvature: whether each holds.
        fail_index: first failing point, -1 if none.
        iterations: ADMM iterations in all.
    """

    points: np.ndarray
    route_s: np.ndarray
    margin: np.ndarray
    clearance: np.ndarray
    max_curvature: float
    ok_clearance: bool
    ok_curvature: bool
    fail_index: int
    iterations: int


def menger_curvature(points: np.ndarray) -> np.ndarray:
    """Curvature of the circle through each point and its neighbours (N,), ends 0, in 1/units."""
    p = np.asarray(points, dtype=np.float64)
    out = np.zeros(len(p))
    if len(p) < 3:
        return out
    a = p[1:-1] - p[:-2]
    b = p[2:] - p[1:-1]
    c = p[2:] - p[:-2]
    cross = np.linalg.norm(np.cross(a, b), axis=1)
    den = np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1) * np.linalg.norm(c, axis=1)
    out[1:-1] = np.where(den > 0, 2.0 * cross / np.maximum(den, 1e-300), 0.0)
    return out


def _second_diff(N: int) -> sparse.csr_matrix:
    e = np.ones(N)
    return sparse.diags([e[:-2], -2 * e[:-2], e[:-2]], [0, 1, 2], shape=(N - 2, N)).tocsr()


def _banded_upper(A: sparse.spmatrix, u: int) -> np.ndarray:
    """Upper banded storage of a symmetric sparse matrix (for scipy.linalg.cholesky_banded)."""
    n = A.shape[0]
    ab = np.zeros((u + 1, n))
    A = A.tocsr()
    for d in range(u + 1):
        ab[u - d, d:] = A.diagonal(d)
    return ab


class _Admm:
    """ADMM for  min (1/h^3)|D2 P|^2 + lam h |P - C|^2  s.t.  |P_i - C_i| <= rho_i,  |D2 P_i| / h^2 <= k.

    Millimetres.  Both constraint sets are convex (balls around the reference
    centreline points; second-order cones on the discrete curvature vectors),
    and the objective is a convex quadratic, so the problem is convex and ADMM
    (scaled form, residual balancing) converges to its optimum when it is
    feasible.  The x-update is one banded Cholesky solve shared by x, y, z.
    """

    def __init__(self, C: np.ndarray, fixed: np.ndarray, h: float, lam: float):
        self.C, self.h, self.lam = C, h, lam
        N = len(C)
        self.N = N
        self.free = np.flatnonzero(~fixed)
        self.fixed = np.flatnonzero(fixed)
        D2 = _second_diff(N)
        self.D2f = D2[:, self.free].tocsr()
        self.D2fT = self.D2f.T.tocsr()
        self.c_fix = D2[:, self.fixed] @ C[self.fixed]  # fixed points' part of D2 P
        self.Pfix = C[self.fixed]
        self.Q = (self.D2fT @ self.D2f).tocsc()
        self.rho1 = 1.0 / h ** 3
        self.rho2 = 1.0 * h
        self._factor()

    def _factor(self) -> None:
        from scipy.linalg import cholesky_banded
        h = self.h
        F = len(self.free)
        A = self.Q * (2.0 / h ** 3 + self.rho2 / h ** 4) + sparse.identity(F) * (2.0 * self.lam * h + self.rho1)
        self.chol = cholesky_banded(_banded_upper(A, 2))

    def solve(self, radius: np.ndarray, kappa: float, P0: np.ndarray | None = None, max_iter: int = 3000,
              tol: float = 1e-5) -> tuple[np.ndarray, bool, int]:
        """Return (P (N,3) with P_free projected into the balls, converged, iterations)."""
        from scipy.linalg import cho_solve_banded
        h, lam = self.h, self.lam
        Cf = self.C[self.free]
        rad = radius[self.free]
        P = (self.C if P0 is None else P0).copy()
        Z1 = P[self.free].copy()
        U1 = np.zeros_like(Z1)
        W = (self.D2f @ Z1 + self.c_fix) / h ** 2
        Z2 = W.copy()
        U2 = np.zeros_like(Z2)
        rhs0 = -(2.0 / h ** 3) * (self.D2fT @ self.c_fix) + 2.0 * lam * h * Cf
        converged = False
        it = 0
        history: list[float] = []
        for it in range(1, max_iter + 1):
            b = rhs0 + self.rho1 * (Z1 - U1) + (self.rho2 / h ** 2) * (self.D2fT @ (Z2 - U2 - self.c_fix / h ** 2))
            X = cho_solve_banded((self.chol, False), b)
            # balls around the reference points
            v = X + U1 - Cf
            nv = np.linalg.norm(v, axis=1)
            Z1_old = Z1
            Z1 = Cf + v * np.minimum(1.0, rad / np.maximum(nv, 1e-300))[:, None]
            # curvature cones
            W = (self.D2f @ X + self.c_fix) / h ** 2
            w = W + U2
            nw = np.linalg.norm(w, axis=1)
            Z2_old = Z2
            Z2 = w * np.minimum(1.0, kappa / np.maximum(nw, 1e-300))[:, None]
            R1 = X - Z1
            R2 = W - Z2
            U1 += R1
            U2 += R2
            if it % 10 == 0 or it == max_iter:
                r_p = max(float(np.abs(R1).max()), float(np.abs(R2).max()) * h ** 2)
                s_d = max(float(np.abs(Z1 - Z1_old).max()), float(np.abs(Z2 - Z2_old).max()) * h ** 2)
                if r_p < tol and s_d < tol:
                    converged = True
                    break
                if it % 250 == 0:  # stalled primal residual: the constraints cannot all hold
                    history.append(r_p)
                    if len(history) >= 4 and r_p > 100 * tol and r_p > 0.5 * history[-4]:
                        break
                if it % 50 == 0:  # residual balancing
                    if r_p > 10 * s_d and self.rho1 < 1e6 / h ** 3:
                        self.rho1 *= 2.0; self.rho2 *= 2.0; U1 /= 2.0; U2 /= 2.0; self._factor()
                    elif s_d > 10 * r_p and self.rho1 > 1e-3 / h ** 3:
                        self.rho1 /= 2.0; self.rho2 /= 2.0; U1 *= 2.0; U2 *= 2.0; self._factor()
        P = P.copy()
        P[self.fixed] = self.Pfix
        P[self.free] = Z1  # inside the balls: the clearance holds whatever the convergence
        return P, converged, it


def smooth_route(route_points: np.ndarray, route_radius: np.ndarray, route_s: np.ndarray,
                 sdf_fn: SdfFn, kappa_max: float, params: TrajectoryParams) -> SmoothResult:
    """Smooth a route polyline (metres) under the curvature bound and the clearance margin.

    See the module docstring, step 3.  Returns the smoothed points and which
    constraint, if any, fails (checked with the discrete curvature and ``sdf_fn``).
    """
    mm = 1.0 / MM
    V = np.asarray(route_points, dtype=np.float64) * mm
    Rv = np.asarray(route_radius, dtype=np.float64) * mm
    Sv = np.asarray(route_s, dtype=np.float64) * mm
    L = Sv[-1]
    h0 = params.smoothing_step_mm
    N = max(2, int(math.ceil(L / h0)) + 1)
    s_ref = np.linspace(0.0, L, N)
    C = np.stack([np.interp(s_ref, Sv, V[:, k]) for k in range(3)], axis=1)
    if N >= 3:
        # the fixed start direction: the chord over the route's first stretch (2 lumen radii, >= 5 mm), not the
        # centreline's first 0.5 mm, which bends toward the rim where a scan cuts the trachea (CASE091: 124 1/m)
        reach = min(L, max(5.0, 2.0 * float(Rv[0])))
        d = np.array([np.interp(reach, Sv, V[:, k]) for k in range(3)]) - C[0]
        if np.linalg.norm(d) > 1e-9:
            C[1] = C[0] + (s_ref[1] - s_ref[0]) * d / np.linalg.norm(d)
    # lumen clearance of the reference centreline points, from the SDF: ball radii and margin clipping
    clear_c = -sdf_fn(C * MM) * mm
    r_c = np.interp(s_ref, Sv, Rv)
    margin = np.minimum(np.maximum(params.clearance_fraction * r_c, params.clearance_min_mm),
                        params.clearance_max_fraction * np.minimum(r_c, np.maximum(clear_c, 0.0)))
    margin = np.maximum(margin, 0.0)
    buffer = min(0.01, 0.1 * params.clearance_min_mm + 1e-3)  # mm
    radius = np.maximum(np.minimum(r_c, clear_c) - margin - buffer, 0.0)
    fixed = np.zeros(N, dtype=bool)
    fixed[[0, min(1, N - 1), N - 1]] = True
    kmax_mm = kappa_max * MM
    iters = 0
    P = C.copy()
    clear = clear_c
    if N >= 5:
        h = L / (N - 1)
        admm = _Admm(C, fixed, h, params.centring_weight)
        k_aim = params.curvature_safety * kmax_mm
        for relax in range(params.relax_iterations + 1):
            for _ in range(4):  # tighten the aim if the discrete curvature (true spacing) exceeds the bound
                P_try, conv, it = admm.solve(radius, k_aim, P0=P, max_iter=params.max_iterations)
                iters += it
                if not conv:
                    break
                P = P_try
                k_now = float(menger_curvature(P).max())
                if k_now <= params.curvature_safety * kmax_mm * 1.001:
                    break
                k_aim *= params.curvature_safety * kmax_mm / k_now
            if not conv:
                # no path keeps both: the least-bending path in the clearance balls shows where the
                # bend is too sharp (clearance wins, the curvature check below fails)
                P, _, it = admm.solve(radius, np.inf, P0=P, max_iter=params.max_iterations)
                iters += it
            clear = -sdf_fn(P * MM) * mm
            deficit = np.where(fixed, 0.0, margin - clear)
            if relax == params.relax_iterations or not (deficit > 0).any():
                break
            pull = maximum_filter1d(np.where(deficit > 0, deficit + buffer, 0.0), size=max(3, int(2.0 / h) | 1))
            radius = np.maximum(radius - pull, 0.0)  # pull back toward the centreline there
    kap = menger_curvature(P)
    bad_c = (clear < margin) | (clear <= 0)
    bad_c[fixed] = clear[fixed] <= 0  # fixed ends sit on the centreline: only fail if outside the lumen
    bad_k = kap > kmax_mm
    bad = np.flatnonzero(bad_c | bad_k)
    return SmoothResult(P * MM, s_ref * MM, margin * MM, clear * MM, float(kap.max()) * mm,
                        not bad_c.any(), not bad_k.any(), int(bad[0]) if len(bad) else -1, iters)



# --------------------------------------------------------------------------- frames and timing


def rotation_minimising_frames(points: np.ndarray, tangents: np.ndarray, y0: np.ndarray) -> np.ndarray:
    """Rotation-minimising frames (double reflection, Wang et al. 2008) -> (T, 3, 3) rotations.

    Columns are the OpenCV camera axes: x right, y down, z = the unit tangent.
    ``y0`` (unit, perpendicular to ``tangents[0]``) is the first camera y axis.
    """
    t = np.asarray(tangents, dtype=np.float64)
    t = t / np.linalg.norm(t, axis=1, keepdims=True)
    x = np.asarray(points, dtype=np.float64)
    out = np.empty((len(t), 3, 3))
    y = np.asarray(y0, dtype=np.float64)
    for i in range(len(t)):
        if i:
            v1 = x[i] - x[i - 1]
            c1 = float(v1 @ v1)
            if c1 > 1e-24:
                yl = y - (2.0 / c1) * (v1 @ y) * v1
                tl = t[i - 1] - (2.0 / c1) * (v1 @ t[i - 1]) * v1
            else:
                yl, tl = y, t[i - 1]
            v2 = t[i] - tl
            c2 = float(v2 @ v2)
            y = yl - (2.0 / c2) * (v2 @ yl) * v2 if c2 > 1e-24 else yl
            y = y - (y @ t[i]) * t[i]  # keep orthonormal against rounding
            y /= np.linalg.norm(y)
        out[i, :, 2] = t[i]
        out[i, :, 1] = y
        out[i, :, 0] = np.cross(y, t[i])
    return out


def initial_down(tangent: np.ndarray, image_up: str = "anterior") -> np.ndarray:
    """Camera +y (image down) for a view along ``tangent`` with image up nearest ``image_up`` (see module doc)."""
    t = np.asarray(tangent, dtype=np.float64) / np.linalg.norm(tangent)
    for name in (image_up, "superior" if image_up == "anterior" else "anterior"):
        up = _WORLD_UP[name]
        perp = up - (up @ t) * t
        if np.linalg.norm(perp) > 0.2:  # view more than ~11.5 deg away from this up direction
            return -perp / np.linalg.norm(perp)
    e = np.eye(3)[int(np.argmin(np.abs(t)))]
    perp = e - (e @ t) * t
    return -perp / np.linalg.norm(perp)


def _speed_profile(s: np.ndarray, kappa: np.ndarray, junctions: np.ndarray, kappa_max: float,
                   params: TrajectoryParams) -> np.ndarray:
    """Advance speed (m/s) at path arclengths ``s`` (m)."""
    v = np.full(len(s), params.speed_mm_s * MM)
    D = params.bifurcation_distance_mm * MM
    if len(junctions) and D > 0:
        d = np.abs(s[:, None] - junctions[None]).min(axis=1)
        ramp = 0.5 * (1.0 + np.cos(np.pi * np.minimum(d / D, 1.0)))  # 1 at the bifurcation, 0 beyond D
        v *= 1.0 - (1.0 - params.bifurcation_slowdown) * ramp
    v *= 1.0 - (1.0 - params.curvature_slowdown) * np.minimum(np.abs(kappa) / kappa_max, 1.0)
    return v


# --------------------------------------------------------------------------- trajectory


@dataclasses.dataclass
class Trajectory:
    """A timestamped camera path.

    Attributes:
        timestamps: (T,) seconds from 0 at ``rate_hz``.
        poses: (T, 4, 4) camera-to-world, OpenCV camera frame, world RAS+ metres.
        arclength: (T,) along the smoothed path, metres.
        branch_id: (T,) graph branch at each pose (nearest route vertex).
        clearance: (T,) ``-sdf`` at the camera centre, metres (distance to the wall).
        curvature: (T,) path curvature, 1/m.
        speed: (T,) advance speed, m/s.
        margin: (T,) required clearance, metres.
        target: :class:`TargetInfo`.
        kappa_max: the curvature bound used, 1/m.
        rate_hz: pose rate.
        max_curvature: max over the whole spline (checked every ~0.1 mm), 1/m.
        route_branches: graph branch ids from the root to the target.
        params: the :class:`TrajectoryParams` as a dict.
    """

    timestamps: np.ndarray
    poses: np.ndarray
    arclength: np.ndarray
    branch_id: np.ndarray
    clearance: np.ndarray
    curvature: np.ndarray
    speed: np.ndarray
    margin: np.ndarray
    target: TargetInfo
    kappa_max: float
    rate_hz: float
    max_curvature: float
    route_branches: list
    params: dict = dataclasses.field(default_factory=dict)
    start: dict = dataclasses.field(default_factory=dict)
    path_poses: np.ndarray | None = None     # (T, 4, 4) the smoothed path's poses (rotation-minimising, no jitter)
    joints: np.ndarray | None = None         # (T, 3) joint plan [q1 m, q2 rad, q3 m] (joint_plan on)
    joint_plan: dict | None = None           # its report (planning/joint_plan.py)

    @property
    def positions(self) -> np.ndarray:
        return self.poses[:, :3, 3]

    @property
    def length(self) -> float:
        return float(self.arclength[-1])

    @property
    def duration(self) -> float:
        return float(self.timestamps[-1])

    @property
    def min_clearance(self) -> float:
        return float(self.clearance.min())

    def summary(self) -> dict:
        jp = {} if self.joint_plan is None else {
            "joint_plan_departure_median_mm": self.joint_plan["departure_from_path_mm"]["median"],
            "joint_plan_departure_max_mm": self.joint_plan["departure_from_path_mm"]["max"],
            "joint_plan_view_departure_median_deg": self.joint_plan["view_departure_from_path_deg"]["median"]}
        return {**jp, "frames": int(len(self.timestamps)), "duration_s": self.duration, "length_m": self.length,
                "max_curvature_per_m": float(self.max_curvature), "kappa_max_per_m": float(self.kappa_max),
                "min_clearance_m": self.min_clearance,
                "min_clearance_minus_margin_m": float((self.clearance - self.margin).min()),
                "route_branches": [int(b) for b in self.route_branches]}

    def to_dict(self) -> dict:
        """Content of ``sequence_YYY/metadata/trajectory.json``."""
        return {
            "description": "camera trajectory: timestamped 4x4 camera-to-world poses along the smoothed airway path",
            "conventions": metadata_block(),
            "units": {"timestamp": "s", "position": "m", "arclength": "m", "clearance": "m",
                      "margin": "m", "curvature": "1/m", "speed": "m/s", "rate": "Hz"},
            "pose": "4x4 camera-to-world; camera frame OpenCV (x right, y down, z forward = view direction); "
                    "world RAS+ metres",
            "orientation": ("view along the path tangent; roll by parallel transport (rotation-minimising frame); "
                            f"image up (camera -y) nearest world {self.params.get('image_up', 'anterior')} at the start")
                           + ("" if self.joints is None else
                              "; that is path_pose: pose is the forward kinematics of the joint plan q aimed at it "
                              "(joint_plan)"),
            "joint_plan": self.joint_plan,
            "rate_hz": float(self.rate_hz),
            "target": self.target.to_dict(),
            "start": self.start,
            "summary": self.summary(),
            "params": self.params,
            "frames": [{"index": i, "timestamp": float(self.timestamps[i]),
                        "pose": np.round(self.poses[i], 12).tolist(),
                        "arclength": float(self.arclength[i]), "branch_id": int(self.branch_id[i]),
                        "clearance": float(self.clearance[i]), "curvature": float(self.curvature[i]),
                        "speed": float(self.speed[i]),
                        **({} if self.path_poses is None else {"path_pose": np.round(self.path_poses[i], 12).tolist()}),
                        **({} if self.joints is None else {"q": [float(v) for v in self.joints[i]]})}
                       for i in range(len(self.timestamps))],
        }

    def to_tum(self) -> str:
        """TUM RGB-D trajectory text: ``timestamp tx ty tz qx qy qz qw`` per line (camera-to-world, m, s)."""
        return tum_text(self.timestamps, self.poses)


def timestamps_dict(traj: Trajectory) -> dict:
    """Content of ``timestamps.json``: frame index -> time in seconds."""
    return {"units": "s", "rate_hz": float(traj.rate_hz), "count": int(len(traj.timestamps)),
            "timestamps": [float(t) for t in traj.timestamps]}


def _kappa_max(params: TrajectoryParams, geometry: ScopeGeometry | None) -> float:
    if params.kappa_max is not None:
        return float(params.kappa_max)
    return (geometry or DEFAULT_GEOMETRY).kappa_max


def _resolve_target(graph: CentrelineGraph, target, params: TrajectoryParams) -> TargetInfo:
    if isinstance(target, (int, np.integer)) and not isinstance(target, bool):
        try:
            b = graph.branch(int(target))
        except KeyError:
            raise InputError(f"target branch {int(target)} is not in the centreline graph") from None
        return TargetInfo("branch", b.id, b.points[-1].copy(), b.points[-1].copy())
    p = np.asarray(target, dtype=np.float64).reshape(-1)
    if p.shape != (3,) or not np.all(np.isfinite(p)):
        raise InputError(f"a target must be a branch id or 3 finite coordinates in metres, got {target!r}")
    bid, s, c, d = map_target_point(graph, p, params.target_tolerance_mm * MM,
                                    nearest=params.unreachable == "nearest")
    r = np.interp(s, np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(graph.branch(bid).points, axis=0),
                                                                      axis=1))]), graph.branch(bid).radius)
    info = TargetInfo("point", bid, c, p, d)
    info._s = s  # type: ignore[attr-defined]
    if d > r + params.target_tolerance_mm * MM:
        info.reached = False
        info.stop_reason = "target_outside_lumen"
        info.note = (f"target {(d - r) / MM:.1f} mm outside the lumen (tolerance {params.target_tolerance_mm:g} mm): "
                     "nearest airway centreline point used")
    return info


def _branch_arclength(graph: CentrelineGraph, info: TargetInfo) -> float:
    s = getattr(info, "_s", None)
    return float(graph.branch(info.branch_id).length if s is None else s)


def _fail_message(res: SmoothResult, route: _Route, kappa_max: float) -> str:
    i = max(res.fail_index, 0)
    s = float(res.route_s[i])
    b = int(route.branch[min(np.searchsorted(route.s, s), len(route.s) - 1)])
    if not res.ok_curvature:
        return (f"needs a bend of curvature {res.max_curvature:.1f} 1/m > kappa_max {kappa_max:.1f} 1/m "
                f"near branch {b}, {s / MM:.1f} mm along the route")
    return (f"cannot keep the clearance margin ({res.margin[i] / MM:.2f} mm; "
            f"{res.clearance[i] / MM:.2f} mm) near branch {b}, {s / MM:.1f} mm along the route")


def read_start_pose(path: str | os.PathLike) -> np.ndarray:
    """A Med-MPD ``start*.txt`` (4x4 pose, translation in mm, world frame of the mask) -> 4x4 with metres."""
    path = os.fspath(path)
    if not os.path.exists(path):
        raise InputError(f"start pose file not found: {path}")
    try:
        T = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except ValueError as exc:
        raise InputError(f"{path}: start pose must be a 4x4 matrix of numbers (mm): {exc}") from exc
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise InputError(f"{path}: start pose must be a finite 4x4 matrix, got shape {T.shape}")
    T = T.copy()
    T[:3, 3] *= MM
    return T


def _start(graph: CentrelineGraph, info: TargetInfo, params: TrajectoryParams, start) -> tuple[float, dict]:
    """Arclength along the route (from the root's first point) where the path starts, and its description."""
    chain = graph.path_to(info.branch_id)
    if start is None:
        off = params.start_offset_mm * MM
        doc = {"kind": "root", "offset_mm": round(off / MM, 6), "note": ""}
        if off > 0 and off >= 0.5 * graph.root.length:
            # a trachea cut just above the carina: start halfway down what there is
            clipped = 0.5 * graph.root.length
            doc.update(offset_mm=round(clipped / MM, 6),
                       note=f"start_offset_mm {params.start_offset_mm:g} mm clipped to {clipped / MM:.1f} mm: the "
                            f"root branch (trachea) is only {graph.root.length / MM:.1f} mm long")
            off = clipped
        return off, doc
    T = np.asarray(start, dtype=np.float64)
    p = T[:3, 3] if T.shape == (4, 4) else T.reshape(3)
    tol = params.target_tolerance_mm * MM
    bid, s_b, c, d = map_target_point(graph, p, tol, nearest=True)
    b = graph.branch(bid)
    sb = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(b.points, axis=0), axis=1))])
    r = float(np.interp(s_b, sb, b.radius))
    where = ", ".join(f"{v / MM:.1f}" for v in p)
    if d > r + tol:
        raise InputError(f"start pose ({where}) mm is {(d - r) / MM:.1f} mm outside the airway lumen "
                         f"(nearest: branch {bid})")
    ids = [x.id for x in chain]
    if bid not in ids:
        raise InputError(f"start pose ({where}) mm lies in branch {bid}, which is not on the route from the trachea "
                         f"to target branch {info.branch_id} (branches {ids})")
    off = sum(x.length for x in chain[:ids.index(bid)]) + s_b
    return off, {"kind": "user_pose", "position": np.round(p, 9).tolist(), "branch_id": int(bid),
                 "offset_mm": round(off / MM, 6), "distance_to_centreline_mm": round(d / MM, 4),
                 "note": "route starts at the centreline point nearest the given start pose; its orientation "
                         "is not used (the view follows the route)"}


def plan_path(graph: CentrelineGraph, target, sdf_fn, params: TrajectoryParams | None = None,
              geometry: ScopeGeometry | None = None, start=None) -> Trajectory:
    """Plan one trajectory from the trachea entry to ``target`` (a branch id or an (3,) point in metres).

    ``sdf_fn``: ``(N, 3) metres -> (N,) metres`` (negative in the lumen), or a
    :class:`Volume` / :class:`AirwayTree` (see :func:`as_sdf_fn`).  Raises
    :class:`InputError` for an unreachable target unless ``params.unreachable``
    is 'nearest' (module docstring, step 4).  ``start``: a user start pose (4x4, metres, world) or
    position (3,); the route starts at the centreline point nearest it, which must lie on the way from the
    trachea to the target.  Without it the route starts ``start_offset_mm`` down the root branch (clipped to
    half that branch when the trachea is shorter).
    """
    params = params or TrajectoryParams()
    fn = as_sdf_fn(sdf_fn)
    kmax = _kappa_max(params, geometry)
    info = _resolve_target(graph, target, params)
    offset, start_doc = _start(graph, info, params, start)
    full = _route(graph, info.branch_id, _branch_arclength(graph, info), offset)
    route = full
    first_fail = ""
    reason = ""
    h_min = 2 * params.smoothing_step_mm * MM
    narrow = np.nonzero(full.radius < params.min_lumen_radius_mm * MM)[0]
    if len(narrow):
        s_narrow = float(full.s[narrow[0]])
        msg = (f"the lumen narrows to {full.radius[narrow[0]] / MM:.2f} mm radius < min_lumen_radius_mm "
               f"{params.min_lumen_radius_mm:g} mm at {s_narrow / MM:.1f} mm along the route")
        if params.unreachable == "error":
            raise InputError(f"target branch {info.branch_id} is unreachable: {msg}")
        first_fail = msg
        reason = "lumen_narrower_than_scope"
        s_new = s_narrow - params.nearest_backoff_mm * MM
        if s_new < h_min:
            raise InputError(f"target branch {info.branch_id}: no reachable point on its route ({msg})")
        route = _truncate(full, s_new)
    while True:
        res = smooth_route(route.points, route.radius, route.s, fn, kmax, params)
        if res.ok_clearance and res.ok_curvature:
            built = _build(graph, route, res, fn, kmax, params, info)
            if isinstance(built, Trajectory):
                traj = built
                break
            s_fail, msg = built
            why = "curvature_limit" if "curvature" in msg else "clearance"
        else:
            msg = _fail_message(res, route, kmax)
            why = "clearance" if res.ok_curvature else "curvature_limit"
            s_fail = float(res.route_s[max(res.fail_index, 0)])
        if params.unreachable == "error":
            raise InputError(f"target branch {info.branch_id} is unreachable: {msg}")
        first_fail = first_fail or msg
        reason = reason or why
        s_new = min(s_fail, route.length) - params.nearest_backoff_mm * MM
        if s_new < h_min:
            raise InputError(f"target branch {info.branch_id}: no reachable point on its route ({first_fail})")
        route = _truncate(route, s_new)
    if route is not full:
        end = traj.positions[-1]
        info.reached = False
        info.note = (f"{(full.length - route.length) / MM:.1f} mm short of the target along the route: "
                     + first_fail) + ("; " + info.note if info.note else "")
        info.point = end.copy()
        info.branch_id = int(route.branch[-1])
        info.stop_reason = reason or info.stop_reason
        traj.target = info
    info.stop_distance = float(np.linalg.norm(traj.positions[-1] - info.requested))
    traj.target = info
    traj.start = start_doc
    if params.joint_plan is not None:
        _plan_in_joint_space(traj, fn, params, geometry or DEFAULT_GEOMETRY)
    return traj


def _plan_in_joint_space(traj: Trajectory, fn: SdfFn, params: TrajectoryParams, geometry: ScopeGeometry) -> None:
    """Replace the camera poses by the forward kinematics of a joint plan aimed at them (step 7)."""
    from ..robot.pybullet_sim import Route
    from .joint_plan import JointPlanParams, plan_joints

    route = Route(traj.path_poses[:, :3, 3], traj.arclength, traj.path_poses[:, :3, :3])
    q, poses, report = plan_joints(route, traj.poses, traj.arclength, traj.timestamps, fn, geometry,
                                   JointPlanParams.from_dict(params.joint_plan))
    traj.poses = poses
    traj.joints = q
    traj.clearance = -np.asarray(fn(poses[:, :3, 3]), float)
    report["camera_clearance_minus_margin_min_mm"] = float((traj.clearance - traj.margin).min() * 1e3)
    traj.joint_plan = report


def _build(graph, route: _Route, res: SmoothResult, fn: SdfFn, kmax: float, params: TrajectoryParams,
           info: TargetInfo) -> "Trajectory | tuple[float, str]":
    """Spline, timing, frames and per-pose checks; ``(route arclength, reason)`` if a check fails."""
    P = res.points
    seg = np.linalg.norm(np.diff(P, axis=0), axis=1)
    keep = np.concatenate([[True], seg > 1e-12])
    P = P[keep]
    u = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(P, axis=0), axis=1))])
    L = float(u[-1])
    if len(P) < 3:
        spl = None
    else:
        spl = CubicSpline(u, P, bc_type="not-a-knot" if len(P) > 3 else "natural")
    # dense curvature check (~0.1 mm)
    sd = np.linspace(0.0, L, max(2, int(math.ceil(L / (0.1 * MM))) + 1))

    def curv(s):
        if spl is None:
            return np.zeros(len(s))
        d1, d2 = spl(s, 1), spl(s, 2)
        n1 = np.linalg.norm(d1, axis=1)
        return np.linalg.norm(np.cross(d1, d2), axis=1) / np.maximum(n1, 1e-12) ** 3

    def pos(s):
        if spl is None:
            return np.stack([np.interp(s, u, P[:, k]) for k in range(3)], axis=1)
        return spl(s)

    def tangent(s):
        if spl is None:
            d = P[-1] - P[0]
            return np.broadcast_to(d / np.linalg.norm(d), (len(s), 3)).copy()
        d1 = spl(s, 1)
        return d1 / np.linalg.norm(d1, axis=1, keepdims=True)

    kd = curv(sd)
    if kd.max() > kmax:  # the spline between the smoothed points bends more than they do (rare)
        s_bad = float(np.interp(sd[int(np.argmax(kd))], u, res.route_s[keep]))
        return s_bad, f"spline curvature {kd.max():.1f} 1/m > kappa_max {kmax:.1f} 1/m at {s_bad / MM:.1f} mm"
    # bifurcations: nearest path arclength to each junction point of the route
    junc_pts = np.stack([np.interp(route.junctions, route.s, route.points[:, k]) for k in range(3)], axis=1) \
        if len(route.junctions) else np.zeros((0, 3))
    pd = pos(sd)
    junc_s = np.array([sd[int(np.argmin(np.linalg.norm(pd - j, axis=1)))] for j in junc_pts])
    v = _speed_profile(sd, kd, junc_s, kmax, params)
    t_d = np.concatenate([[0.0], np.cumsum(0.5 * (1.0 / v[1:] + 1.0 / v[:-1]) * np.diff(sd))])
    dt = 1.0 / params.rate_hz
    K = int(math.ceil(t_d[-1] / dt - 1e-9))
    ts = np.arange(K + 1) * dt
    sk = np.minimum(np.interp(ts, t_d, sd), L)
    sk[-1] = L
    X = pos(sk)
    T = tangent(sk)
    R = rotation_minimising_frames(X, T, initial_down(T[0], params.image_up))
    path_poses = np.tile(np.eye(4), (len(ts), 1, 1))
    path_poses[:, :3, :3] = R
    path_poses[:, :3, 3] = X
    if params.view_jitter_deg > 0:
        rng = np.random.default_rng(params.jitter_seed)
        w = rng.normal(size=(len(ts), 3))
        w[:, 2] = 0.0
        sig = params.view_jitter_time_s * params.rate_hz
        if len(ts) > 1:
            w[:, :2] = gaussian_filter1d(w[:, :2], sigma=sig, axis=0, mode="nearest")
        w[:, :2] /= max(float(np.sqrt((w[:, :2] ** 2).sum(axis=1).mean())), 1e-12)  # RMS angle 1
        w *= math.radians(params.view_jitter_deg)
        R = R @ Rotation.from_rotvec(w).as_matrix()
    poses = np.tile(np.eye(4), (len(ts), 1, 1))
    poses[:, :3, :3] = R
    poses[:, :3, 3] = X
    clear = -fn(X)
    # route arclength of each pose via the smoothed points' projections, then margin and branch
    s_route = np.interp(sk, u, res.route_s[keep])
    margin = np.interp(s_route, res.route_s, res.margin)
    if np.any(clear < margin):
        i = int(np.argmin(clear - margin))
        return float(s_route[i]), (f"clearance {clear[i] / MM:.2f} mm < margin {margin[i] / MM:.2f} mm "
                                   f"between smoothed points at {s_route[i] / MM:.1f} mm")
    bidx = np.clip(np.searchsorted(route.s, s_route, side="right") - 1, 0, len(route.s) - 1)
    branch = route.branch[bidx]
    chain = [b.id for b in graph.path_to(int(route.branch[-1]))]
    return Trajectory(timestamps=ts, poses=poses, arclength=sk, branch_id=branch.astype(np.int64),
                      clearance=clear, curvature=curv(sk), speed=np.interp(sk, sd, v), margin=margin,
                      target=info, kappa_max=kmax, rate_hz=params.rate_hz, max_curvature=float(kd.max()),
                      route_branches=chain, params=params.to_dict(), path_poses=path_poses)


def plan_trajectories(graph: CentrelineGraph, sdf_fn, params: TrajectoryParams | None = None,
                      geometry: ScopeGeometry | None = None) -> list[Trajectory]:
    """One trajectory per configured target (:func:`select_targets`), in that order."""
    params = params or TrajectoryParams()
    fn = as_sdf_fn(sdf_fn)
    return [plan_path(graph, t, fn, params, geometry) for t in select_targets(graph, params)]
