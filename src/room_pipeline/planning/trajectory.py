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
    7. **Joint space** (``joint_plan``: on in the default config, ``joint_plan.enabled``; None here = off): the poses of steps 5-6 become
       ``path_poses`` (what the shaft follows and the camera aims at) and the camera poses are the
       forward kinematics of a joint trajectory ``q(t)`` of the scope (:mod:`.joint_plan`: the
       constant-curvature bending segment with its base on the path, one whole-sequence solve:
       position/view trade-off, a hard roll hold while straight, joint, rate and acceleration
       limits, the scope body kept in the lumen), so the simulator
       can execute the plan; ``joint_plan`` in ``trajectory.json`` says how far it departs from
       the path.  ``clearance`` is then measured at those camera positions.
    8. **Where the insertion ends** (``stop_at_wall``, on by default): the sequence stops before the
       first frame whose camera (or, with a joint plan, bending-segment backbone) is closer to the wall
       than the scope's radius + ``stop_clearance_mm`` (:mod:`.insertion_stop`); the kept frames are
       planned again in joint space; ``trajectory.json`` -> ``insertion_stop`` says where and why.

Poses are 4x4 camera-to-world in the OpenCV camera frame (x right, y down, z
forward), world RAS+ metres, as in :mod:`room_pipeline.conventions`.
All functions are pure; the caller writes files (``Trajectory.to_dict`` for
``metadata/trajectory.json``, :func:`timestamps_dict` for ``timestamps.json``,
``Trajectory.to_tum`` for a TUM trajectory).

Modules, one job each: :mod:`.trajectory_params` (the config), :mod:`.targets` (step 1),
:mod:`.centreline_route` (step 2), :mod:`.smoothing` (step 3), :mod:`.frames` (steps 5-6: speed profile,
orientation), :mod:`.joint_plan` (step 7), :mod:`.sdf_fn` (the clearance evaluators),
:mod:`.trajectory_record` (:class:`Trajectory` and its files); this one assembles them (:func:`plan_path`:
steps 4-6 and the unreachable-target fallback) and re-exports their public names.
"""
from __future__ import annotations

import math
import os

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.ndimage import gaussian_filter1d
from scipy.spatial.transform import Rotation

from ..anatomy.centreline import CentrelineGraph
from ..conventions import MM
from ..errors import InputError
from ..robot.kinematics import DEFAULT_GEOMETRY, ScopeGeometry
from .centreline_route import _Route, _route, _truncate
from .frames import _speed_profile, initial_down, rotation_minimising_frames
from .sdf_fn import SdfFn, as_sdf_fn
from .smoothing import SmoothResult, smooth_route
from .targets import TargetInfo, map_target_point, select_targets
from .trajectory_params import TrajectoryParams
from .trajectory_record import Trajectory

# the rest of the planner's API, importable from here as before the split
from ..io.tum import parse_tum  # noqa: F401
from .frames import _WORLD_UP  # noqa: F401
from .sdf_fn import volume_sdf_fn  # noqa: F401
from .smoothing import menger_curvature  # noqa: F401
from .targets import read_target_file  # noqa: F401
from .trajectory_params import IMAGE_UP, TARGET_MODES, UNREACHABLE_MODES  # noqa: F401
from .trajectory_record import timestamps_dict  # noqa: F401


def _kappa_max(params: TrajectoryParams, geometry: ScopeGeometry | None) -> float:
    if params.kappa_max is not None:
        return float(params.kappa_max)
    return (geometry or DEFAULT_GEOMETRY).kappa_max


def _resolve_target(graph: CentrelineGraph, target, params: TrajectoryParams,
                    within: tuple[int, float] | None = None) -> TargetInfo:
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
                                    nearest=params.unreachable == "nearest", within=within)
    r = np.interp(s, np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(graph.branch(bid).points, axis=0),
                                                                      axis=1))]), graph.branch(bid).radius)
    info = TargetInfo("point", bid, c, p, d)
    info._s = s  # type: ignore[attr-defined]
    if d > r + params.target_tolerance_mm * MM:
        info.reached = False
        info.stop_reason = "target_outside_lumen"
        info.note = (f"target {(d - r) / MM:.1f} mm outside the lumen (tolerance {params.target_tolerance_mm:g} mm): "
                     "nearest airway centreline point used"
                     + (f" among the airways below the start pose (branch {within[0]} on)" if within else ""))
    return info


def start_point(graph: CentrelineGraph, start, params: TrajectoryParams) -> tuple[int, float]:
    """``(branch id, arclength)`` of the centreline point a user start pose maps to (as :func:`_start` maps it)."""
    T = np.asarray(start, dtype=np.float64)
    p = T[:3, 3] if T.shape == (4, 4) else T.reshape(3)
    bid, s_b, _, _ = map_target_point(graph, p, params.target_tolerance_mm * MM, nearest=True)
    return bid, s_b


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


def _no_reachable_point(info, start_doc: dict, why: str) -> str:
    """The one-line error of a route that fails within its first millimetres: from a user start pose, it names
    the pose (the scope does not fit where the user put it); from the trachea, the target."""
    if start_doc.get("kind") == "user_pose":
        where = ", ".join(f"{v / MM:.1f}" for v in start_doc["position"])
        return (f"start pose ({where}) mm: the scope does not fit there ({why}; branch {start_doc['branch_id']}): "
                f"give a start pose nearer the trachea, or a thinner scope (trajectory.min_lumen_radius_mm, "
                f"robot geometry)")
    return f"target branch {info.branch_id}: no reachable point on its route ({why})"


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
    # a point target with a user start: mapped among the airways below the start (a route can only go on from it)
    within = start_point(graph, start, params) if start is not None else None
    info = _resolve_target(graph, target, params, within)
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
            raise InputError(_no_reachable_point(info, start_doc, msg))
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
            raise InputError(_no_reachable_point(info, start_doc, first_fail))
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
    aims = traj.poses.copy()
    if params.joint_plan is not None:
        _plan_in_joint_space(traj, fn, params, geometry or DEFAULT_GEOMETRY)
    if params.stop_at_wall:
        traj = _stop_at_wall(traj, aims, fn, params, geometry or DEFAULT_GEOMETRY)
    return traj


#: re-plans of the kept frames (joint plan) before the last check's frames are simply cut
_STOP_REPLANS = 3


def _stop_at_wall(traj: Trajectory, aims: np.ndarray, fn: SdfFn, params: TrajectoryParams,
                  geometry: ScopeGeometry) -> Trajectory:
    """Step 8 (``stop_at_wall``): end the insertion before the first frame whose tip or body is closer to the
    wall than the scope's radius + ``stop_clearance_mm`` (:mod:`.insertion_stop`); ``aims``: the path poses
    the joint plan aimed at (re-planned on the kept frames)."""
    from .insertion_stop import blocked, truncate
    from .joint_plan import JointPlanParams

    jp = JointPlanParams.from_dict(params.joint_plan or {})
    radius, extra = 0.5 * jp.scope_diameter_mm * MM, params.stop_clearance_mm * MM
    planned, note, replans = len(traj.timestamps), None, 0
    while True:
        k, found = blocked(traj, fn, geometry, radius, extra, jp.body_points)
        if k is None:
            break
        note = note or found
        if k < 2:
            what = f"{found['reason']} {found['clearance_mm']:.2f} mm < {found['required_mm']:.2f} mm at frame {k}"
            if (traj.start or {}).get("kind") == "user_pose":
                raise InputError(_no_reachable_point(traj.target, traj.start, f"trajectory.stop_at_wall: {what}"))
            raise InputError(f"target branch {traj.target.branch_id}: trajectory.stop_at_wall: the scope does not "
                             f"fit from the start ({what})")
        cut = truncate(traj, k)
        if params.joint_plan is not None and replans < _STOP_REPLANS:
            replans += 1
            cut.poses = aims[:k].copy()
            _plan_in_joint_space(cut, fn, params, geometry)
        traj = cut
    if note is None:
        return traj
    kept = len(traj.timestamps)
    note.update(frames_planned=planned, frames_kept=kept, joint_replans=replans,
                last_kept_tip_clearance_mm=float(traj.clearance[-1] / MM))
    info = traj.target
    info.reached = False
    info.note = (f"insertion stopped at frame {kept} of {planned} (trajectory.stop_at_wall): {note['reason']} "
                 f"{note['clearance_mm']:.2f} mm < scope radius + stop_clearance_mm {note['required_mm']:.2f} mm "
                 f"at frame {note['frame_index']}") + ("; " + info.note if info.note else "")
    info.stop_reason = "scope_clearance"
    info.point = traj.positions[-1].copy()
    info.branch_id = int(traj.branch_id[-1])
    info.stop_distance = float(np.linalg.norm(traj.positions[-1] - info.requested))
    traj.insertion_stop = note
    return traj


def _plan_in_joint_space(traj: Trajectory, fn: SdfFn, params: TrajectoryParams, geometry: ScopeGeometry) -> None:
    """Replace the camera poses by the forward kinematics of a joint plan aimed at them (step 7)."""
    from ..robot.route import Route
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
