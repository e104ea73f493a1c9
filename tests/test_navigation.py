"""Vision-based navigation (issue #19): perception, planner, true-lumen check, control, CLI errors, episodes.

Geometry: closed tubes built here (straight and bent; real meshes rendered by the real ray caster), so the
fast tests need no pipeline output; the phantom episode is `slow`.
"""
from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest

from room_pipeline.anatomy.centreline import CentrelineGraph, GraphBranch
from room_pipeline.errors import ConfigError, InputError
from room_pipeline.io.mesh import Mesh, write_obj
from room_pipeline.navigation.closed_loop import (EpisodeParams, Patient, check_target, operator_command,
                                                  path_command, reach_command, run_episode, start_pose, Airways, Trace)
from room_pipeline.navigation.shaft import LumenShaft
from room_pipeline.navigation.tip_control import aim_command
from room_pipeline.navigation.axis import axis_target, lumen_axis, tube_clearance, wall_ahead
from room_pipeline.navigation.lumen import TrueLumen
from room_pipeline.navigation.perception import back_project, median_scale
from room_pipeline.navigation.planner import PlannerParams, choose_goal, free_centre, plan_path
from room_pipeline.render.camera import CameraIntrinsics
from room_pipeline.robot.kinematics import ScopeGeometry, fk
from room_pipeline.robot.sim_params import SimParams

KMAX = ScopeGeometry().kappa_max


def tube(radius=0.005, bend_radius=None, angle=0.0, straight=0.08, n_ring=32, step=0.001):
    """Closed tube along +z (then bending toward +x on a circle of ``bend_radius``), end caps included."""
    arc = (bend_radius or 0.0) * angle
    s = np.arange(0.0, straight + arc + 1e-12, step)
    C, T = [], []
    for si in s:
        if si <= straight or not bend_radius:
            C.append([0.0, 0.0, si])
            T.append([0.0, 0.0, 1.0])
        else:
            a = (si - straight) / bend_radius
            C.append([bend_radius * (1 - math.cos(a)), 0.0, straight + bend_radius * math.sin(a)])
            T.append([math.sin(a), 0.0, math.cos(a)])
    C, T = np.array(C), np.array(T)
    th = np.linspace(0, 2 * np.pi, n_ring, endpoint=False)
    V = []
    for c, t in zip(C, T):
        n1 = np.array([0.0, 1.0, 0.0])
        n2 = np.cross(t, n1)
        V += [c + radius * (math.cos(a) * n1 + math.sin(a) * n2) for a in th]
    n = len(C)
    F = []
    for i in range(n - 1):
        for j in range(n_ring):
            a, b = i * n_ring + j, i * n_ring + (j + 1) % n_ring
            F += [[a, b, a + n_ring], [b, b + n_ring, a + n_ring]]
    c0, c1 = len(V), len(V) + 1
    V += [C[0], C[-1]]
    for j in range(n_ring):
        F.append([c0, (j + 1) % n_ring, j])
        F.append([c1, (n - 1) * n_ring + j, (n - 1) * n_ring + (j + 1) % n_ring])
    return Mesh(np.array(V), np.array(F)), C


def render_depth(mesh, pose, px=64):
    from room_pipeline.render.raycast import RaycastRenderer
    from room_pipeline.render.scene import Scene

    cam = CameraIntrinsics.from_fov(px, px, 85.0)
    r = RaycastRenderer(Scene(mesh, cam, pose[None], np.zeros(1)))
    return r.render(0, {"depth"})["depth"], cam


def pose_at(z):
    P = np.eye(4)
    P[2, 3] = z
    return P


# ----------------------------------------------------------------------------- perception


def test_back_project_reprojects_onto_the_depth_map():
    cam = CameraIntrinsics.from_fov(40, 30, 80.0)
    rng = np.random.default_rng(0)
    d = rng.uniform(0.01, 0.05, (30, 40))
    d[3, 4] = 0.0
    d[5, 6] = np.nan
    cl = back_project(d, cam, 1)
    assert len(cl.points) == 40 * 30 - 2
    uv = cam.project(cl.points)
    assert np.allclose(uv, cl.pixels, atol=1e-9)
    assert np.allclose(cl.points[:, 2], d[cl.pixels[:, 1].astype(int), cl.pixels[:, 0].astype(int)])
    assert len(back_project(d, cam, 3).points) < len(cl.points)
    with pytest.raises(InputError, match="depth map"):
        back_project(d[:, :10], cam)


def test_back_project_follows_the_camera_lens_model():
    """With lens distortion (render.distortion) the cloud must come from the camera's own rays, not a pinhole
    formula: every point projects back onto its (distorted) pixel."""
    cam = CameraIntrinsics.from_fov(40, 30, 80.0, distortion=(-0.101, -0.152, 0.00096, -0.0049, 0.102))
    d = np.random.default_rng(1).uniform(0.01, 0.05, (30, 40))
    cl = back_project(d, cam, 1)
    assert np.allclose(cam.project(cl.points), cl.pixels, atol=1e-6)
    pinhole = back_project(d, CameraIntrinsics.from_fov(40, 30, 80.0), 1)
    assert np.abs(cl.points - pinhole.points).max() > 1e-4           # the lens model is really in use


def test_median_scale_recovers_the_scale_and_refuses_empty_overlap():
    gt = np.linspace(0.01, 0.08, 100).reshape(10, 10)
    scaled, s = median_scale(gt * 7.0, gt)
    assert s == pytest.approx(1 / 7.0)
    assert np.allclose(scaled, gt)
    with pytest.raises(InputError, match="median-scale"):
        median_scale(np.zeros((10, 10)), gt)


# ----------------------------------------------------------------------------- planner


def test_straight_tube_plan_is_straight_free_and_inside_the_true_lumen():
    mesh, _ = tube(straight=0.12)
    pose = pose_at(0.01)
    depth, cam = render_depth(mesh, pose)
    cl = back_project(depth, cam, 1)
    p = PlannerParams()
    goal = choose_goal(cl, p)
    assert goal is not None and goal.depth > 0.05                       # far down the tube
    assert math.hypot(goal.point[0], goal.point[1]) < 2.5e-3             # near its axis
    plan = plan_path(cl, goal.point, p)
    assert plan.collision_free
    assert plan.max_curvature() <= p.kappa_max + 1e-9
    assert np.abs(plan.points[:, :2]).max() < 2.5e-3                   # zero curvature case: stays near the axis
    w, _ = plan.to_world(pose)
    rep = TrueLumen(mesh).path_report(w, p.scope_radius_mm * 1e-3)
    assert not rep["collides_with_true_lumen"] and rep["min_sphere_clearance_mm"] > 0


def test_bent_tube_plan_turns_with_the_lumen_within_the_curvature_limit():
    mesh, _ = tube(radius=0.005, bend_radius=0.04, angle=1.0, straight=0.03)
    pose = pose_at(0.005)
    depth, cam = render_depth(mesh, pose)
    cl = back_project(depth, cam, 1)
    p = PlannerParams()
    goal = choose_goal(cl, p)
    assert goal.point[0] > 0.001                                         # the lumen turns toward +x
    plan = plan_path(cl, goal.point, p)
    assert plan.collision_free
    assert plan.points[-1, 0] > 0.001
    assert plan.max_curvature() <= p.kappa_max + 1e-9
    rep = TrueLumen(mesh).path_report(plan.to_world(pose)[0], p.scope_radius_mm * 1e-3)
    assert not rep["collides_with_true_lumen"]


def test_plan_is_deterministic_for_a_seed():
    mesh, _ = tube(radius=0.005, bend_radius=0.04, angle=1.0, straight=0.03)
    depth, cam = render_depth(mesh, pose_at(0.005))
    cl = back_project(depth, cam, 1)
    p = PlannerParams(seed=3)
    goal = choose_goal(cl, p)
    a, b = plan_path(cl, goal.point, p), plan_path(cl, goal.point, p)
    assert a.points.tobytes() == b.points.tobytes()


def test_a_wall_across_the_way_makes_the_plan_collide():
    cam = CameraIntrinsics.from_fov(48, 48, 85.0)
    depth = np.full((48, 48), 0.012)                                     # a flat wall 12 mm ahead
    cl = back_project(depth, cam, 1)
    plan = plan_path(cl, np.array([0.0, 0.0, 0.03]), PlannerParams())   # a goal behind it
    assert not plan.collision_free
    assert plan.behind_surface.max() > 0 or plan.clearance.min() < 2.5e-3


def test_no_free_point_gives_no_goal():
    cam = CameraIntrinsics.from_fov(32, 32, 85.0)
    cl = back_project(np.full((32, 32), 0.002), cam, 1)                  # a wall 2 mm ahead: nothing fits a 2.5 mm sphere
    assert choose_goal(cl, PlannerParams()) is None
    assert choose_goal(back_project(np.zeros((32, 32)), cam, 1), PlannerParams()) is None


def test_command_picks_the_opening_on_its_side():
    cam = CameraIntrinsics.from_fov(64, 64, 85.0)
    v, u = np.mgrid[0:64, 0:64]
    depth = 0.012 + 0.045 * np.exp(-((u - 16) ** 2 + (v - 32) ** 2) / 40.0) \
        + 0.040 * np.exp(-((u - 48) ** 2 + (v - 32) ** 2) / 40.0)      # two openings, the left one deeper
    cl = back_project(depth, cam, 1)
    p = PlannerParams()
    assert choose_goal(cl, p).point[0] < 0                               # no command: the deepest (left)
    g = choose_goal(cl, p, command=np.array([1.0, 0.0]))                 # "right"
    assert g.point[0] > 0 and g.regions == 2
    assert choose_goal(cl, p, command=np.array([-1.0, 0.0])).point[0] < 0


def test_planner_params_refuse_bad_values():
    with pytest.raises(ConfigError, match="kappa_max"):
        PlannerParams(kappa_max=0.0)
    with pytest.raises(ConfigError, match="unknown key"):
        PlannerParams.from_dict({"radius": 1.0})
    with pytest.raises(ConfigError, match="policy"):
        EpisodeParams(policy="magic")
    with pytest.raises(ConfigError, match="fork_child_deg"):
        EpisodeParams(fork_child_deg=-5.0)


# ----------------------------------------------------------------------------- control and graph


def test_reach_command_puts_the_free_space_tip_on_a_reachable_target():
    g = ScopeGeometry()
    q_true = np.array([-0.003, 0.7, 0.0])
    target = fk(q_true, geometry=g)[:3, 3]
    q = reach_command(target, lambda q3: pose_at(q3), np.array([0.0, 0.0, 0.0]), g, 0.0, 0.0, 0.0)
    assert np.linalg.norm(fk(q, geometry=g)[:3, 3] - target) < 1e-4
    assert abs(q[0]) <= g.q1_max


def test_path_command_puts_the_tip_where_the_path_crosses_its_reachable_dome():
    """Follow-the-leader tip control: a straight path from the base's side through a reachable tip point; the
    command's constant-curvature tip lies on the path (residual and fk distance < 0.3 mm)."""
    g = ScopeGeometry()
    tip = fk(np.array([-0.003, 0.7, 0.0]), geometry=g)[:3, 3]
    d = np.array([0.3, -0.2, 1.0]) / np.linalg.norm([0.3, -0.2, 1.0])
    path = tip + np.arange(-0.01, 0.03, 2.5e-4)[:, None] * d
    q, resid = path_command(path, lambda q3: pose_at(q3), np.zeros(3), g, 0.0, 0.0, 0.0)
    p = fk(q, geometry=g)[:3, 3]
    off = np.linalg.norm(np.cross(p - tip, d))
    assert resid < 3e-4 and off < 3e-4 and abs(q[0]) <= g.q1_max


def test_airways_distance_and_tip_control_choice():
    a = Airways(two_branch_graph())
    assert a.distance(np.array([0.002, 0.0, 0.05])) == pytest.approx(0.002)
    with pytest.raises(ConfigError, match="tip_control"):
        EpisodeParams(tip_control="wiggle")
    with pytest.raises(ConfigError, match="retract_force_n"):
        EpisodeParams(retract_force_n=-1.0)


def test_forward_trace_ignores_a_sideways_sweep_of_the_tip():
    """A roll of the bent tip sweeps it sideways: with its view direction the shaft's path does not grow."""
    tr, plain = Trace(pose_at(0.0)), Trace(pose_at(0.0))
    z = np.array([0.0, 0.0, 1.0])
    for k in range(1, 11):                                  # 10 mm sideways, 1 mm steps
        tr.extend(np.array([0.0, k * 1e-3, 0.0]), z)
        plain.extend(np.array([0.0, k * 1e-3, 0.0]))
    assert tr.s_end == pytest.approx(0.2) and plain.s_end > 0.208          # the plain trace grows by the sweep
    tr.extend(np.array([0.0, 0.01, 0.005]), z)              # 5 mm ahead: counted as 5 mm
    assert tr.s_end == pytest.approx(0.205)
    assert np.allclose(tr.route.frame(0.205)[:3, 3], [0.0, 0.01, 0.005])


def test_aim_command_turns_the_view_to_a_world_point_and_holds_the_bend_for_a_fixed_one():
    """tip_control aim: the commanded arc's end tangent points from the tip to the target (in the base frame);
    the bend depends on the target's direction from the tip, not on the current view (no pursuit)."""
    g = ScopeGeometry()
    base = lambda q3: pose_at(q3)                                   # noqa: E731
    tip = np.array([0.0, 0.0, g.l])
    target = tip + 0.02 * np.array([math.sin(0.4), 0.0, math.cos(0.4)])
    q = aim_command(target, tip, base, np.zeros(3), g, 0.0, 0.0, 0.0)
    view = fk(q, geometry=g)[:3, 2]
    assert np.degrees(math.acos(np.clip(view @ (target - tip) / 0.02, -1, 1))) < 0.01
    q_bent = aim_command(target, tip, base, np.array([-0.004, 1.0, 0.0]), g, 0.0, 0.0, 0.0)
    assert q_bent[0] == pytest.approx(q[0]) and abs(q[0]) <= g.q1_max
    with pytest.raises(ConfigError, match="shaft"):
        EpisodeParams(shaft="rope")
    with pytest.raises(ConfigError, match="depth_target"):
        EpisodeParams(depth_target="moon")
    with pytest.raises(ConfigError, match="single_opening"):
        PlannerParams(single_opening="both")


def test_free_centre_points_back_to_the_lumen_axis_from_an_off_axis_camera():
    """depth_target free_centre: in a 12 mm tube, the free lumen's centre 10 mm ahead is on the axis seen from
    an axial camera, and on the axis's side (within 2 mm of it; the free cross-section seen from off-axis
    weighs its far side more) from a camera 2-2.5 mm off it."""
    mesh, _ = tube(radius=0.006, straight=0.12)
    for off in (0.0, 0.002, -0.0025):
        P = pose_at(0.02)
        P[0, 3] = off
        d, cam = render_depth(mesh, P)
        cl = back_project(d, cam, 1)
        c = free_centre(cl, PlannerParams(), choose_goal(cl, PlannerParams()).point, 0.01)
        assert abs(c[2] - 0.01) < 1.5e-3 and abs(c[1]) < 1e-4
        assert abs(c[0] + off) < (1e-4 if off == 0 else 2e-3) and (off == 0 or np.sign(c[0]) == -np.sign(off))


def test_lumen_axis_target_pulls_an_off_axis_camera_back_to_the_axis():
    """depth_target axis: in a 12 mm tube the free cross-sections' centres lie on the tube's axis (within 0.3 mm, 64 px)
    seen from an axial camera and from cameras up to 3.5 mm off it; the target 4 mm along the axis from the
    camera's foot (its first centre: nearer ones are cut by the field of view) is on the axis; a depth map without any hit (all 0) gives no axis."""
    mesh, _ = tube(radius=0.006, straight=0.12)
    for off in (0.0, 0.002, -0.0025, 0.0035):
        P = pose_at(0.02)
        P[0, 3] = off
        d, cam = render_depth(mesh, P)
        ax = lumen_axis(d, cam)
        assert ax.split_m is None and ax.usable.sum() >= 5
        assert np.abs(ax.centres[ax.usable][:, 0] + off).max() < 3e-4          # 64 px: a pixel is ~0.2 mm here
        p, t = axis_target(ax, 0.004)
        z0 = ax.centres[ax.usable][0, 2]                  # the camera is behind the axis's first centre
        assert abs(p[0] + off) < 3e-4 and abs(p[1]) < 3e-4 and abs(p[2] - z0 - 0.004) < 3e-4 and t[2] > 0.99
    assert lumen_axis(np.zeros((64, 64)), cam) is None


def test_lumen_axis_takes_the_commanded_child_at_a_fork():
    """Near the Y fork (trunk 12 mm, children 9 mm at +-35 deg in x) the cross-sections split: the command picks
    the child on its side (left = -x in this camera) and the target turns toward it, unless a held point of the
    other child (``prefer``, the closed loop's memory of its choice) is given; far from the fork (30 mm) no command
    moves the target off the trunk's axis."""
    mesh, _ = y_airway()
    for z, sideways in ((0.07, False), (0.1, True)):
        d, cam = render_depth(mesh, pose_at(z))
        xs = []
        for cmd in ((-1.0, 0.0), (1.0, 0.0)):
            ax = lumen_axis(d, cam, cmd)
            xs.append(axis_target(ax, 0.004)[0][0])
        if sideways:
            assert ax.split_m is not None and xs[0] < -1e-3 and xs[1] > 1e-3
            held = lumen_axis(d, cam, (-1.0, 0.0), prefer=np.array([0.008, 0.0, 0.012]))   # a point in the +x child
            assert axis_target(held, 0.004)[0][0] > 1e-3                                   # beats the command
        else:
            assert np.abs(xs).max() < 1e-4


def test_tube_clearance_and_wall_ahead_from_one_depth_map():
    """Logged per step (closed loop): the straight segment from the camera to a point 30 mm down a 12 mm tube's axis
    keeps ~6 mm from the observed wall (the nearest wall the camera sees; 64 px); to a point as far off to the side
    (4 mm) it keeps ~2 mm; to a point beyond the tube's end cap (planar depth 0.1 m) it passes behind the observed
    surface: negative, by how far. Looking at the end cap 10 mm ahead, the wall ahead (within the scope radius of
    the view axis) is at 10 mm; down the open tube none within 2.5 mm of the axis is nearer than the cap."""
    from scipy.spatial import cKDTree

    mesh, _ = tube(radius=0.006, straight=0.12)
    d, cam = render_depth(mesh, pose_at(0.02))
    cloud = back_project(d, cam, 1)
    tree = cKDTree(cloud.points)
    centre = tube_clearance(np.array([0.0, 0.0, 0.03]), d, cam, tree)
    side = tube_clearance(np.array([0.004, 0.0, 0.03]), d, cam, tree)
    through = tube_clearance(np.array([0.0, 0.0, 0.11]), d, cam, tree)
    assert 5e-3 < centre < 6.2e-3 and 1.5e-3 < side < 2.5e-3 and centre > side
    assert -0.015 < through < -0.005                          # the cap is 100 mm ahead: 10 mm behind it
    assert wall_ahead(cloud.points, 0.0025) == pytest.approx(0.1, abs=1e-3)
    d2, cam2 = render_depth(mesh, pose_at(0.11))
    assert wall_ahead(back_project(d2, cam2, 1).points, 0.0025) == pytest.approx(0.01, abs=5e-4)


def test_a_point_held_before_the_fork_no_longer_picks_its_child():
    """fork_child_mm > 0 (hold_tol_m): a point held at an earlier fork that now lies before this fork's split (in
    the parent lumen, here 5 mm ahead on the +x side of the trunk) no longer picks the child: the command does
    (left = -x); without the check (the old rule) the stale point picks the +x child against the command. The
    axis reports what chose (pick_by)."""
    mesh, _ = y_airway()
    d, cam = render_depth(mesh, pose_at(0.1))
    stale = np.array([0.003, 0.0, 0.005])
    old = lumen_axis(d, cam, (-1.0, 0.0), prefer=stale)
    new = lumen_axis(d, cam, (-1.0, 0.0), prefer=stale, hold_tol_m=1e-3)
    assert old.split_m is not None and old.split_m > stale[2] + 1e-3
    assert old.pick_by == "held" and axis_target(old, 0.004)[0][0] > 1e-3
    assert new.pick_by == "command" and axis_target(new, 0.004)[0][0] < -1e-3
    beyond = lumen_axis(d, cam, (-1.0, 0.0), prefer=np.array([0.008, 0.0, 0.012]), hold_tol_m=1e-3)
    assert beyond.pick_by == "held" and axis_target(beyond, 0.004)[0][0] > 1e-3      # a point in the child still holds


def test_sideways_target_frees_the_held_roll():
    """Point control near zero bending holds the roll: a target 90 deg off the held bending plane is bent toward
    in that plane's nearer half (the wrong plane); with sideways_rad the roll turns to the target's plane."""
    g = ScopeGeometry()
    tip = fk(np.array([-0.0004, math.pi / 2, 0.0]), geometry=g)[:3, 3]
    held = reach_command(tip, lambda q3: pose_at(q3), np.zeros(3), g, 0.0, 0.05, 0.15)
    free = reach_command(tip, lambda q3: pose_at(q3), np.zeros(3), g, 0.0, 0.05, 0.15, sideways_rad=math.radians(45))
    assert held[1] == 0.0
    assert free[1] == pytest.approx(math.pi / 2, abs=1e-3)
    assert np.linalg.norm(fk(free, geometry=g)[:3, 3] - tip) < 1e-4 < np.linalg.norm(fk(held, geometry=g)[:3, 3] - tip)


def test_lumen_shaft_follows_the_centreline_and_a_branch_change_keeps_the_base():
    """shaft lumen: the base rides on the (smoothed) centreline root -> the tip's branch; entering a child moves
    nothing that lies more than the smoothing's reach before the fork (the base is l = 50 mm behind the tip)."""
    a = Airways(two_branch_graph())
    sh = LumenShaft(a, pose_at(0.06))
    # (the smoothing's 'nearest' end shortens the first ~4 sigma = 12 mm of arclength by ~1.2 mm)
    assert sh.s_end == pytest.approx(0.06, abs=1.5e-3) and sh.branch == 0
    before = sh.route.frame(0.06)
    assert np.allclose(before[:3, 3], [0.0, 0.0, 0.06], atol=1.5e-3) and np.allclose(before[:3, 2], [0, 0, 1], atol=1e-6)
    assert abs(before[0, 3]) < 1e-9 and abs(before[1, 3]) < 1e-9
    sh.extend(np.array([0.01, 0.0, 0.11]))                  # the tip in the right branch
    assert sh.branch == 2 and sh.s_end == pytest.approx(0.1 + 0.01 * math.sqrt(2), abs=2e-3)
    assert np.allclose(sh.route.frame(0.06), before, atol=1e-9)
    far = sh.route.frame(0.125)[:3, 3]                         # well into the branch: on its centreline
    assert abs(far[0] - (far[2] - 0.1)) < 1e-4 and far[0] > 0


def two_branch_graph():
    root = GraphBranch(0, -1, 0, np.array([[0, 0, z] for z in np.arange(0, 0.101, 0.001)]), np.full(101, 0.008))
    left = GraphBranch(1, 0, 1, np.array([[-x, 0, 0.1 + x] for x in np.arange(0, 0.031, 0.001)]), np.full(31, 0.005))
    right = GraphBranch(2, 0, 1, np.array([[x, 0, 0.1 + x] for x in np.arange(0, 0.031, 0.001)]), np.full(31, 0.005))
    return CentrelineGraph([root, left, right])


def test_unknown_or_root_target_is_an_input_error_and_commands_follow_the_image():
    g = two_branch_graph()
    with pytest.raises(InputError, match="not in the centreline graph"):
        check_target(g, 99)
    with pytest.raises(InputError, match="trachea"):
        check_target(g, 0)
    pose = start_pose(g, 0.06)
    assert np.allclose(pose[:3, 2], [0, 0, 1])
    cam = CameraIntrinsics.from_fov(64, 64, 85.0)
    a = Airways(g)
    right = operator_command(a, 2, 0, pose, cam)
    left = operator_command(a, 1, 0, pose, cam)
    assert {right, left} == {"left", "right"} and right != left
    # image right (camera x) is world -x here (looking along +z with image up = +y, anterior): branch 2 (+x)
    # is on the image's left
    assert pose[0, 0] == pytest.approx(-1.0) and right == "left"
    assert operator_command(a, 2, 2, pose, cam) is None


def _write_patient(root, mesh, graph):
    (root / "anatomy").mkdir(parents=True)
    write_obj(root / "anatomy" / "lung_model.obj", mesh)
    write_obj(root / "anatomy" / "collision_model.obj", mesh)
    (root / "anatomy" / "centreline_graph.json").write_text(json.dumps(graph.to_dict()))


def test_cli_unknown_target_is_one_error_line(tmp_path):
    mesh, C = tube(straight=0.16)
    root = GraphBranch(0, -1, 0, C[:101], np.full(101, 0.005))
    child = GraphBranch(1, 0, 1, C[100:], np.full(len(C) - 100, 0.005))
    _write_patient(tmp_path / "p", mesh, CentrelineGraph([root, child]))
    r = subprocess.run([sys.executable, "-m", "room_pipeline.cli", "navigate", "episode", "--output-dir", str(tmp_path),
                        "--patient", "p", "--target", "7"], capture_output=True, text=True)
    assert r.returncode == 2
    assert r.stderr.strip().splitlines() == [r.stderr.strip()] and r.stderr.startswith("room: error: ")
    assert "target branch 7" in r.stderr
    r = subprocess.run([sys.executable, "-m", "room_pipeline.cli", "navigate", "episode", "--output-dir", str(tmp_path),
                        "--patient", "nobody", "--target", "1"], capture_output=True, text=True)
    assert r.returncode == 2 and r.stderr.startswith("room: error: ") and "missing" in r.stderr


def test_cli_demo_refuses_a_folder_without_rendered_frames(tmp_path):
    r = subprocess.run([sys.executable, "-m", "room_pipeline.cli", "navigate", "demo", str(tmp_path), "--frames", "0",
                        "--out", str(tmp_path / "navigation_demo")],
                       capture_output=True, text=True)
    assert r.returncode == 2 and r.stderr.startswith("room: error: ") and len(r.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "navigation_demo").exists()


# ----------------------------------------------------------------------------- episodes


def y_airway(r0=0.006, r1=0.0045, trunk=0.10, child=0.06, angle_deg=35.0, h=0.0007, r2=None, angle2_deg=None,
             flare=0.0):
    """A closed Y-shaped lumen (marching cubes of the union of three capsules: trunk along +z, two children
    -angle_deg / +angle2_deg in the x-z plane, radii r1 / r2; both angle_deg and r1 by default) and its
    centreline graph (root 0, children 1 (-x) and 2 (+x)); ``flare`` > 0: the trunk's last 25 mm widen toward
    +x (a fourth capsule, shifted ``flare`` that way: a fork's flare toward child 2); metres."""
    from skimage.measure import marching_cubes

    a, a2 = math.radians(angle_deg), math.radians(angle_deg if angle2_deg is None else angle2_deg)
    radii = (r1, r1 if r2 is None else r2)
    top = np.array([0.0, 0.0, trunk])
    ends = [top + child * np.array([-math.sin(a), 0.0, math.cos(a)]), top + child * np.array([math.sin(a2), 0.0, math.cos(a2)])]
    segs = [(np.array([0.0, 0.0, -0.01]), top, r0)] + [(top, e, r) for e, r in zip(ends, radii)]
    if flare > 0:
        segs.append((np.array([0.0, 0.0, trunk - 0.025]), top + [flare, 0.0, 0.0], r0))
    lo = np.array([-child * math.sin(a) - 0.01, -0.01, 0.0])
    hi = np.array([child * math.sin(a2) + 0.01, 0.01, trunk + child * max(math.cos(a), math.cos(a2)) + 0.008])
    X = np.stack(np.meshgrid(*[np.arange(lo[k], hi[k] + h, h) for k in range(3)], indexing="ij"), axis=-1)
    sdf = np.full(X.shape[:3], np.inf)
    for p0, p1, r in segs:
        d = p1 - p0
        t = np.clip(((X - p0) @ d) / (d @ d), 0.0, 1.0)
        sdf = np.minimum(sdf, np.linalg.norm(X - (p0 + t[..., None] * d), axis=-1) - r)
    sdf[:, :, 0] = np.abs(sdf[:, :, 0]) + h                   # closed at the bottom
    v, f, _, _ = marching_cubes(np.pad(sdf, 1, constant_values=h).astype(np.float32), 0.0, spacing=(h, h, h))
    mesh = Mesh(v + lo - h, f[:, ::-1].copy())
    s = np.arange(0.0, trunk + 1e-9, 1e-3)
    branches = [GraphBranch(0, -1, 0, np.stack([0 * s, 0 * s, s], 1), np.full(len(s), r0))]
    for i, e in enumerate(ends):
        u = np.linspace(0, 1, int(round(child / 1e-3)) + 1)[:, None]
        branches.append(GraphBranch(i + 1, 0, 1, top + u * (e - top), np.full(len(u), radii[i])))
    return mesh, CentrelineGraph(branches)


@pytest.mark.slow
@pytest.mark.parametrize("policy,target", [pytest.param("oracle", 1, marks=pytest.mark.exhaustive),
                                           pytest.param("oracle", 2, marks=pytest.mark.exhaustive),
                                           ("depth", 1), pytest.param("depth", 2, marks=pytest.mark.exhaustive)])
def test_episode_through_a_bifurcation_reaches_the_commanded_child_without_contact_over_half_a_newton(policy, target):
    """The bifurcation case: a 12 mm trachea forking at +-35 deg into 9 mm children (the scope is 5 mm); the
    operator's word picks the child; the config's defaults (shaft lumen) reach it with no contact over 0.5 N."""
    mesh, graph = y_airway()
    pat = Patient("y", mesh, mesh, graph)
    res = run_episode(pat, target, EpisodeParams(policy=policy, max_time_s=40.0), PlannerParams(), SimParams())
    assert res["outcome"] == "reached", res["outcome"]
    assert res["peak_contact_force_n"] <= 0.5 and res["min_wall_clearance_mm"] > -0.2
    assert res["generation_reached"] == 1


@pytest.mark.slow
@pytest.mark.parametrize("fork_child_mm", [40.0, pytest.param(0.0, marks=pytest.mark.exhaustive)])
def test_episode_into_the_commanded_child_against_the_fork_flare(fork_child_mm):
    """The fork's flare: the trunk's last 25 mm widen 4 mm toward the +x child, so its cross-sections' centres lean
    that way; commanded left, the GT-depth policy enters the -x child at <= 0.5 N, with the default (fork_child_mm
    40: the child's centre is the target once the commanded fork is seen; the log shows it held) and with session
    11's rule (0). Measured at session 12's 5 ms physics step: both reach (17-20 s); the phantom's failures this
    fixed (benchmarks/results/navigation.md) did not reproduce on this synthetic fork. Passes at 2.5 ms (session 14)."""
    mesh, graph = y_airway(flare=0.004)
    pat = Patient("y_flare", mesh, mesh, graph)
    res = run_episode(pat, 1, EpisodeParams(max_time_s=40.0, fork_child_mm=fork_child_mm), PlannerParams(), SimParams())
    assert res["outcome"] == "reached", res["outcome"]
    assert res["peak_contact_force_n"] <= 0.5 and res["generation_reached"] == 1
    picks = [s["axis_openings"]["by"] for s in res["log"] if s.get("axis_openings")]
    assert "command" in picks and (fork_child_mm == 0 or "held" in picks)


def curved_fork(r0=0.006, r1=0.004, r2=0.0031, trunk=0.09, bend_r=0.04, bend_deg=35.0, child=0.04, child_deg=20.0,
                h=0.0007):
    """A closed lumen like the phantom's generation-3 branches (marching cubes of capsules): a straight trunk
    (radius ``r0``, along +z) into a branch of radius ``r1`` curving toward +x on a circle of ``bend_r`` by
    ``bend_deg``, forking at its end into two children of radius ``r2``, +-``child_deg`` from the branch's end
    tangent (child 3 toward the curve's inside, child 2 outside); and its centreline graph (root 0, branch 1,
    children 2, 3); metres."""
    from skimage.measure import marching_cubes

    s = np.arange(0.0, trunk + 1e-9, 1e-3)
    P0 = np.stack([0 * s, 0 * s, s], 1)
    a = np.radians(np.arange(0.0, bend_deg + 1e-9, 1.0))
    P1 = np.stack([bend_r * (1 - np.cos(a)), 0 * a, trunk + bend_r * np.sin(a)], 1)
    tang = np.array([math.sin(a[-1]), 0.0, math.cos(a[-1])])
    inward = np.array([math.cos(a[-1]), 0.0, -math.sin(a[-1])])
    u = np.linspace(0, child, int(round(child / 1e-3)) + 1)[:, None]
    c = math.radians(child_deg)
    kids = [P1[-1] + u * (math.cos(c) * tang + sgn * math.sin(c) * inward) for sgn in (-1, 1)]
    segs = [(P0[0] - [0, 0, 0.01], P0[-1], r0)]
    segs += [(P1[i], P1[i + 1], r1 + (r0 - r1) * max(0.0, 1 - i / 6)) for i in range(len(P1) - 1)]
    segs += [(k[0], k[-1], r2) for k in kids]
    pts = np.vstack([P0, P1] + kids)
    lo, hi = pts.min(0) - 0.01, pts.max(0) + 0.01
    lo[2] = 0.0
    X = np.stack(np.meshgrid(*[np.arange(lo[k], hi[k] + h, h) for k in range(3)], indexing="ij"), axis=-1)
    sdf = np.full(X.shape[:3], np.inf)
    for p0, p1, r in segs:
        d = p1 - p0
        t = np.clip(((X - p0) @ d) / (d @ d), 0.0, 1.0)
        sdf = np.minimum(sdf, np.linalg.norm(X - (p0 + t[..., None] * d), axis=-1) - r)
    sdf[:, :, 0] = np.abs(sdf[:, :, 0]) + h                   # closed at the bottom
    v, f, _, _ = marching_cubes(np.pad(sdf, 1, constant_values=h).astype(np.float32), 0.0, spacing=(h, h, h))
    mesh = Mesh(v + lo - h, f[:, ::-1].copy())
    branches = [GraphBranch(0, -1, 0, P0, np.full(len(P0), r0)), GraphBranch(1, 0, 1, P1, np.full(len(P1), r1))]
    branches += [GraphBranch(2 + i, 1, 2, k, np.full(len(k), r2)) for i, k in enumerate(kids)]
    return mesh, CentrelineGraph(branches)


@pytest.mark.slow
def test_episode_through_a_curving_branch_to_the_child_seen_far_aside():
    """``fork_child_deg`` (off by default): a 4 mm branch curving 35 deg, whose fork into 3.1 mm children (the scope
    is 2.5 mm in radius) shows up to the side as the tip enters the curve; with 25 deg the held child's centre is
    not steered for while it is more than 25 deg off the view and more than 15 mm deep (the log says so:
    child_gated), the axis target takes the tip through the curve, and the GT-depth policy enters the inner child
    with no contact over 0.5 N. Measured at the 5 ms step: reached in 21.7 s at 0.045 N (the default rule: 21.9 s,
    0.047 N; this synthetic branch does not reproduce the phantom's tunnelling, benchmarks/results/
    navigation_failures.md). Passes at 2.5 ms (session 14's default)."""
    mesh, graph = curved_fork()
    pat = Patient("curve", mesh, mesh, graph)
    res = run_episode(pat, 3, EpisodeParams(max_time_s=40.0, fork_child_deg=25.0), PlannerParams(), SimParams())
    assert res["outcome"] == "reached", res["outcome"]
    assert res["peak_contact_force_n"] <= 0.5 and res["generation_reached"] == 2
    gated = [s for s in res["log"] if s.get("child_gated")]
    assert gated and all(s["child_deg"] > 25.0 for s in gated)
    steps = [s for s in res["log"] if "force_max_n" in s]
    assert len(steps) == len(res["log"]) and max(s["force_max_n"] for s in steps) == pytest.approx(
        res["peak_contact_force_n"], abs=1e-5)                      # the log's per-period peaks (rounded to 1e-5 N)


@pytest.mark.slow
@pytest.mark.parametrize("policy", ["depth", pytest.param("oracle", marks=pytest.mark.exhaustive)])
def test_episode_in_a_straight_tube_reaches_the_target_without_contact_over_half_a_newton(policy):
    """The issue's bound: no contact over 0.5 N. At the simulate default of this round (mass x10, 5 ms) the
    ground-truth-depth policy grazes the 6 mm tube's wall (min clearance -0.011 mm, i.e. 11 um of soft-contact
    penetration) on its way; a penetration past 0.1 mm would mean a real push into the wall. Passes at the closed
    loop's 2.5 ms step (session 14's default)."""
    mesh, C = tube(radius=0.006, straight=0.18)
    root = GraphBranch(0, -1, 0, C[:111], np.full(111, 0.006))
    child = GraphBranch(1, 0, 1, C[110:], np.full(len(C) - 110, 0.006))
    pat = Patient("tube", mesh, mesh, CentrelineGraph([root, child]))
    res = run_episode(pat, 1, EpisodeParams(policy=policy, max_time_s=30.0), PlannerParams(), SimParams())
    assert res["outcome"] == "reached", res["outcome"]
    assert res["peak_contact_force_n"] <= 0.5
    assert res["min_wall_clearance_mm"] > -0.1
    assert res["generation_reached"] == 1
    again = run_episode(pat, 1, EpisodeParams(policy=policy, max_time_s=30.0), PlannerParams(), SimParams())
    assert again["time_s"] == res["time_s"] and again["path_length_mm"] == res["path_length_mm"]


def test_diagnose_finds_the_fork_and_classes_a_wrong_branch_episode():
    """navigation/diagnose.py (benchmarks/navigation.py --trace): on a Y graph (trunk 0 along +z to 100 mm, children
    1 (-x) and 2 (+x) at +-35 deg), an episode toward child 1 whose tip ends in child 2 left the route at the fork
    0 -> 1 / 2; the target on child 2's side over the last steps with a split seen is ``target_in_wrong_child``, on
    child 1's side ``late_turn``; no split seen at all is ``no_fork_seen``; an episode that stays on the route has
    no fork."""
    from room_pipeline.navigation import diagnose

    s = np.arange(0.0, 0.1001, 1e-3)
    top, a = np.array([0.0, 0.0, 0.1]), math.radians(35)
    u = np.linspace(0, 1, 61)[:, None]
    kids = [GraphBranch(i + 1, 0, 1, top + u * 0.06 * np.array([sx * math.sin(a), 0.0, math.cos(a)]), np.full(61, 0.0045))
            for i, sx in enumerate((-1.0, 1.0))]
    air = Airways(CentrelineGraph([GraphBranch(0, -1, 0, np.stack([0 * s, 0 * s, s], 1), np.full(len(s), 0.006))] + kids))

    def log(target_x, split=20.0):
        out = []
        for k, z in enumerate(np.arange(60.0, 112.0, 1.0)):
            tip = [0.0, 0.0, z] if z <= 100 else [(z - 100) * math.tan(a), 0.0, z]     # into child 2 (+x)
            out.append({"t": k * 0.1, "branch": air.locate(np.array(tip) * 1e-3)[0], "command": "left",
                        "axis_split_mm": split, "tip_mm": tip, "target_mm": [target_x, 0.0, z + 8], "force_n": 0.0})
        return out

    wrong = diagnose.trace(air, 1, log(3.0))
    assert (wrong["parent"], wrong["right"], wrong["wrong"]) == (0, 1, 2) and wrong["class"] == "target_in_wrong_child"
    assert diagnose.trace(air, 1, log(-3.0))["class"] == "late_turn"
    assert diagnose.trace(air, 1, log(3.0, split=None))["class"] == "no_fork_seen"
    assert diagnose.trace(air, 2, log(3.0)) is None
