"""The insertion stops where the plan cannot keep the scope off the wall (``trajectory.stop_at_wall``; on by default).

A real scope cannot put its tip (radius ``scope_diameter_mm / 2``) closer to the wall than its radius: the
wall is there.  A plan that asks for such a pose is not executable; the simulator then presses the scope
into the wall, and the recorded frames are the contact's, not the plan's (issue #17: in the default
sequences every frame where the planned camera is closer to the wall than the scope's radius is in contact).
The rule a robotics user expects: the insertion ends at the first planned frame where

* the **tip**: the planned camera centre's clearance ``-sdf`` (m) is below ``radius + stop_clearance_mm``, or
* the **body** (joint plan only): a backbone point of the bending segment (``joint_plan.body_points``, base to
  camera; only the part already on the planned path, at route arclength >= the first frame's, where the route
  itself is inside the lumen) has ``-sdf`` below ``radius + stop_clearance_mm``,

and every frame from there on is dropped.  The note (``trajectory.json`` -> ``insertion_stop``) says which
frame, why, the clearance there and the frames planned and kept.  With a joint plan the kept frames are
planned again on their own (the whole-sequence solve is pulled by its end, so the dropped frames must not
shape the kept ones) and checked again, until a plan passes.  No threshold depends on the anatomy: the
scope's radius and the configured clearance only.  Lengths in metres unless a name says ``_mm``.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from ..conventions import MM
from ..robot.kinematics import ScopeGeometry, fk
from .sdf_fn import SdfFn


def blocked(traj, fn: SdfFn, geometry: ScopeGeometry, radius: float, clearance: float,
            body_points: int) -> tuple[int | None, dict]:
    """First frame (index) where the tip or the body of ``traj`` is closer to the wall than
    ``radius + clearance`` (m), or None; and the note describing it (clearances in mm)."""
    need = radius + clearance
    tip = -np.asarray(fn(traj.poses[:, :3, 3]), float)
    T = len(tip)
    body = np.full(T, np.inf)
    if traj.joints is not None and traj.path_poses is not None:
        from ..robot.route import Route
        route = Route(traj.path_poses[:, :3, 3], traj.arclength, traj.path_poses[:, :3, :3])
        q = np.asarray(traj.joints, float)
        s_body = np.linspace(0.0, geometry.l, max(2, int(body_points)))
        F = route.frames(q[:, 2])
        L = fk(np.column_stack([q[:, 0], q[:, 1], np.zeros(T)])[:, None, :], s_body[None, :], geometry=geometry)
        P = np.einsum("kij,kbj->kbi", F[:, :3, :3], L[:, :, :3, 3]) + F[:, None, :3, 3]
        c = -np.asarray(fn(P.reshape(-1, 3)), float).reshape(T, -1)
        s_route = q[:, 2:3] + s_body[None, :]
        on_route = route.frames(s_route.ravel())[:, :3, 3]
        # only the part of the segment already on the planned path (not its straight extension behind the start,
        # outside the airway the planner knows) and where the route itself is in the lumen
        inside = (-np.asarray(fn(on_route), float) > 0.0).reshape(T, -1) & (s_route >= float(traj.arclength[0]))
        body = np.where(inside, c, np.inf).min(axis=1)
    bad_tip, bad_body = tip < need, body < need
    bad = bad_tip | bad_body
    if not bad.any():
        return None, {}
    k = int(np.argmax(bad))
    reason = "tip_clearance" if bad_tip[k] else "body_clearance"
    value = tip[k] if bad_tip[k] else body[k]
    return k, {"frame_index": k, "reason": reason, "clearance_mm": float(value / MM),
               "required_mm": float(need / MM), "scope_radius_mm": float(radius / MM),
               "stop_clearance_mm": float(clearance / MM), "frames_planned": T, "frames_kept": k,
               "arclength_mm": float(traj.arclength[k] / MM),
               "description": "the insertion ends before this frame: the plan's " + (
                   "camera centre" if reason == "tip_clearance" else "bending-segment backbone") +
               " is closer to the wall than the scope's radius + stop_clearance_mm (trajectory.stop_at_wall); "
               "frame_index, reason, clearance_mm and arclength_mm are the first plan's; frames_kept: after the kept "
               "frames were planned again (joint_replans) and checked again, at most frame_index"}


_PER_FRAME = ("timestamps", "poses", "arclength", "branch_id", "clearance", "curvature", "speed", "margin",
              "path_poses", "joints")


def truncate(traj, k: int):
    """The trajectory's first ``k`` frames (every per-frame array cut; the rest kept)."""
    out = dataclasses.replace(traj)
    for name in _PER_FRAME:
        v = getattr(traj, name)
        if v is not None:
            setattr(out, name, np.asarray(v)[:k].copy())
    return out
