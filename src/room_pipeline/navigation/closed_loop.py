"""Closed-loop navigation of the simulated scope from rendered images (issue #19).

Episode (one patient, one target branch of the centreline graph)
    The scope starts in the trachea (``start_offset_mm`` down the root branch, looking along it).  Every
    control step (``1 / control_rate_hz`` s, default 0.1 s) the policy sees only the camera's image at the
    *simulated* tip pose, rendered by the fast Open3D ray caster (:class:`~room_pipeline.render.raycast.
    RaycastRenderer`, ``image_px`` square, the render config's field of view), and, while the tip is in a
    branch that ends in a bifurcation on the way to the target, the operator's command for it: the word
    "left" / "right" / "up" / "down" (the image direction from the wrong child's opening to the right
    one, computed from the graph and the true pose, as an operator watching the screen would say it).
    It returns a target tip position; :func:`reach_command` turns it into a command ``q = (q1, q2, q3)``
    (tendon differential m, roll rad, insertion m): the insertion advances at ``speed_mm_s`` (``slow_factor``
    of it while the plan is not collision-free) and the constant-curvature bend that would put the tip on the
    target once the scope has gone ``lookahead_mm`` further is commanded (position-only tip control; the
    simulate stage's pose IK stalled here: with the shaft on the tip's own path, its targets were out of
    reach and its insertion stopped).  The command is rate-limited (the simulate config's actuator rates),
    sent through the actuator model (:class:`~room_pipeline.robot.actuation.Actuator`: the paper's delay
    ~ U(0, delay_max_s) drawn once per episode from ``seed``, and gains), and PyBullet
    (:class:`~room_pipeline.robot.pybullet_adapter.ScopeSim`, the simulate config's scope, contact and friction,
    at ``physics_step_s``) integrates the control period against the decimated
    lumen (``collision_model.obj``).

Switches (default off; none measured better than the default over the benchmark's targets, README)
    ``tip_control: path``: :func:`~room_pipeline.navigation.tip_control.path_command` puts the tip on the
    route / plan / dark ray where it crosses the dome of reachable tips (the look-ahead is then tied to the
    segment's length; ``lookahead_mm`` is only the insertion preview); ``retract_force_n > 0``: retract at
    ``retract_mm_s`` while the last period's peak contact force exceeded it; ``forward_trace``: the shaft's
    path grows only by the tip's advance along its view (a roll sweep of the bent tip is not shaft motion);
    ``tip_control: aim``: :func:`~room_pipeline.navigation.tip_control.aim_command` turns the view toward the
    point ``aim_mm`` along the plan / route / ray (the bend set relative to the shaft); ``depth_target:
    free_centre``: the depth policy's tip target is :func:`~room_pipeline.navigation.planner.free_centre`
    ``centre_depth_mm`` ahead (a point of the anatomy, not of the view); ``fork_slow_mm`` > 0: insert at
    ``fork_slow_factor`` of the speed while a fork is seen nearer than that (``depth_target: axis``).

Depth target ``axis`` (:mod:`.axis`)
    The lumen's axis estimated from the depth map alone: the centres of the free cross-sections ``depth > z``
    at 1 mm steps of ``z``, the operator's command picking the child where they split (a split across the
    command's direction is not the commanded fork: the opening straight ahead is kept); the tip target is
    ``lookahead_mm`` along that axis from the camera's foot on it, a point of the anatomy (the oracle's rule
    on an estimated centreline).  Once the fork is at hand (split nearer than ``axis_lead_mm`` +
    ``lookahead_mm``) the chosen child's centre is held as a world point (from the scope's own pose, not the
    route) and picks the child in later frames until the tip passes it: a sibling seen sideways just past
    the carina is not taken for the next fork.  ``sideways_deg`` > 0 (depth policy only): the roll is not held
    near zero bending for a target more than that off the held bending plane (held, the tip bent in the wrong
    plane; with it the oracle took a wrong branch on 3 of patient_000's 5 benchmark targets, so it keeps
    the held roll).
    ``fork_child_mm`` (default 40; 0 = session 11's rule above): as soon as the commanded fork is seen nearer
    than this (a split the word parts its way, or the child held from it), the chosen child's centre 3 mm past
    the split is held (every frame) and is itself the tip target, instead of ``lookahead_mm`` along the axis:
    an operator steers for the commanded opening as soon as it shows, not when the carina is at the tip.
    Traced (benchmarks/navigation.py ``--trace``, :mod:`.diagnose`), the 4 mm look-ahead on an axis that turns
    only at the fork moved the tip across too late, from a tip already 2-4 mm off the route on the parent's
    flared cross-sections.  While held and no commanded split is seen in a frame, the held point stays the
    target (no flicker back to the axis); a held point that lies before a newly seen split (in the parent
    lumen: an earlier fork's) no longer picks that fork's child (``lumen_axis(hold_tol_m=1 mm)``): traced, a
    point held from the main carina picked the child against the next fork's command.
    Logged per step: ``tip_mm`` / ``target_mm`` (world), ``route_error_mm`` (tip to the route's centreline), ``axis_target_mm`` /
    ``axis_split_mm`` (depth_target axis: the target in the camera frame, the fork's depth),
    ``trace_lag_mm`` (shaft path length minus insertion minus ``l``), ``tip_deflection_mm`` (simulated tip
    minus the arc model's tip), ``force_max_n`` / ``penetration_max_mm`` (the control period's peak summed contact
    force and deepest contact over its physics steps), and from the depth map alone (depth policy): ``wall_ahead_mm``
    (:func:`~.axis.wall_ahead`: the nearest observed wall within the scope radius + 0.5 mm of the view axis),
    ``tube_clear_mm`` (:func:`~.axis.tube_clearance` of the straight segment to the held child) and ``child_deg``
    (its angle off the view axis).
    ``fork_child_deg`` > 0 (off by default): the held child's centre is the target only while it lies within that
    angle of the view axis or nearer than ``fork_child_far_mm`` (planar depth); else (logged ``child_gated``) the axis
    target: a child seen far and far aside means the branch curves toward it (traced: steering straight for it, the
    far target underbends the segment and the tip presses the curve's wall; benchmarks/results/navigation_failures.md).

Shaft
    ``shaft: lumen`` (default, :class:`LumenShaft`): the bending-segment base slides along the airway's
    centreline to the tip's branch: the passive insertion tube of a bronchoscope, pushed in, is bent along the
    lumen by the walls.  Measured: with it the oracle reaches every generation-4 target (benchmarks/results/
    navigation.md); with ``trace`` the 50 mm bending segment spanned the carina's turn from a base on the
    tip's swept (roll-zigzagged) path, its middle pressed the wall and the tip was pushed into a neighbour
    branch (0 %, 20-46 N).  ``shaft: trace`` (follow-the-leader): the simulate stage constrains the shaft to
    the *planned* route; in closed loop there is none, so the
    bending-segment base slides along the path the tip itself has traced (a rotation-minimising frame
    along it; before the start, a straight line back out of the trachea): a continuum scope's shaft
    follows where its tip went.  Honest limit: the shaft is kinematic, so contact forces act on the
    bending segment only.

Policies
    ``depth``: depth map (ground truth: the ray caster's planar z; the upper bound of any estimator) ->
    point cloud -> :func:`~room_pipeline.navigation.planner.choose_goal` (farthest free point, in the
    region the command points to) -> :func:`~room_pipeline.navigation.planner.plan_path` (its collision
    flag sets the insertion speed); the tip target is ``lookahead_mm`` along the lumen axis estimated from
    the depth map (``depth_target: axis``, default, below; ``plan``: the plan's point ``lookahead_mm`` ahead,
    last round's default; the axis falls back to it where no axis is found).  ``darkest``: the naive baseline: the RGB
    image (Lambertian tip-light shading, the render config's light), blurred; the darkest region (the
    lumen is dark), chosen by the command when several; steer along the ray through its centroid.
    ``oracle``: the centreline route of the graph to the target, the point ``lookahead_mm`` ahead of the
    tip's nearest route point (uses the true pose and anatomy: the reference, not a vision policy).

Outcome
    ``reached`` when the tip's nearest centreline point is in the target branch at >= ``reach_fraction``
    of its length; ``wrong_branch`` when it is ``wrong_branch_mm`` into a branch off the route and at least
    ``wrong_branch_gap_mm`` nearer that branch's centreline than the route's (siblings' centrelines run within
    a fraction of a mm of each other for several mm past a bifurcation: a tip on the route is not in the
    wrong branch because a sibling's centreline passes nearer);
    ``stalled`` when the insertion gained < 1 mm over ``stall_time_s``; ``timeout`` at ``max_time_s``;
    ``tunnelled`` when a contact got deeper than ``simulate.unstable_penetration_mm`` (the soft contact gave way
    and the scope went through the wall: the physics past that point is not a bronchoscope's, so the episode
    stops there as a failure instead of reporting tens of N at tens of mm of penetration).
    Reported: time (s), tip path length (mm), physics steps in contact, peak summed normal contact force
    (N, every physics step), minimum distance from the scope's backbone to the TRUE lumen surface minus
    the scope radius (mm, every control step), the deepest generation of the route reached, and CPU time
    per control step split into render / plan / simulate (``time.process_time``).
"""
from __future__ import annotations

import dataclasses
import math
import time
from typing import Any, Callable

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from ..io.mesh import Mesh
from ..render.camera import CameraIntrinsics
from ..robot.actuation import Actuator, CommandSignal, sample_delay
from ..robot.controller import rate_limit
from ..robot.kinematics import ScopeGeometry
from ..geometry.rotations import rz as _rz
from ..robot.pybullet_adapter import ScopeSim
from ..robot.sim_params import SimParams
from .airways import COMMANDS, Airways, Patient, check_target, generation_targets, operator_command, start_pose  # noqa: F401
from .lumen import TrueLumen
from .perception import back_project
from .axis import axis_target, lumen_axis, tube_clearance, wall_ahead
from .params import EpisodeParams  # noqa: F401 (also re-exported: the episode's parameters)
from .planner import PlannerParams, choose_goal, free_centre, plan_path
from .shaft import LumenShaft, Trace  # noqa: F401
from .tip_control import _model_error, aim_command, path_command, reach_command  # noqa: F401

MM = 1e-3


# --------------------------------------------------------------------------- the episode


class _Eyes:
    """The policy's camera: depth (and RGB for the darkest policy) at any pose, fast ray caster."""

    def __init__(self, mesh: Mesh, camera: CameraIntrinsics, rgb: bool, light=None, material=None) -> None:
        from ..render.raycast import RaycastConfig, RaycastRenderer
        from ..render.scene import Film, Scene, TipLight, TissueMaterial

        self.camera = camera
        kw = {}
        if rgb:
            kw = dict(light=light or TipLight(), material=material or TissueMaterial(), film=Film(exposure_ev=0.0))
        self.scene = Scene(mesh, camera, np.eye(4)[None], np.zeros(1), **kw)
        self.r = RaycastRenderer(self.scene, RaycastConfig(per_pixel_texture=False))
        vv, uu = np.mgrid[0:camera.height, 0:camera.width]
        self.uv = np.stack([uu.ravel(), vv.ravel()], axis=1).astype(float)

    def depth(self, pose: np.ndarray) -> np.ndarray:
        d, hit = self.r.depth_at(pose, self.uv)
        return np.where(hit, d, 0.0).reshape(self.camera.height, self.camera.width)

    def rgb(self, pose: np.ndarray) -> np.ndarray:
        """(H, W, 3) uint8 sRGB frame at ``pose`` (for a depth estimator; needs ``rgb=True``)."""
        self.scene.poses[0] = pose
        self.r._cache.clear()
        return self.r.render(0, {"rgb"})["rgb"]

    def luminance(self, pose: np.ndarray) -> np.ndarray:
        self.scene.poses[0] = pose
        self.r._cache.clear()                 # one reusable frame slot: a new pose each call
        out = self.r.render(0, {"rgb"})
        lin = out["rgb_linear"].astype(np.float64)
        lum = 0.2126 * lin[..., 0] + 0.7152 * lin[..., 1] + 0.0722 * lin[..., 2]
        return np.where(out["hit"], lum, 0.0)  # no hit (beyond the far plane) is the darkest


def run_episode(patient: Patient, target: int, params: EpisodeParams, planner: PlannerParams,
                sim_params: SimParams, geometry: ScopeGeometry | None = None, record_frames: bool = False,
                depth_source: Callable[[_Eyes, np.ndarray], np.ndarray] | None = None) -> dict:
    """One closed-loop episode toward branch ``target``; returns the outcome and per-step log (see module doc).

    ``depth_source(eyes, tip_pose)`` -> (H, W) planar depth, m (0 = none): what the ``depth`` policy plans on;
    None = the ray caster's ground truth (:mod:`.depth_source` builds estimator-backed ones)."""
    check_target(patient.graph, target)
    sim_params = dataclasses.replace(sim_params, time_step_s=params.physics_step_s)
    geometry = geometry or ScopeGeometry()
    planner = dataclasses.replace(planner, kappa_max=min(planner.kappa_max, geometry.kappa_max),
                                  scope_radius_mm=sim_params.scope_diameter_mm / 2)
    airways = Airways(patient.graph)
    route_ids = airways.route(target)
    route_P, route_s = airways.route_polyline(target)
    route_tree = cKDTree(route_P)
    lumen = TrueLumen(patient.mesh)
    cam = CameraIntrinsics.from_fov(params.image_px, params.image_px, params.fov_deg, 1e-4, 0.5)
    eyes = _Eyes(patient.mesh, cam, rgb=params.policy == "darkest" or depth_source is not None)

    pose0 = start_pose(patient.graph, params.start_offset_mm * MM)
    trace = Trace(pose0) if params.shaft == "trace" else LumenShaft(airways, pose0)
    sim = ScopeSim(sim_params, geometry)
    try:
        sim.set_wall(patient.collision.vertices, patient.collision.faces)
        rng = np.random.default_rng(params.seed)
        delay = sample_delay(rng, sim_params.delay_max_s) if sim_params.actuation else 0.0
        signal = CommandSignal()
        act = Actuator(signal, delay, geometry.q1_max, sim_params.gain_q1, sim_params.gain_q2,
                       enabled=sim_params.actuation)
        max_rate = np.array([sim_params.max_rate_q1_mm_s * MM, math.radians(sim_params.max_rate_q2_deg_s),
                             min(sim_params.max_rate_q3_mm_s, params.speed_mm_s) * MM])
        ctrl_dt = 1.0 / params.control_rate_hz
        n_sub = max(1, int(round(ctrl_dt / sim_params.time_step_s)))
        h = ctrl_dt / n_sub

        def apply(q, hh=0.0, reset=True):
            base = trace.route.frame(q[2])
            base[:3, :3] = base[:3, :3] @ _rz(q[1])
            prev = sim.base_pose if (sim_params.insertion_by_velocity and hh > 0.0) else None
            sim.set_base(base, prev, hh, reset=reset)
            sim.set_bend(q[0])

        q = np.array([0.0, 0.0, trace.s_end - geometry.l])
        signal.add(0.0, q)
        apply(act(0.0))
        sim.reset_joints()
        sim.step(int(round(sim_params.settle_time_s / sim_params.time_step_s)))

        t = 0.0
        log: list[dict] = []
        peak_force, contact_steps, steps = 0.0, 0, 0
        min_clear = math.inf
        gen_reached = patient.graph.root.generation
        cpu = {"render": 0.0, "plan": 0.0, "simulate": 0.0}
        q3_hist = [(0.0, q[2])]
        outcome = "timeout"
        tip_prev = None
        f_period = 0.0
        tunnelled = False
        path_len = 0.0
        frames = []
        k = 0
        hold = None                    # depth_target axis: world point in the child chosen at the fork at hand
        while t < params.max_time_s - 1e-9:
            tip = sim.tip_pose()
            if not np.all(np.isfinite(tip)):
                outcome = "diverged"
                break
            p_tip = tip[:3, 3]
            if tip_prev is not None:
                path_len += float(np.linalg.norm(p_tip - tip_prev))
            tip_prev = p_tip.copy()
            trace.extend(p_tip, tip[:3, 2] if params.forward_trace else None)
            sd = lumen.signed_distance(sim.sample_points())
            min_clear = min(min_clear, float((-sd).min()) - sim.radius)
            branch, s_in = airways.locate(p_tip)
            if branch in route_ids:
                gen_reached = max(gen_reached, patient.graph.branch(branch).generation)
            if branch == target and s_in >= params.reach_fraction * airways.cum[target][-1]:
                outcome = "reached"
                break
            d_route = float(route_tree.query(p_tip)[0])
            if (branch not in route_ids and s_in >= params.wrong_branch_mm * MM
                    and d_route - airways.distance(p_tip) >= params.wrong_branch_gap_mm * MM):
                outcome = "wrong_branch"
                break
            if t >= params.stall_time_s:
                old = [qq for tt, qq in q3_hist if tt <= t - params.stall_time_s]
                if old and q[2] - old[-1] < 1 * MM:
                    outcome = "stalled"
                    break
            word = operator_command(airways, target, branch, tip, cam)
            c0 = time.process_time()
            path = aim = None
            defl = _model_error(act(t), trace.route.frame, geometry, p_tip)
            info: dict[str, Any] = {"t": round(t, 6), "branch": branch, "command": word,
                                    "route_error_mm": round(d_route * 1e3, 3),
                                    "trace_lag_mm": round((trace.s_end - float(q[2]) - geometry.l) * 1e3, 3),
                                    "tip_deflection_mm": round(float(np.linalg.norm(defl)) * 1e3, 3)}
            if params.policy == "oracle":
                _, i = route_tree.query(p_tip)
                s_goal = route_s[i] + params.lookahead_mm * MM
                j = int(min(len(route_s) - 2, np.searchsorted(route_s, s_goal)))
                tgt = route_P[j]
                tan = route_P[j + 1] - route_P[j]
                ja = int(min(len(route_s) - 1, np.searchsorted(route_s, route_s[i] + params.aim_mm * MM)))
                aim = route_P[ja]
                ahead = route_P[i:]
                path = ahead[route_s[i:] - route_s[i] <= 2 * geometry.l]
                c1 = time.process_time()
            elif params.policy == "depth":
                depth = eyes.depth(tip) if depth_source is None else depth_source(eyes, tip)
                c1 = time.process_time()
                cloud = back_project(depth, cam, 1)
                tree = cKDTree(cloud.points) if len(cloud.points) else None
                ahead = wall_ahead(cloud.points, sim.radius + 0.5 * MM)
                info["wall_ahead_mm"] = round(ahead * 1e3, 3) if math.isfinite(ahead) else None
                goal = choose_goal(cloud, planner, COMMANDS.get(word) if word else None, tree) if tree else None
                if goal is None:
                    tgt, tan = p_tip, tip[:3, 2]
                    info["plan"] = None
                else:
                    pl = plan_path(cloud, goal.point, dataclasses.replace(planner, seed=planner.seed + k), tree)
                    pc, tc = pl.at(params.lookahead_mm * MM)
                    if params.depth_target == "free_centre":
                        fc = free_centre(cloud, planner, goal.point, params.centre_depth_mm * MM, tree)
                        pc = pc if fc is None else fc
                    tgt = tip[:3, :3] @ pc + p_tip
                    aim = tip[:3, :3] @ pl.at(min(params.aim_mm * MM, pl.length))[0] + p_tip
                    tan = tip[:3, :3] @ tc
                    path = pl.to_world(tip)[0]
                    info["plan"] = {"free": pl.collision_free, "length_mm": round(pl.length * 1e3, 3),
                                    "goal_depth_mm": round(goal.depth * 1e3, 3), "regions": goal.regions}
                    if record_frames:
                        frames.append({"depth": depth, "plan": pl, "pose": tip.copy(), "goal": goal})
                if params.depth_target == "axis":
                    prefer = None if hold is None else tip[:3, :3].T @ (hold - p_tip)
                    if prefer is not None and prefer[2] <= 0:
                        hold = prefer = None                    # passed the held child's point: the fork is done
                    fc = params.fork_child_mm * MM
                    ax = lumen_axis(depth, cam, COMMANDS.get(word) if word else None, lead_m=params.axis_lead_mm * MM,
                                    prefer=prefer, hold_tol_m=1e-3 if fc > 0 else None)
                    near = fc > 0 and ax is not None and ax.split_m is not None and ax.split_m <= fc and \
                        ax.pick_by in ("held", "command")                   # the commanded fork is seen
                    if near or (fc == 0 and ax is not None and ax.split_m is not None and
                                ax.split_m <= (params.axis_lead_mm + params.lookahead_mm) * MM):
                        ch = ax.centres[ax.centres[:, 2] >= ax.split_m]         # the fork is at hand: hold its child
                        child_c = ch[min(3, len(ch) - 1)]
                        hold = tip[:3, :3] @ child_c + p_tip
                    if ax is not None:
                        pa, ta = axis_target(ax, params.lookahead_mm * MM)
                        direct = child_c if near else (prefer if fc > 0 and prefer is not None else None)
                        if direct is not None:        # the chosen child's centre itself (see fork_child_mm)
                            clear = tube_clearance(direct, depth, cam, tree)
                            info["tube_clear_mm"] = round(clear * 1e3, 3) if math.isfinite(clear) else None
                            off = math.atan2(math.hypot(direct[0], direct[1]), direct[2])    # off the view axis
                            info["child_deg"] = round(math.degrees(off), 1)
                            if params.fork_child_deg <= 0 or off <= math.radians(params.fork_child_deg) or \
                                    direct[2] <= params.fork_child_far_mm * MM:
                                pa, ta = direct, direct / np.linalg.norm(direct)
                            else:       # far and far aside: the branch curves; the axis through the curve first
                                info["child_gated"] = True
                        tgt, tan = tip[:3, :3] @ pa + p_tip, tip[:3, :3] @ ta
                        info["axis_target_mm"] = [round(float(x) * 1e3, 3) for x in pa]   # camera frame
                        info["axis_split_mm"] = None if ax.split_m is None else round(ax.split_m * 1e3, 1)
                        if ax.openings:
                            info["axis_openings"] = {"uv_px": ax.openings, "pick": ax.pick, "by": ax.pick_by,
                                                     "held": prefer is not None}
            else:
                lum = eyes.luminance(tip)
                c1 = time.process_time()
                ray = _darkest_ray(lum, cam, params.dark_quantile, COMMANDS.get(word) if word else None)
                tan = tip[:3, :3] @ ray
                tgt = p_tip + params.lookahead_mm * MM * tan
                aim = p_tip + params.aim_mm * MM * tan
                path = p_tip + np.arange(0.0, 2 * geometry.l, 1e-3)[:, None] * tan
            tan = tan / np.linalg.norm(tan)
            q_prev = signal(t)
            # push at the insertion speed, bend the tip toward the target
            speed = params.speed_mm_s * MM * (1.0 if info.get("plan", {}) is None or
                                              (info.get("plan") or {}).get("free", True) else params.slow_factor)
            if params.fork_slow_mm > 0 and info.get("axis_split_mm") is not None and \
                    info["axis_split_mm"] <= params.fork_slow_mm:
                speed *= params.fork_slow_factor             # a fork at hand: give the bend time to turn into it
            if params.retract_force_n > 0 and f_period > params.retract_force_n:
                speed = -params.retract_mm_s * MM        # an operator backs off a pressing wall, then steers again
            if params.tip_control == "aim" and aim is not None:
                q_new = aim_command(aim, p_tip, trace.route.frame, q_prev, geometry, speed * ctrl_dt,
                                    sim_params.roll_hold_q1_fraction, sim_params.roll_free_q1_fraction,
                                    preview_m=params.lookahead_mm * MM)
            elif params.tip_control == "path" and path is not None and len(path):
                q_new, resid = path_command(path, trace.route.frame, q_prev, geometry, speed * ctrl_dt,
                                            sim_params.roll_hold_q1_fraction, sim_params.roll_free_q1_fraction,
                                            preview_m=params.lookahead_mm * MM)
                info["path_residual_mm"] = round(resid * 1e3, 3)
            else:
                q_new = reach_command(tgt, trace.route.frame, q_prev, geometry, speed * ctrl_dt,
                                      sim_params.roll_hold_q1_fraction, sim_params.roll_free_q1_fraction,
                                      preview_m=params.lookahead_mm * MM,
                                      sideways_rad=math.radians(params.sideways_deg) if params.policy == "depth" else 0.0)
            q = rate_limit(q_new, q_prev, ctrl_dt, max_rate)
            c2 = time.process_time()
            signal.add(t + ctrl_dt, q)
            sim.update_friction()
            f_period, pen_period = 0.0, 0.0
            for j in range(n_sub):
                tj = t + (j + 1) * h
                apply(act(tj), h, reset=(j == 0))
                sim.step(1)
                f, pen = sim.contacts()
                peak_force = max(peak_force, f)
                if pen > sim_params.unstable_penetration_mm * MM:
                    tunnelled = True
                f_period = max(f_period, f)
                pen_period = max(pen_period, pen)
                contact_steps += int(f > 0)
                steps += 1
            c3 = time.process_time()
            cpu["render"] += c1 - c0
            cpu["plan"] += c2 - c1
            cpu["simulate"] += c3 - c2
            info["cpu_s"] = round(c3 - c0, 5)
            info["q_cmd"] = [round(float(x), 7) for x in q]
            info["force_n"] = round(f, 5)
            info["force_max_n"] = round(f_period, 5)                   # the period's peak, and its deepest contact
            info["penetration_max_mm"] = round(pen_period * 1e3, 4)
            info["wall_clearance_mm"] = round((float((-sd).min()) - sim.radius) * 1e3, 3)
            info["tip_mm"] = [round(float(x) * 1e3, 3) for x in p_tip]        # world, for traces (not the policy's)
            info["target_mm"] = [round(float(x) * 1e3, 3) for x in tgt]
            log.append(info)
            t += ctrl_dt
            k += 1
            q3_hist.append((t, q[2]))
            if tunnelled:              # the soft contact gave way (the scope through the wall): stop, a failure
                outcome = "tunnelled"
                break
        n = max(1, len(log))
        result = {
            "patient": patient.name, "target": int(target), "target_generation": patient.graph.branch(target).generation,
            "policy": params.policy, "outcome": outcome, "success": outcome == "reached",
            "time_s": round(t, 6), "path_length_mm": path_len * 1e3,
            "contact_steps": contact_steps, "physics_steps": steps, "peak_contact_force_n": peak_force,
            "min_wall_clearance_mm": min_clear * 1e3, "generation_reached": int(gen_reached),
            "actuation_delay_s": delay, "control_steps": len(log),
            "cpu_per_step_s": {kk: v / n for kk, v in cpu.items()} | {"total": sum(cpu.values()) / n},
            "log": log,
        }
        if record_frames:
            result["frames"] = frames
        return result
    finally:
        sim.close()


def _darkest_ray(lum: np.ndarray, cam: CameraIntrinsics, quantile: float, command) -> np.ndarray:
    """Unit camera-frame ray through the centroid of the darkest region (the one the command points to)."""
    L = ndimage.gaussian_filter(lum, sigma=max(1.0, cam.width / 32))
    thr = np.quantile(L, quantile)
    mask = L <= thr
    labels, n = ndimage.label(mask)
    if n == 0:
        u, v = cam.cx, cam.cy
    else:
        sizes = np.bincount(labels.ravel(), minlength=n + 1)
        regions = [kk for kk in range(1, n + 1) if sizes[kk] >= 3] or [int(np.argmax(sizes[1:]) + 1)]
        cents = np.array([np.argwhere(labels == kk).mean(axis=0)[::-1] for kk in regions])   # (u, v)
        if command is not None and len(regions) > 1:
            pick = int(np.argmax((cents - cents.mean(axis=0)) @ np.asarray(command, float)))
        else:
            means = [L[labels == kk].mean() for kk in regions]
            pick = int(np.argmin(means))
        u, v = cents[pick]
    ray = cam.rays_at(np.array([u, v], dtype=np.float64))          # the camera's own model (lens included)
    return ray / np.linalg.norm(ray)
