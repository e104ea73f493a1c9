"""The 3-D scene of one sequence: what is drawn (mesh, planned / simulated paths, cameras, scope backbones).

Why the scope's shape is reconstructed here: ``simulation.json`` records the tip pose and the joints per
frame, not the backbone, so :func:`scope_backbones` rebuilds it from the simulator's ``kinematic``
insertion model (route + ``q3``, then :func:`room_pipeline.robot.kinematics.fk`) and states, per drawn
frame, how far its tip lies from the simulated tip.  Once the simulation saves its backbone points (the
PyBullet body's vertices), this module should draw those instead.
"""
from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Mapping

import numpy as np

from ..catalog import RENDER_JSON, SIMULATION_JSON, TRAJECTORY_JSON, SequencePaths
from ..errors import InputError
from ..io.records import POSE_KEY, pose_track_from_doc
from .colour import pick_frames
from .common import read_json


@dataclasses.dataclass
class Scene3D:
    """What one 3-D view draws (world RAS+, metres); None / empty = absent."""

    mesh_vertices: np.ndarray | None = None
    mesh_faces: np.ndarray | None = None
    planned: np.ndarray | None = None          # (N, 3) planned camera positions
    simulated: np.ndarray | None = None        # (M, 3) simulated tip positions
    rendered: np.ndarray | None = None         # (K, 3) positions of the rendered cameras
    scopes: list = dataclasses.field(default_factory=list)   # (P, 3) backbone polylines
    tips: np.ndarray | None = None             # (S, 3) simulated tip positions at the scope frames
    scope_radius: float = 0.0025


def scope_backbones(trajectory: Mapping, simulation: Mapping, robot: Mapping, n_frames: int,
                    step_m: float = 1e-3) -> tuple[list[np.ndarray], np.ndarray, list[int], list[float]]:
    """Backbone polylines of the simulated scope at ``n_frames`` evenly spaced simulation frames.

    Reconstruction (the simulator's ``kinematic`` insertion model): the bending-segment base is
    the planned route's frame at arclength ``q3``, rolled by ``q2``; the shaft is the route from
    its start up to ``q3`` (sampled every ``step_m``); the bending segment is the constant-curvature
    arc of :func:`room_pipeline.robot.kinematics.fk` for ``q1``.  Joints are the recorded ``q_act``.

    Returns (polylines (P_i, 3) metres, simulated tip positions (S, 3), the frame indices, and per
    frame the distance (m) between the reconstructed tip and the simulated ``tip_pose``).
    Raises InputError when the inputs lack what the reconstruction needs.
    """
    from ..robot.kinematics import ScopeGeometry, fk
    from ..robot.route import Route

    if robot.get("insertion_model", "kinematic") != "kinematic":
        raise InputError(f"insertion model {robot.get('insertion_model')!r}: the shaft shape is not recorded "
                         "(only the kinematic model's shaft follows the planned route)")
    try:
        planned = pose_track_from_doc(trajectory, POSE_KEY[TRAJECTORY_JSON], TRAJECTORY_JSON)
        if planned.arclength is None:
            raise KeyError("arclength")
        k = robot.get("kinematics") or {}
        geometry = ScopeGeometry(l=float(k.get("bending_length", ScopeGeometry.l)),
                                 gamma=float(k.get("gamma", ScopeGeometry.gamma)),
                                 q1_max=float(k.get("q1_max", ScopeGeometry.q1_max)))
        sf = simulation["frames"]
        picks = pick_frames(len(sf), n_frames + 1)[1:] if n_frames > 0 and len(sf) > 1 else []
        picks = picks[-n_frames:] if n_frames else []
        qs = [np.asarray(sf[i]["q_act"], dtype=np.float64) for i in picks]
        tips = pose_track_from_doc(simulation, POSE_KEY[SIMULATION_JSON], SIMULATION_JSON).positions[picks]
    except (KeyError, TypeError, ValueError, IndexError, InputError) as exc:
        raise InputError(f"trajectory/simulation/robot_config lack what the scope drawing needs ({exc})") from None
    route = Route.from_trajectory(planned)
    lines, mismatch = [], []
    for q, tip in zip(qs, tips):
        s0 = float(route.s[0])
        shaft = [route.frame(s)[:3, 3] for s in np.arange(s0, q[2], step_m)] if q[2] > s0 else []
        base = route.frame(float(q[2]))
        c2, s2 = math.cos(q[1]), math.sin(q[1])
        base[:3, :3] = base[:3, :3] @ np.array([[c2, -s2, 0.0], [s2, c2, 0.0], [0.0, 0.0, 1.0]])
        ss = np.linspace(0.0, geometry.l, 25)
        arc = fk(np.array([q[0], 0.0, 0.0]), ss, geometry=geometry)
        bend = (base @ arc)[:, :3, 3]
        lines.append(np.vstack([np.reshape(shaft, (-1, 3)), bend]))
        mismatch.append(float(np.linalg.norm(bend[-1] - tip)))
    return lines, tips, picks, mismatch


def sequence_scene(seq: Path, mesh, scope_frames: int) -> tuple[Scene3D, list[str]]:
    """The 3-D scene of one sequence and the caption lines saying what is drawn (and what is not)."""
    sp = SequencePaths(seq)
    sc = Scene3D()
    notes = []
    if mesh is not None:
        sc.mesh_vertices, sc.mesh_faces = mesh.vertices, mesh.faces
    traj, why = read_json(sp.trajectory)
    try:
        if traj is not None:
            sc.planned = pose_track_from_doc(traj, POSE_KEY[TRAJECTORY_JSON], sp.trajectory).positions
    except (KeyError, TypeError, ValueError, IndexError, InputError):
        traj, why = None, "trajectory.json has no 4x4 frame poses"
    if sc.planned is None:
        notes.append(f"planned trajectory not drawn: {why}")
    sim, why_s = read_json(sp.simulation)
    try:
        if sim is not None:
            sc.simulated = pose_track_from_doc(sim, POSE_KEY[SIMULATION_JSON], sp.simulation).positions
    except (KeyError, TypeError, ValueError, IndexError, InputError):
        sim, why_s = None, "simulation.json has no tip poses"
    if sc.simulated is None:
        notes.append(f"simulated tip path not drawn: {why_s}")
    rend, _ = read_json(sp.render_json)
    if isinstance(rend, dict) and rend.get("frames"):
        try:
            sc.rendered = pose_track_from_doc(rend, POSE_KEY[RENDER_JSON], sp.render_json).positions
        except (KeyError, TypeError, ValueError, IndexError, InputError):
            notes.append("rendered cameras not drawn: render.json frames lack 4x4 poses")
    if scope_frames and traj is not None and sim is not None:
        robot, why_r = read_json(sp.robot_config)
        if robot is None:
            notes.append(f"scope not drawn: {why_r}")
        else:
            try:
                lines, tips, picks, mism = scope_backbones(traj, sim, robot, scope_frames)
                sc.scopes, sc.tips = lines, tips
                diam = (robot.get("scope") or {}).get("outer_diameter")
                if isinstance(diam, (int, float)) and diam > 0:
                    sc.scope_radius = 0.5 * float(diam)
                notes.append("scope (tube, outer diameter %.1f mm) at simulation frames %s; reconstructed "
                             "model tip vs simulated tip: %s mm" % (2e3 * sc.scope_radius,
                                                                   ", ".join(map(str, picks)),
                                                                   ", ".join(f"{1e3 * m:.2f}" for m in mism)))
            except InputError as exc:
                notes.append(f"scope not drawn: {exc}")
    elif scope_frames:
        notes.append("scope not drawn: it needs trajectory.json and simulation.json")
    return sc, notes
