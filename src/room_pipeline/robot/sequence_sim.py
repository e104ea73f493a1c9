"""Simulating one sequence: the simulate stage's inputs read and checked, the entrance opened, the records.

Modelling choice: the airway is open proximally.  The lumen mesh is closed at
its top (the trachea entry of the phantom or the volume border of a CT), but a
real airway continues to the larynx, and the scope's bending segment (50 mm)
reaches above the first pose.  Triangles behind the plane of the first pose
and within three root radii of the path axis are left out of the collision
mesh (:func:`open_entrance`); the count is recorded.

The simulator's report keeps machine-dependent entries (wall time, real-time
factor, mesh build time) out of the data files (:func:`data_report`); they go
to the metrics (:func:`sim_metrics`).
"""
from __future__ import annotations

import numpy as np

from ..errors import InputError
from ..io.jsondoc import read_json
from ..io.mesh import Mesh
from ..io.records import pose_track

#: report entries that depend on the machine, kept out of the data files (they go to metrics)
TIMING_KEYS = ("wall_time_s", "realtime_factor")


def open_entrance(mesh: Mesh, start: np.ndarray, tangent: np.ndarray, radius: float) -> tuple[Mesh, int]:
    """Drop the triangles proximal to the start plane near the path axis (see module docstring)."""
    c = mesh.vertices[mesh.faces].mean(axis=1)
    rel = c - start
    along = rel @ tangent
    off_axis = np.linalg.norm(rel - along[:, None] * tangent, axis=1)
    drop = (along < 0) & (off_axis < 3.0 * radius)
    return Mesh(mesh.vertices, mesh.faces[~drop]), int(drop.sum())


def read_inputs(trajectory_json, graph_json, key: str):
    """The planned trajectory (timestamps, poses, arclength) and the root branch's radius; a missing or
    malformed file is one :class:`InputError` line naming it."""
    path = trajectory_json
    try:
        traj = pose_track(path, read_json(path))
        if traj.arclength is None:
            raise ValueError("frames without 'arclength'")
        path = graph_json
        graph = read_json(path)
        root_radius = float(next(b for b in graph["branches"] if b["parent"] == -1)["mean_radius"])
    except StopIteration:
        raise InputError(f"simulate {key}: {path} has no root branch (parent -1)") from None
    except (OSError, ValueError, KeyError, TypeError, IndexError, InputError) as exc:
        raise InputError(f"simulate {key}: cannot read {path} ({type(exc).__name__}: "
                         f"{' '.join(str(exc).split())})") from None
    if not (np.isfinite(root_radius) and root_radius > 0):
        raise InputError(f"simulate {key}: {graph_json}: root branch radius must be > 0, got {root_radius}")
    return traj, root_radius


def data_report(report: dict, n_dropped: int) -> dict:
    """The simulator's report for ``simulation.json``: without timings, with the entrance faces removed."""
    out = {k: v for k, v in report.items() if k not in TIMING_KEYS}
    if isinstance(out.get("mesh"), dict):
        out["mesh"] = {k: v for k, v in out["mesh"].items() if k != "build_time_s"}
    out["entrance_faces_removed"] = n_dropped
    out["unstable_runs"] = [{k: v for k, v in u.items() if k not in TIMING_KEYS} for u in out["unstable_runs"]]
    return out


def sim_metrics(n_frames: int, r: dict) -> dict:
    """The DVC metrics of a simulation report ``r`` (tracking, view error, roll, contact, stability, speed)."""
    return {"frames": int(n_frames),
            "tracking_error_median_mm": round(r["tracking_error_mm"]["median"], 4),
            "tracking_error_max_mm": round(r["tracking_error_mm"]["max"], 4),
            "view_error_median_deg": round(r["tracking_error_deg"]["median"], 4),
            "view_error_max_deg": round(r["tracking_error_deg"]["max"], 4),
            "camera_roll_straight_stretch_max_deg": round(r["camera_roll_deg"]["straight_stretch_change_max"], 4),
            "contact_force_max_n": round(r["contact_force_n"]["max"], 6),
            "penetration_max_mm": round(r["penetration_mm"]["max"], 6),
            "time_step_s": r["time_step_s"], "unstable_runs": len(r["unstable_runs"]),
            "realtime_factor": round(r["realtime_factor"], 3)}
